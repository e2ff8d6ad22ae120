"""Recording bytes to text: gzip, encodings, line ends, the ``#`` preamble and the header row.

Everything here looks at the start of the file or at one line, so it is linear in the file's size
whatever the file holds (a 6 MB line, a 140 KiB header cell, a corrupt gzip stream).
"""
from __future__ import annotations

import collections
import contextlib
import csv
import gzip
import logging
import re
import zlib
from pathlib import Path
from typing import Sequence

from gyronet.errors import RecordingError

log = logging.getLogger(__name__)

MAX_COLUMNS = 10_000  # a header with more cells is not a recording's
MAX_NAME_CHARS = 256  # a header cell longer than this is not a column name
_BOMS = ((b"\xff\xfe\x00\x00", "utf-32-le"), (b"\x00\x00\xfe\xff", "utf-32-be"),
         (b"\xff\xfe", "utf-16-le"), (b"\xfe\xff", "utf-16-be"))
_CONTROL = re.compile(r"[\x00-\x08\x0b\x0c\x0e-\x1f\x7f-\x9f]")


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
    with field_limit(len(text)):
        return [n.strip() for n in next(csv.reader([text], delimiter=delimiter))]


@contextlib.contextmanager
def field_limit(chars: int):
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
        tool, as_lower = other_tool(names), {n.strip().lower() for n in names}
        lower = [c for c in missing if c in as_lower]
        renames = [f"{n} -> {ALIASES[n.strip().lower()]}" for n in names
                   if ALIASES.get(n.strip().lower()) in missing]
        hint = (f"; it looks like a {tool} log: python scripts/convert.py input={path} output=F.csv format={tool}"
                if tool else f"; names are lower case: {', '.join(lower)}" if lower else
                f"; rename {', '.join(renames)} (in s, degC and deg/s)" if renames else "")
        raise RecordingError(f"{path}: missing required column(s) {', '.join(missing)}"
                             f" (header has {show(', '.join(names), 120)}){hint}")
    return trailing


# other loggers' names for the required columns: the error suggests the rename (the units are the user's to check)
ALIASES = {**dict.fromkeys(("t", "t_s", "time", "timestamp", "timestamp_s", "time_sec"), "time_s"),
           **dict.fromkeys(("temp", "temperature", "temp_degc", "temperature_c", "t_c"), "temp_c"),
           **{f"{prefix}{a}": f"gyro_{a}_dps" for a in "xyz" for prefix in ("g", "gyr", "gyro_", "gyro", "w", "omega_")}}


def other_tool(names: Sequence[str]) -> str | None:
    """The importer (``psim``, ``lpms``) whose log has this header, or None."""
    low = {n.strip().lower().replace(" ", "") for n in names}
    if "time(ms)" in low and any(n.startswith("gyrox") for n in low):
        return "psim"
    if any(n.startswith("timestamp") for n in low) and any(n.startswith(("gyrox", "gyrx")) for n in low):
        return "lpms"
    return None


_COMMA_NUMBER = re.compile(r"[+-]?\d*,\d+(?:[eE][+-]?\d+)?")
_DOT_NUMBER = re.compile(r"[+-]?\d*\.\d+(?:[eE][+-]?\d+)?")


def sniff(raw: bytes) -> tuple[str, str]:
    """(delimiter, decimal mark) of a table: ``;`` or tab when the header has no comma, and a
    decimal comma when such a table's first rows hold more numbers like ``1,5`` than like ``1.5``
    (a text cell "ok, stable" is not a number)."""
    head = raw[:65536].decode("utf-8", "replace")
    lines = [ln for ln in head.split("\n") if ln.strip() and not ln.lstrip().startswith("#")]
    if not lines or "," in lines[0]:
        return ",", "."
    delimiter = ";" if ";" in lines[0] else "\t" if "\t" in lines[0] else ","
    if delimiter == ",":
        return ",", "."
    cells = [c.strip().strip('"') for ln in lines[1:20] for c in ln.split(delimiter)]
    commas = sum(bool(_COMMA_NUMBER.fullmatch(c)) for c in cells)
    dots = sum(bool(_DOT_NUMBER.fullmatch(c)) for c in cells)
    decimal = "," if commas > dots else "."
    return delimiter, decimal
