"""The shape of a recording's body: cells per line, counted before any number is parsed.

Unquoted text is scanned with numpy (newlines and delimiters by position), quoted text with the csv
module. A line with missing or extra cells is refused by line number instead of being shifted or
padded by pandas; empty trailing cells (trailing commas) and a last line cut by a stopped logger are
the only irregularities let through.
"""
from __future__ import annotations

import csv
import io
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from gyronet.recordings.csvtable.badlines import bad_line
from gyronet.recordings.csvtable.text import MAX_COLUMNS, field_limit
from gyronet.errors import RecordingError

log = logging.getLogger(__name__)


@dataclass
class _Lines:
    """The body's non-blank lines: their cell counts and file line numbers, and a way to split one."""

    cells: np.ndarray
    numbers: np.ndarray
    terminated: bool  # the last one ends with a newline
    cells_of: Callable[[int], list[str]]
    blank: int = 0  # blank lines skipped
    extra_empty: np.ndarray | None = None  # per line: every cell beyond the header's is empty (quick test)


def scan_bytes(body: bytes, first_line: int, delimiter: str, n_names: int) -> tuple[_Lines, np.ndarray]:
    """Line and cell structure of an unquoted body, vectorised; also where each line ends."""
    data = np.frombuffer(body, dtype=np.uint8)
    newline = np.flatnonzero(data == 10)
    starts = np.concatenate([[0], newline + 1])
    ends = np.concatenate([newline, [len(data)]])
    if len(data) and data[-1] == 10:  # the "line" after the final newline
        starts, ends = starts[:-1], ends[:-1]
    seps = np.flatnonzero(data == ord(delimiter))
    first_sep = np.searchsorted(seps, starts)
    n_sep = np.searchsorted(seps, ends) - first_sep
    blank = np.zeros(len(starts), dtype=bool)
    maybe = np.flatnonzero(n_sep == 0)
    blank[maybe[ends[maybe] == starts[maybe]]] = True
    for i in maybe[ends[maybe] > starts[maybe]]:  # spaces only: pandas skips those too
        blank[i] = not body[starts[i]:ends[i]].strip(b" \t")
    keep = np.flatnonzero(~blank)
    starts, ends, n_sep, first_sep = starts[keep], ends[keep], n_sep[keep], first_sep[keep]
    extra_empty = np.zeros(len(keep), dtype=bool)
    long = np.flatnonzero(n_sep >= n_names)
    if long.size:
        # after the separator that ends the header's last column, only separators: empty cells
        last_sep = seps[first_sep[long] + n_names - 1]
        extra_empty[long] = ends[long] - last_sep - 1 == n_sep[long] - n_names

    def cells_of(i: int) -> list[str]:
        return body[starts[i]:ends[i]].decode("utf-8", "replace").split(delimiter)

    lines = _Lines(n_sep + 1, first_line + keep, bool(len(keep)) and ends[-1] < len(data), cells_of,
                   int(blank.sum()), extra_empty)
    return lines, ends


def scan_quoted(path: Path, text: str, first_line: int, delimiter: str) -> _Lines:
    """Line and cell structure of a body that uses quotes, with the csv module (slow, exact)."""
    rows, numbers, blank = [], [], 0
    reader = csv.reader(io.StringIO(text), delimiter=delimiter, strict=False)
    with field_limit(len(text)):
        try:
            for row in reader:
                if not row or (len(row) == 1 and not row[0].strip(" \t")):
                    blank += 1
                    continue
                rows.append(row)
                numbers.append(first_line + reader.line_num - 1)
        except csv.Error as err:
            raise RecordingError(f"{path}: line {first_line + reader.line_num - 1}: cannot split into cells "
                                 f"({err})") from None
    terminated = text.rstrip(" \t").endswith("\n") or not rows
    return _Lines(np.array([len(r) for r in rows], dtype=np.int64), np.array(numbers, dtype=np.int64),
                  terminated, rows.__getitem__, blank)


def check_shape(path: Path, lines: _Lines, n_names: int, header_trailing: int) -> tuple[np.ndarray, bool]:
    """Refuse a line with missing or extra cells; return the lines to read and whether any has empty
    cells beyond the header's (trailing commas: ignored). An unterminated last line that is short or
    ends in an empty cell is a write cut off: ignored, with a warning."""
    cells = lines.cells
    keep = np.ones(len(cells), dtype=bool)
    if len(cells) and not lines.terminated:
        last = lines.cells_of(len(cells) - 1)
        if len(last) < n_names or (len(last) == n_names and not last[-1].strip(" \t")):
            keep[-1] = False
            log.warning("%s: line %d is cut short (no newline at the end of the file, %d of %d cells): ignored",
                        path, lines.numbers[-1], len(last), n_names)
    wide = np.flatnonzero(cells > MAX_COLUMNS)
    if wide.size:
        raise bad_line(path, f"line {lines.numbers[wide[0]]}: malformed row: {cells[wide[0]]} cells (a "
                             f"recording has at most {MAX_COLUMNS})")
    short = np.flatnonzero(keep & (cells < n_names))
    long = np.flatnonzero(keep & (cells > n_names))
    bad_long = None
    for i in long if lines.extra_empty is None else long[~lines.extra_empty[long]]:
        if any(c.strip(" \t") for c in lines.cells_of(i)[n_names:]):
            bad_long = int(i)
            break
    candidates = [i for i in (short[0] if short.size else None, bad_long) if i is not None]
    if candidates:
        i = min(candidates)
        line = int(lines.numbers[i])
        if cells[i] > n_names and header_trailing:
            raise bad_line(path, f"line {line}: column {n_names + 1} has a value but no name in the header")
        hint = ""
        if cells[i] > n_names and (cells[keep] > n_names).all():
            hint = " (every line has more cells than the header: a column without a name?)"
        elif cells[i] < n_names:
            hint = " (a missing cell)"
        raise bad_line(path, f"line {line}: malformed row: {cells[i]} cells where the header names "
                             f"{n_names} columns{hint}")
    if long.size:
        log.info("%s: %d line(s) end with empty cells beyond the header's %d columns (trailing "
                 "delimiters): ignored", path, long.size, n_names)
    return keep, bool(long.size)
