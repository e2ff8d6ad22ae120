"""Recording CSV bytes -> float64 columns: fast when the file is clean, exact about what is wrong when not.

Cheap checks on the raw bytes come first (compression, encoding, the ``#`` preamble and the header,
then the number of cells on every line, counted with numpy), so that pandas' C parser only sees a
table whose shape is already known: it can no longer shift columns, take the first one as an index
or spend minutes on a huge line. Only when that parse fails (a non-numeric cell), or the file uses
quotes, does a slower text path run, to name the first bad cell or to drop an auxiliary column.
Every check is linear in the file's size.
"""
from __future__ import annotations

import csv
import io
import logging
import re
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import pandas as pd

from gyronet.recordings.csvtable.badlines import bad_line, drop_bad_lines
from gyronet.recordings.csvtable.cells import MISSING, NA_TOKENS, parse_numbers
from gyronet.recordings.csvtable.shape import check_shape, scan_bytes, scan_quoted
from gyronet.recordings.csvtable.tail import drop_cut_last_line
from gyronet.recordings.csvtable.text import check_header, read_preamble, read_source, show, sniff, split_header, to_utf8
from gyronet.errors import RecordingError

log = logging.getLogger(__name__)

# pandas < 3 parses floats to within an ulp unless asked for round trips; 3 always round-trips
_FLOAT_OPTIONS = {"float_precision": "round_trip"} if int(pd.__version__.split(".")[0]) < 3 else {}


@dataclass
class Table:
    """A parsed recording: numeric columns by name, the ``#`` metadata, where each row came from."""

    columns: dict[str, np.ndarray]
    meta: dict[str, str]
    lines: np.ndarray  # file line number of each row, 1-based
    dropped: dict[str, str] = field(default_factory=dict)  # auxiliary column -> why it was dropped
    cut_rows: int = 0  # an unterminated last line cut short, dropped with a warning (0 or 1)
    dropped_lines: dict[str, int] = field(default_factory=dict)  # bad_lines=drop: lines left out, by reason


def _read_fast(body: bytes, delimiter: str, decimal: str, usecols: int | None = None,
               skip_blank: bool = False, text: Sequence[bool] = ()) -> pd.DataFrame | None:
    """pandas' C parser, columns by position; None when a cell is not a number or a line is too long.

    Blank lines are rows of NaN unless ``skip_blank``: then a clean-looking parse has one row a line.
    Columns where ``text`` is True are read as text (auxiliary ones, which may hold a logger's status word).
    """
    dtype = {i: object if t else np.float64 for i, t in enumerate(text)} if any(text) else np.float64
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return pd.read_csv(io.BytesIO(body), header=None, index_col=False, dtype=dtype,
                               usecols=None if usecols is None else list(range(usecols)), sep=delimiter,
                               decimal=decimal, skip_blank_lines=skip_blank, na_values=list(NA_TOKENS),
                               keep_default_na=False, comment=None, quoting=csv.QUOTE_NONE, engine="c",
                               encoding="utf-8", encoding_errors="replace", **_FLOAT_OPTIONS)
    except (ValueError, pd.errors.ParserError, pd.errors.EmptyDataError):
        return None


def _plainly_clean(frame: pd.DataFrame | None, n_names: int) -> bool:
    """Whether a fast parse needs no second look: as many columns as names and no NaN in the last
    one (a short line, a blank line or an empty last cell would leave one there)."""
    if frame is None or frame.shape[1] != n_names or len(frame) == 0:
        return False
    return not frame.iloc[:, -1].isna().any()


def _frame_values(frame: pd.DataFrame, names: Sequence[str], decimal: str) -> tuple[dict, dict]:
    """Each column as float64, and for an auxiliary one read as text, which of its cells are not numbers."""
    values, wrong = {}, {}
    for i, n in enumerate(names):
        if frame[i].dtype == object:  # an auxiliary column read as text
            values[n], wrong[n] = parse_numbers(frame[i].fillna(""), decimal)
        else:
            values[n] = frame[i].to_numpy(dtype=np.float64)
    return values, wrong


def parse_table(path: Path, required: Sequence[str], delimiter: str | None = ",",
                decimal: str | None = ".", bad_lines: str = "refuse") -> Table:
    """Read a recording's table; ``delimiter`` or ``decimal`` None: sniffed (``;``, tab, ``1,5``).

    Required columns must be numbers in every row. An auxiliary column that is not (text, an empty
    cell, NaN or inf) is dropped, named in one warning and in ``Table.dropped``. ``bad_lines="drop"``
    leaves out the lines that would be refused one by one, counted in ``Table.dropped_lines``.
    """
    raw = to_utf8(read_source(path), path)
    if delimiter is None or decimal is None:
        sniffed = sniff(raw)
        delimiter, decimal = delimiter or sniffed[0], decimal or sniffed[1]
    meta, header_line, header, body_start = read_preamble(raw, path)
    names = split_header(header, delimiter)
    trailing = check_header(path, names, required, delimiter, header)
    body, dropped_lines = raw[body_start:], {}
    if bad_lines == "drop":  # first: a left-out line's short cells must not vouch for a cut last cell below them
        body, dropped_lines = drop_bad_lines(path, body, names, required, delimiter, decimal, header_line + 1)
    body, cut_rows = drop_cut_last_line(path, body, delimiter, len(names), header_line + 1)
    # pandas makes a column of every cell of the first line: a huge one must not get there
    first = re.search(rb"[^ \t\n]", body)
    start = first.start() if first else len(body)
    end = body.find(b"\n", start)
    first_line = body[start:len(body) if end < 0 else end]
    fits = first_line.count(delimiter.encode()) == len(names) - 1
    frame = _read_fast(body, delimiter, decimal) if fits else None
    wrong: dict[str, np.ndarray] = {}
    auxiliary = [n not in required for n in names]
    if frame is None and fits and any(auxiliary):
        # a word in an auxiliary column ('OK') sent all 2 M rows down the text path: 22.7 s against 0.8
        frame = _read_fast(body, delimiter, decimal, text=auxiliary)
    if _plainly_clean(frame, len(names)):
        values, wrong = _frame_values(frame, names, decimal)
        numbers = header_line + 1 + np.arange(len(frame))
        columns, dropped = _validate(path, names, set(required), values, wrong, numbers,
                                     lambda r: ["" if pd.isna(v) else str(v) for v in frame.iloc[r]])
        return Table(columns, meta, numbers, dropped, cut_rows, dropped_lines)
    quoted = b'"' in body
    if quoted:
        lines = scan_quoted(path, body.decode("utf-8", "replace"), header_line + 1, delimiter)
    else:
        lines, ends = scan_bytes(body, header_line + 1, delimiter, len(names))
    keep, extra = check_shape(path, lines, len(names), trailing)
    rows = np.flatnonzero(keep)
    if rows.size == 0:
        raise RecordingError(f"{path}: no samples after the header")
    if quoted:
        frame = None
    elif extra or not keep.all() or lines.blank or frame is None or frame.shape != (rows.size, len(names)):
        frame = _read_fast(body[:int(ends[rows[-1]])], delimiter, decimal, len(names) if extra else None, True)
    if frame is not None and frame.shape == (rows.size, len(names)):
        values, wrong = _frame_values(frame, names, decimal)  # a text column ('nan', then 'ok') stays text
    else:  # the text path: slower, and names the first cell that is not a number
        texts = list(zip(*(lines.cells_of(int(i))[:len(names)] for i in rows)))
        parsed = {n: parse_numbers(t, decimal) for n, t in zip(names, texts)}
        values = {n: v for n, (v, _) in parsed.items()}
        wrong = {n: w for n, (_, w) in parsed.items()}
    numbers = lines.numbers[rows]
    columns, dropped = _validate(path, names, set(required), values, wrong, numbers,
                                 lambda r: lines.cells_of(int(rows[r])))
    return Table(columns, meta, numbers, dropped, cut_rows + int(len(keep) > 0 and not keep[-1]), dropped_lines)


def _validate(path: Path, names: list[str], required: set[str], values: dict[str, np.ndarray],
              wrong: dict[str, np.ndarray], numbers: np.ndarray, cells_of: Callable[[int], list[str]] | None
              ) -> tuple[dict[str, np.ndarray], dict[str, str]]:
    """Refuse a required column that is not finite numbers, or time that does not increase; drop an auxiliary
    column that is not finite numbers (one warning)."""
    first: tuple[int, str] | None = None
    for name in names:
        bad = np.flatnonzero(wrong[name]) if name in required and name in wrong else ()
        if len(bad) and (first is None or bad[0] < first[0]):
            first = (int(bad[0]), name)
    if first is not None:
        row, name = first
        cells = [c.strip(" \t") for c in cells_of(row)]
        if cells[:len(names)] == names:
            raise bad_line(path, f"line {numbers[row]} repeats the header (two recordings joined into one file?)")
        raise bad_line(path, f"line {numbers[row]}: column {name!r}: non-numeric value "
                       f"{show(cells[names.index(name)], 40)}")
    for name in (n for n in names if n in required):
        bad = np.flatnonzero(~np.isfinite(values[name]))
        if bad.size:
            what = MISSING if np.isnan(values[name][bad[0]]) else "infinite value"
            raise bad_line(path, f"line {numbers[bad[0]]}: column {name!r}: {what}"
                           f" ({bad.size} such cell(s) in this column)")
    dropped: dict[str, str] = {}
    for name in (n for n in names if n not in required):
        text = wrong.get(name, np.zeros(len(values[name]), dtype=bool))
        bad = np.flatnonzero(text | ~np.isfinite(values[name]))
        if bad.size:
            row = int(bad[0])
            what = (f"non-numeric value {show(cells_of(row)[names.index(name)].strip(), 20)}" if text[row]
                    else MISSING if np.isnan(values[name][row]) else "infinite value")
            dropped[name] = f"line {numbers[row]}: {what}, {bad.size} such cell(s)"
    if dropped:
        log.warning("%s: auxiliary column(s) dropped, not a finite number in every row: %s", path,
                    "; ".join(f"{n} ({why})" for n, why in dropped.items()))
    if "time_s" in required:
        _check_time(path, values["time_s"], numbers)
    return {n: values[n] for n in names if n not in dropped}, dropped


def _check_time(path: Path, time_s: np.ndarray, lines: np.ndarray) -> None:
    """Refuse time that does not increase, naming the line (CONTRACT.md section 1)."""
    bad = np.flatnonzero(np.diff(time_s) <= 0)
    if bad.size:
        row = int(bad[0]) + 1
        raise bad_line(path, f"line {lines[row]}: time_s {float(time_s[row])!r} does not "
                       f"increase (previous {float(time_s[row - 1])!r})")
