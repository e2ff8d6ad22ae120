"""Recording CSV bytes -> float64 columns: fast when the file is clean, exact about what is wrong when not.

Cheap checks on the raw bytes come first (compression, encoding, the ``#`` preamble and the header,
then the number of cells on every line, counted with numpy), so that pandas' C parser only sees a
table whose shape is already known: it can no longer shift columns, take the first one as an index
or spend minutes on a huge line. Only when that parse fails (a non-numeric cell), or the file uses
quotes, does a slower text path run, to name the first bad cell or to drop an auxiliary column.
Every check is linear in the file's size.
"""
from __future__ import annotations

import collections
import contextlib
import csv
import gzip
import io
import logging
import re
import warnings
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import pandas as pd

from gyronet.errors import RecordingError

log = logging.getLogger(__name__)

MAX_COLUMNS = 10_000  # a header with more cells is not a recording's
MAX_NAME_CHARS = 256  # a header cell longer than this is not a column name
# what both parsers read as NaN (pandas' defaults, passed explicitly so the text path agrees)
NA_TOKENS = ("", "#N/A", "#N/A N/A", "#NA", "-1.#IND", "-1.#QNAN", "-NaN", "-nan", "1.#IND", "1.#QNAN",
             "<NA>", "N/A", "NA", "NULL", "NaN", "None", "n/a", "nan", "null")
_BOMS = ((b"\xff\xfe\x00\x00", "utf-32-le"), (b"\x00\x00\xfe\xff", "utf-32-be"),
         (b"\xff\xfe", "utf-16-le"), (b"\xfe\xff", "utf-16-be"))
_CONTROL = re.compile(r"[\x00-\x08\x0b\x0c\x0e-\x1f\x7f-\x9f]")
# pandas < 3 parses floats to within an ulp unless asked for round trips; 3 always round-trips
_FLOAT_OPTIONS = {"float_precision": "round_trip"} if int(pd.__version__.split(".")[0]) < 3 else {}


@dataclass
class Table:
    """A parsed recording: numeric columns by name, the ``#`` metadata, where each row came from."""

    columns: dict[str, np.ndarray]
    meta: dict[str, str]
    lines: np.ndarray  # file line number of each row, 1-based
    dropped: dict[str, str] = field(default_factory=dict)  # auxiliary column -> why it was dropped


def show(text: str, limit: int = 60) -> str:
    """A piece of the file, quoted and cut, so that an error stays one short line."""
    return repr(text[:limit] + ("..." if len(text) > limit else ""))


def read_source(path: Path) -> bytes:
    """The file's bytes, gunzipped when they are gzip (whatever the name says)."""
    try:
        raw = path.read_bytes()
    except OSError as err:
        raise RecordingError(f"{path}: cannot read ({err.strerror or err})") from None
    if raw[:2] == b"\x1f\x8b":
        try:
            return gzip.decompress(raw)
        except (EOFError, zlib.error, gzip.BadGzipFile, OSError) as err:
            what = "truncated" if isinstance(err, EOFError) else "corrupt"
            raise RecordingError(f"{path}: {what} gzip file ({str(err).splitlines()[0][:80]})") from None
    if path.suffix.lower() == ".gz" and raw:
        log.warning("%s: not gzip-compressed despite its name; read as plain text", path)
    return raw


def to_utf8(raw: bytes, path: Path) -> bytes:
    """UTF-8 bytes with ``\\n`` line ends: UTF-16/32 (with a BOM, or plain ASCII in UTF-16) transcoded."""
    encoding = next((enc for bom, enc in _BOMS if raw.startswith(bom)), None)
    if encoding is not None:
        raw = raw[2 if "16" in encoding else 4:]
    else:
        head = raw[:256 - 256 % 2]
        if len(head) >= 8 and 0 in head:
            if not any(head[1::2]) and all(head[0::2]):
                encoding = "utf-16-le"
            elif not any(head[0::2]) and all(head[1::2]):
                encoding = "utf-16-be"
    if encoding is not None:
        try:
            raw = raw.decode(encoding).encode("utf-8")
        except UnicodeDecodeError as err:
            raise RecordingError(f"{path}: not valid {encoding.upper()} text (byte {err.start})") from None
    if raw.startswith(b"\xef\xbb\xbf"):
        raw = raw[3:]
    if b"\r" in raw:
        raw = raw.replace(b"\r\n", b"\n").replace(b"\r", b"\n")
    return raw


def _decode_line(line: bytes) -> str:
    for encoding in ("utf-8", "cp1252"):  # a '°' from a Windows editor in a comment
        try:
            return line.decode(encoding)
        except UnicodeDecodeError:
            pass
    return line.decode("latin-1")


def split_header(text: str, delimiter: str) -> list[str]:
    """Header cells, stripped; quoted cells (``"time_s"``) are unquoted."""
    if '"' not in text:
        return [n.strip() for n in text.split(delimiter)]
    with _field_limit(len(text)):
        return [n.strip() for n in next(csv.reader([text], delimiter=delimiter))]


@contextlib.contextmanager
def _field_limit(chars: int):
    """The csv module refuses fields over 128 KiB by default: lift that for one parse."""
    old = csv.field_size_limit()
    csv.field_size_limit(max(old, chars + 1))
    try:
        yield
    finally:
        csv.field_size_limit(old)


def read_preamble(raw: bytes, path: Path) -> tuple[dict[str, str], int, str, int]:
    """The ``#`` metadata, the header's line number and text, and the offset of the first data byte."""
    meta: dict[str, str] = {}
    pos, line_no = 0, 0
    while pos < len(raw):
        end = raw.find(b"\n", pos)
        end = len(raw) if end < 0 else end
        line_no += 1
        text = _decode_line(raw[pos:end]).strip()
        pos = end + 1
        if _CONTROL.search(text):
            raise RecordingError(f"{path}: not a CSV file (binary content on line {line_no})")
        if not text:
            continue
        if text.startswith("#"):
            key, sep, value = text[1:].partition("=")
            if sep:
                meta[key.strip()] = value.strip()
            continue
        return meta, line_no, text, min(pos, len(raw))
    raise RecordingError(f"{path}: empty file (no header row)")


def check_header(path: Path, names: list[str], required: Sequence[str], delimiter: str, text: str) -> int:
    """Refuse a header that cannot be a recording's; return how many trailing empty cells it has."""
    if len(names) > MAX_COLUMNS:
        raise RecordingError(f"{path}: the header has {len(names)} cells (a recording has at most "
                             f"{MAX_COLUMNS}); not a recording")
    if len(names) < 2:
        other = next((d for d in (";", "\t") if d != delimiter and d in text), None)
        if other is not None:
            raise RecordingError(
                f"{path}: cells are separated by {other!r}, not {delimiter!r}; convert it first: python "
                f"scripts/convert.py input={path} output=NEW.csv (reads ';', tabs and decimal commas)")
        raise RecordingError(f"{path}: not a CSV recording (first line {show(text)} has no "
                             f"{'commas' if delimiter == ',' else repr(delimiter)})")
    trailing = 0
    while names and not names[-1]:
        names.pop()
        trailing += 1
    long = next((i for i, n in enumerate(names) if len(n) > MAX_NAME_CHARS), None)
    if long is not None:
        raise RecordingError(f"{path}: column {long + 1} of the header is {len(names[long])} characters "
                             f"long (at most {MAX_NAME_CHARS}); not a column name")
    if "" in names:
        raise RecordingError(f"{path}: column {names.index('') + 1} of the header has no name")
    counts = collections.Counter(names)
    duplicate = next((n for n in names if counts[n] > 1), None)
    if duplicate is not None:
        raise RecordingError(f"{path}: duplicate column {show(duplicate)} in the header")
    present = set(names)
    missing = [c for c in required if c not in present]
    if missing:
        raise RecordingError(f"{path}: missing required column(s) {', '.join(missing)}"
                             f" (header has {show(', '.join(names), 120)})")
    return trailing


def sniff(raw: bytes) -> tuple[str, str]:
    """(delimiter, decimal mark) of a table: ``;`` or tab when the header has no comma, and a
    decimal comma when such a table has commas in its first rows (``1,5;2,25``)."""
    head = raw[:65536].decode("utf-8", "replace")
    lines = [ln for ln in head.split("\n") if ln.strip() and not ln.lstrip().startswith("#")]
    if not lines or "," in lines[0]:
        return ",", "."
    delimiter = ";" if ";" in lines[0] else "\t" if "\t" in lines[0] else ","
    decimal = "," if delimiter != "," and any("," in ln for ln in lines[1:20]) else "."
    return delimiter, decimal


@dataclass
class _Lines:
    """The body's non-blank lines: their cell counts and file line numbers, and a way to split one."""

    cells: np.ndarray
    numbers: np.ndarray
    terminated: bool  # the last one ends with a newline
    cells_of: Callable[[int], list[str]]
    blank: int = 0  # blank lines skipped
    extra_empty: np.ndarray | None = None  # per line: every cell beyond the header's is empty (quick test)


def _scan_bytes(body: bytes, first_line: int, delimiter: str, n_names: int) -> tuple[_Lines, np.ndarray]:
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


def _scan_quoted(path: Path, text: str, first_line: int, delimiter: str) -> _Lines:
    """Line and cell structure of a body that uses quotes, with the csv module (slow, exact)."""
    rows, numbers, blank = [], [], 0
    reader = csv.reader(io.StringIO(text), delimiter=delimiter, strict=False)
    with _field_limit(len(text)):
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


def _check_shape(path: Path, lines: _Lines, n_names: int, header_trailing: int) -> tuple[np.ndarray, bool]:
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
            raise RecordingError(f"{path}: line {line}: column {n_names + 1} has a value but no name in the header")
        hint = ""
        if cells[i] > n_names and (cells[keep] > n_names).all():
            hint = " (every line has more cells than the header: a column without a name?)"
        elif cells[i] < n_names:
            hint = " (a missing cell)"
        raise RecordingError(f"{path}: line {line}: malformed row: {cells[i]} cells where the header names "
                             f"{n_names} columns{hint}")
    if long.size:
        log.info("%s: %d line(s) end with empty cells beyond the header's %d columns (trailing "
                 "delimiters): ignored", path, long.size, n_names)
    return keep, bool(long.size)


def _numbers(cells: Sequence[str], decimal: str) -> tuple[np.ndarray, np.ndarray]:
    """Text cells -> float64 and a mask of the cells that are not numbers (NA spellings give NaN)."""
    text = pd.Series(cells, dtype=object).str.strip(" \t")
    missing = text.isin(NA_TOKENS).to_numpy()
    wrong = np.zeros(len(text), dtype=bool)
    if decimal != ".":
        wrong = text.str.contains(".", regex=False).to_numpy(dtype=bool)
        text = text.str.replace(decimal, ".", regex=False)
    values = pd.to_numeric(text, errors="coerce").to_numpy(dtype=np.float64)
    return values, wrong | (np.isnan(values) & ~missing)


def _read_fast(body: bytes, delimiter: str, decimal: str, usecols: int | None = None,
               skip_blank: bool = False) -> pd.DataFrame | None:
    """pandas' C parser, columns by position; None when a cell is not a number or a line is too long.

    Blank lines are rows of NaN unless ``skip_blank``: then a clean-looking parse has one row a line.
    """
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return pd.read_csv(io.BytesIO(body), header=None, index_col=False, dtype=np.float64,
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
    return not np.isnan(frame.iloc[:, -1].to_numpy()).any()


def parse_table(path: Path, required: Sequence[str], delimiter: str | None = ",",
                decimal: str | None = ".") -> Table:
    """Read a recording's table; ``delimiter`` or ``decimal`` None: sniffed (``;``, tab, ``1,5``).

    Required columns must be numbers in every row. An auxiliary column that is not (text, an empty
    cell, NaN or inf) is dropped, named in one warning and in ``Table.dropped``.
    """
    raw = to_utf8(read_source(path), path)
    if delimiter is None or decimal is None:
        sniffed = sniff(raw)
        delimiter, decimal = delimiter or sniffed[0], decimal or sniffed[1]
    meta, header_line, header, body_start = read_preamble(raw, path)
    names = split_header(header, delimiter)
    trailing = check_header(path, names, required, delimiter, header)
    body = raw[body_start:]
    frame = _read_fast(body, delimiter, decimal)
    wrong: dict[str, np.ndarray] = {}
    if _plainly_clean(frame, len(names)):
        values = {n: frame[i].to_numpy(dtype=np.float64) for i, n in enumerate(names)}
        numbers = header_line + 1 + np.arange(len(frame))
        return _finish(path, names, required, values, wrong, numbers, None, meta)
    quoted = b'"' in body
    if quoted:
        lines = _scan_quoted(path, body.decode("utf-8", "replace"), header_line + 1, delimiter)
    else:
        lines, ends = _scan_bytes(body, header_line + 1, delimiter, len(names))
    keep, extra = _check_shape(path, lines, len(names), trailing)
    rows = np.flatnonzero(keep)
    if rows.size == 0:
        raise RecordingError(f"{path}: no samples after the header")
    if quoted:
        frame = None
    elif extra or not keep.all() or lines.blank or frame is None or frame.shape != (rows.size, len(names)):
        frame = _read_fast(body[:int(ends[rows[-1]])], delimiter, decimal, len(names) if extra else None, True)
    if frame is not None and frame.shape == (rows.size, len(names)):
        values = {n: frame[i].to_numpy(dtype=np.float64) for i, n in enumerate(names)}
    else:  # the text path: slower, and names the first cell that is not a number
        texts = list(zip(*(lines.cells_of(int(i))[:len(names)] for i in rows)))
        parsed = {n: _numbers(t, decimal) for n, t in zip(names, texts)}
        values = {n: v for n, (v, _) in parsed.items()}
        wrong = {n: w for n, (_, w) in parsed.items()}
    return _finish(path, names, required, values, wrong, lines.numbers[rows],
                   lambda r: lines.cells_of(int(rows[r])), meta)


def _finish(path: Path, names: list[str], required: Sequence[str], values: dict[str, np.ndarray],
            wrong: dict[str, np.ndarray], numbers: np.ndarray, cells_of: Callable[[int], list[str]] | None,
            meta: dict[str, str]) -> Table:
    columns, dropped = _validate(path, names, set(required), values, wrong, numbers, cells_of)
    return Table(columns, meta, numbers, dropped)


def _validate(path: Path, names: list[str], required: set[str], values: dict[str, np.ndarray],
              wrong: dict[str, np.ndarray], numbers: np.ndarray, cells_of: Callable[[int], list[str]]
              ) -> tuple[dict[str, np.ndarray], dict[str, str]]:
    """Refuse a required column that is not finite numbers; drop such an auxiliary one (one warning)."""
    first: tuple[int, str] | None = None
    for name in names:
        bad = np.flatnonzero(wrong[name]) if name in required and name in wrong else ()
        if len(bad) and (first is None or bad[0] < first[0]):
            first = (int(bad[0]), name)
    if first is not None:
        row, name = first
        cells = [c.strip(" \t") for c in cells_of(row)]
        if cells[:len(names)] == names:
            raise RecordingError(f"{path}: line {numbers[row]} repeats the header (two recordings joined "
                                 "into one file?)")
        raise RecordingError(f"{path}: line {numbers[row]}: column {name!r}: non-numeric value "
                             f"{show(cells[names.index(name)], 40)}")
    for name in (n for n in names if n in required):
        bad = np.flatnonzero(~np.isfinite(values[name]))
        if bad.size:
            what = "empty cell or NaN" if np.isnan(values[name][bad[0]]) else "infinite value"
            raise RecordingError(f"{path}: line {numbers[bad[0]]}: column {name!r}: {what}"
                                 f" ({bad.size} such cell(s) in this column)")
    dropped: dict[str, str] = {}
    for name in (n for n in names if n not in required):
        text = wrong.get(name, np.zeros(len(values[name]), dtype=bool))
        bad = np.flatnonzero(text | ~np.isfinite(values[name]))
        if bad.size:
            row = int(bad[0])
            what = (f"non-numeric value {show(cells_of(row)[names.index(name)].strip(), 20)}" if text[row]
                    else "empty cell or NaN" if np.isnan(values[name][row]) else "infinite value")
            dropped[name] = f"line {numbers[row]}: {what}, {bad.size} such cell(s)"
    if dropped:
        log.warning("%s: auxiliary column(s) dropped, not a finite number in every row: %s", path,
                    "; ".join(f"{n} ({why})" for n, why in dropped.items()))
    return {n: values[n] for n in names if n not in dropped}, dropped
