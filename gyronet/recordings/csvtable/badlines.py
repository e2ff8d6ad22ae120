"""``bad_lines=drop``: leave out the data lines the loader would refuse one by one, counted by reason.

By default a malformed line refuses the whole file, naming the line (a file is never silently altered);
``python scripts/convert.py input=F.csv output=G.csv bad_lines=drop`` recovers the good samples instead. Each
line is judged as the loader judges it: its number of cells, a repeated header, a required cell that is not a
finite number, then a time out of order (the fewest such lines are left out). A left-out line is blanked, not
removed, so that the lines after it keep their numbers; the loader then reads the rest as usual.
"""
from __future__ import annotations

import bisect
import csv
import io
import logging
from pathlib import Path
from typing import Iterator, Sequence

import numpy as np

from gyronet.errors import RecordingError
from gyronet.recordings.csvtable.cells import parse_numbers
from gyronet.recordings.csvtable.text import field_limit, show

log = logging.getLogger(__name__)

REMEDY = "python scripts/convert.py input={path} output=NEW.csv bad_lines=drop leaves out such lines, counted"
SHOWN = 5  # left-out lines named in the warning


def bad_line(path: Path | str, message: str) -> RecordingError:
    """A refusal for one malformed line, pointing to the remedy that keeps the rest of the file."""
    return RecordingError(f"{path}: {message}; {REMEDY.format(path=path)}")


def _records(text: str, delimiter: str) -> Iterator[tuple[int, int, list[str]]]:
    """(index of its first line, of its last, its cells) of each line; with quotes, of each record as the loader
    reads it (``shape.scan_quoted``): a quoted cell may hold a line end."""
    if '"' not in text:
        for i, line in enumerate(text.split("\n")):
            yield i, i, line.split(delimiter)
        return
    reader = csv.reader(io.StringIO(text), delimiter=delimiter, strict=False)
    start = 0
    with field_limit(len(text)):
        try:
            for cells in reader:
                yield start, reader.line_num - 1, cells
                start = reader.line_num
        except csv.Error:
            return  # the loader refuses the file at this line, naming it


def _longest_increasing(values: np.ndarray) -> np.ndarray:
    """Indices of a longest strictly increasing subsequence of ``values`` (patience sorting, O(n log n))."""
    if len(values) < 2 or np.all(np.diff(values) > 0):
        return np.arange(len(values))
    tails: list[float] = []  # the smallest last value of an increasing run of each length
    tail_at: list[int] = []
    parent = np.full(len(values), -1)
    for i, value in enumerate(values.tolist()):
        k = bisect.bisect_left(tails, value)
        if k < len(tails) and tails[k] == value:
            continue  # a repeated time: the earlier row stays
        tails[k:k + 1], tail_at[k:k + 1] = [value], [i]
        parent[i] = tail_at[k - 1] if k else -1
    chain, i = [], tail_at[-1]
    while i >= 0:
        chain.append(i)
        i = parent[i]
    return np.array(chain[::-1], dtype=int)


def drop_bad_lines(path: Path, body: bytes, names: list[str], required: Sequence[str], delimiter: str,
                   decimal: str, first_line: int) -> tuple[bytes, dict[str, int]]:
    """``body`` (the bytes under the header, ``\\n`` line ends) with every malformed line blanked, and how many
    were left out by reason; one warning names the first ``SHOWN`` of them.

    ``first_line`` is the file line number of the body's first line.
    """
    raw_lines = body.split(b"\n")  # an undecodable byte never becomes a newline: the two splits agree
    why: dict[int, tuple[str, str]] = {}  # first line index -> (reason key, what the warning says)
    last_of: dict[int, int] = {}  # first line index -> last line index of a record
    candidates, rows = [], []
    n = len(names)
    for i, last, cells in _records(body.decode("utf-8", "replace"), delimiter):
        if not cells or (len(cells) == 1 and not cells[0].strip(" \t")):
            continue
        last_of[i] = last
        if last == len(raw_lines) - 1 and (len(cells) < n or (len(cells) == n and not cells[-1].strip(" \t"))):
            continue  # an unterminated last line cut short: the loader drops it as such (cut_rows), as by default
        if len(cells) != n and (len(cells) < n or any(c.strip(" \t") for c in cells[n:])):
            why[i] = ("cell_count", f"{len(cells)} cells where the header names {n} columns")
        elif cells[0].strip(" \t") == names[0] and [c.strip(" \t") for c in cells[:n]] == names:
            why[i] = ("repeated_header", "repeats the header")
        else:
            candidates.append(i)
            rows.append(cells)
    usable = np.ones(len(rows), dtype=bool)
    time_s = np.zeros(len(rows))
    for column, name in enumerate(names):
        if name not in required:
            continue
        values, wrong = parse_numbers([r[column] for r in rows], decimal)
        for k in np.flatnonzero(usable & (wrong | ~np.isfinite(values))):
            cell = rows[k][column].strip(" \t")
            key, what = (("non_numeric", f"non-numeric value {show(cell, 40)}") if wrong[k] else
                         ("missing_value", "missing value") if np.isnan(values[k]) else ("infinite", "infinite value"))
            why[candidates[k]] = (key, f"column {name!r}: {what}")
        usable &= ~wrong & np.isfinite(values)
        if name == "time_s":
            time_s = values
    # the fewest rows left out to put time in order: one stamp corrupted far ahead costs itself, not every row after
    kept = np.flatnonzero(usable)
    in_order = np.zeros(len(kept), dtype=bool)
    in_order[_longest_increasing(time_s[kept])] = True
    for j in np.flatnonzero(~in_order):
        why[candidates[kept[j]]] = ("time_not_increasing", f"time_s {float(time_s[kept[j]])!r} is out of order "
                                    "with the rows around it")
    if not why:
        return body, {}
    counts: dict[str, int] = {}
    for i in sorted(why):
        counts[why[i][0]] = counts.get(why[i][0], 0) + 1
        raw_lines[i:last_of[i] + 1] = [b""] * (last_of[i] + 1 - i)
    named = "; ".join(f"line {first_line + i}: {why[i][1]}" for i in sorted(why)[:SHOWN])
    log.warning("%s: bad_lines=drop: %d malformed line(s) left out (%s): %s%s", path, len(why),
                ";".join(f"{k}:{v}" for k, v in counts.items()), named, "; ..." if len(why) > SHOWN else "")
    return b"\n".join(raw_lines), counts
