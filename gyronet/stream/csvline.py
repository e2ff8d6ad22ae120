"""The CSV line protocol: a header line, then one sample a line, the columns of CONTRACT.md section 1.

Lines end in ``\\n`` (a ``\\r`` before it is ignored); ``#`` lines are metadata and skipped. A
sender that reconnects may send its header again: the same header is skipped. A different one
(unique names, ``time_s`` and every ``required`` column among them) replaces the current header
once a sample line fits it; when the next line fits the current header instead, it was a stray
line (``bad_header``) and the current header stays. A header that lacks a required column is a
``bad_header`` fault at once. So one corrupt line that reads like a header cannot turn every
later sample into a fault.

Numbers are read as the offline loader (pandas) reads them: ASCII decimal with an optional sign,
point and exponent. Python's ``float`` also takes ``1_000``, ``١`` and friends; those are
``non_numeric`` here, as offline. ``nan`` and ``inf`` spellings are ``nan`` faults.
"""
from __future__ import annotations

import logging
import re
from typing import Iterable, Mapping, Sequence

from gyronet.stream.events import Fault, Sample, SampleCheck

log = logging.getLogger(__name__)

_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*\Z")
_SPACE = " \t\x0b\x0c"  # what pandas skips around a number (str.strip() would also take \x1c-\x1f)
_NUMBER_CELL = re.compile(rf"[{_SPACE}]*[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?[{_SPACE}]*\Z")
# a line of only these characters is read by float() exactly as pandas reads it, or float() fails
_PLAIN = "0123456789eE+-., \t"
# spellings of NaN and infinity that float() reads; refused as 'nan' (offline: as not finite)
_NON_FINITE = frozenset(f"{sign}{word}" for sign in ("", "+", "-") for word in ("nan", "inf", "infinity"))
MAX_LINE_BYTES = 4096


def encode_csv_header(columns: Sequence[str]) -> bytes:
    """The header line."""
    return (",".join(columns) + "\n").encode("ascii")


def encode_csv_line(sample: Sample | Mapping[str, float], columns: Sequence[str]) -> bytes:
    """One sample line, values in ``columns`` order, each written so that it reads back exactly."""
    row = sample.row() if isinstance(sample, Sample) else sample
    return (",".join(repr(float(row[c])) for c in columns) + "\n").encode("ascii")


def parse_number(cell: str) -> float | None:
    """The value of one CSV cell as the offline loader reads it; None when it is not a number."""
    if _NUMBER_CELL.match(cell):
        return float(cell)
    word = cell.strip(_SPACE).lower()
    return float(word) if word in _NON_FINITE else None


class CsvLineParser:
    """Incremental parser of the CSV line protocol: feed bytes in any chunks.

    Parameters
    ----------
    max_line_bytes
        A longer line is one ``garbage`` fault (bytes are dropped up to the next newline).
    required
        Columns a header must carry to be accepted (``time_s`` always): the consumer's inputs,
        e.g. ``Compensator.input_columns``.
    check
        The time and value checks (default ``SampleCheck()``).
    """

    def __init__(self, max_line_bytes: int = MAX_LINE_BYTES, required: Iterable[str] = (),
                 check: SampleCheck | None = None):
        self.max_line_bytes = max_line_bytes
        self.required = list(dict.fromkeys(["time_s", *required]))
        self.header: list[str] | None = None
        self.check = check or SampleCheck()
        self._candidate: tuple[list[str], bytes] | None = None  # a new header no line has fitted yet
        self._buffer = bytearray()
        self._discarding = False

    @property
    def columns(self) -> list[str] | None:
        """The columns of the current header (None before one arrived)."""
        return self.header

    def feed(self, data: bytes) -> list[Sample | Fault]:
        """Parse the complete lines ``data`` makes; keep the partial last line."""
        self._buffer += data
        out: list[Sample | Fault] = []
        while True:
            end = self._buffer.find(b"\n")
            if end < 0:
                break
            line = bytes(self._buffer[:end])
            del self._buffer[:end + 1]
            if self._discarding:
                self._discarding = False
                continue
            self._handle(line, out)
        if not self._discarding and len(self._buffer) > self.max_line_bytes:
            out.append(Fault("garbage", bytes(self._buffer), f"line longer than {self.max_line_bytes} bytes"))
            self._discarding = True
        if self._discarding:
            self._buffer.clear()
        return out

    def flush(self) -> list[Sample | Fault]:
        """End of stream (or of a connection): a partial last line is a cut line."""
        rest = bytes(self._buffer).strip()
        self._buffer.clear()
        discarding, self._discarding = self._discarding, False
        if rest and not discarding:
            return [Fault("truncated", rest, "stream ended inside a line")]
        return []

    def _handle(self, line: bytes, out: list) -> None:
        if len(line) > self.max_line_bytes:
            out.append(Fault("garbage", line, f"line longer than {self.max_line_bytes} bytes"))
            return
        try:
            text = line.decode("ascii").strip(_SPACE + "\r")
        except UnicodeDecodeError:
            out.append(Fault("garbage", line, "not ASCII text"))
            return
        if not text or text.startswith("#"):
            return
        values: list[float] | None = None
        if not text.strip(_PLAIN):  # the common case: every character part of a plain number
            cells = text.split(",")
            try:
                values = [float(cell) for cell in cells]
            except ValueError:  # an empty cell, a stray sign: parse_number says which
                cells = [cell.strip(_SPACE) for cell in cells]
        else:
            cells = [cell.strip(_SPACE) for cell in text.split(",")]
            if _is_header(cells):
                self._header_line(cells, line, out)
                return
        if self.header is None:
            out.append(Fault("no_header", line))
            return
        out.append(self._sample(self._header_for(len(cells), out), cells, values, line))

    def _header_line(self, cells: list[str], line: bytes, out: list) -> None:
        missing = [c for c in self.required if c not in cells]
        if missing:
            out.append(Fault("bad_header", line, f"lacks {', '.join(missing)}"))
            return
        if cells == self.header:  # the sender re-sent its header: any stray candidate is dropped
            self._drop_candidate(out)
            return
        if self.header is None:
            log.info("CSV header: %s", ",".join(cells))
            self.header = cells
            return
        self._drop_candidate(out)
        self._candidate = (cells, line)

    def _header_for(self, n_cells: int, out: list) -> list[str]:
        """The header a line of ``n_cells`` is read with; settles a pending candidate header.

        A line that fits the candidate adopts it (the newest wins when both fit); one that fits
        only the current header proves the candidate a stray line; one that fits neither is
        judged against the current header and settles nothing.
        """
        if self._candidate is None:
            return self.header
        candidate = self._candidate[0]
        if n_cells == len(candidate):
            log.info("CSV header: %s", ",".join(candidate))
            self.header, self._candidate = candidate, None
            return candidate
        if n_cells == len(self.header):
            self._drop_candidate(out)
        return self.header

    def _drop_candidate(self, out: list) -> None:
        if self._candidate is not None:
            out.append(Fault("bad_header", self._candidate[1], "no sample line fits it; the header stays"))
            self._candidate = None

    def _sample(self, header: list[str], cells: list[str], values: list[float] | None, line: bytes,
                ) -> Sample | Fault:
        if len(cells) < len(header):
            return Fault("truncated", line, f"{len(cells)} of {len(header)} cells")
        if len(cells) > len(header):
            return Fault("bad_field_count", line, f"{len(cells)} cells, header has {len(header)}")
        if values is None:
            values = []
            for name, cell in zip(header, cells):
                value = parse_number(cell)
                if value is None:
                    return Fault("non_numeric", line, f"{name}={cell[:20]!r}")
                values.append(value)
        row = dict(zip(header, values))
        time_s = row.pop("time_s")
        return self.check.check(time_s, row, line)


def _is_header(cells: list[str]) -> bool:
    """A header: unique names, ``time_s`` among them."""
    return "time_s" in cells and len(set(cells)) == len(cells) and all(_NAME.match(c) for c in cells)
