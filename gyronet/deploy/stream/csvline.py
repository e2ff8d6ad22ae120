"""The CSV line protocol: a header line, then one sample a line, the columns of CONTRACT.md section 1.

Lines end in ``\\n`` (a ``\\r`` before it is ignored); ``#`` lines are metadata and skipped. A
sender that reconnects may send its header again: the same header is skipped. A different one
(unique names, ``time_s`` and every ``required`` column among them) replaces the current header,
and the one before is kept: a later line that fits only the one before proves the new one a stray
line (``bad_header``) and brings the one before back. A header that lacks a required column is a
``bad_header`` fault at once. So one corrupt line that reads like a header (even one followed by
a damaged line that fits it) cannot turn every later sample into a fault.

Numbers are read as the offline loader (pandas) reads them: ASCII decimal with an optional sign,
point and exponent. Python's ``float`` also takes ``1_000``, ``١`` and friends; those are
``non_numeric`` here, as offline. ``nan`` and ``inf`` spellings are ``nan`` faults.

With ``blocks=True`` (the live loop), a run of complete good lines comes out as one ``SampleBlock``
read at once (:mod:`.csv_run`); any line that is not plainly good goes the per-line way below, so
the samples, faults and their order are the same.
"""
from __future__ import annotations

import logging
import re
from dataclasses import dataclass
from typing import Iterable, Mapping, Sequence

from gyronet.deploy.stream.csv_run import LineRun
from gyronet.deploy.stream.events import Fault, Sample, SampleBlock, SampleCheck

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
    blocks
        Good lines in a row (a flood) come out as one ``SampleBlock`` of columns, read at once
        (:mod:`.csv_run`), instead of one ``Sample`` each: the same samples, faults and order
        (``events.as_samples`` takes the blocks apart), for a consumer that takes columns.
    """

    def __init__(self, max_line_bytes: int = MAX_LINE_BYTES, required: Iterable[str] = (),
                 check: SampleCheck | None = None, blocks: bool = False):
        self.max_line_bytes = max_line_bytes
        self.blocks = blocks
        self._run: LineRun | None = None  # the block reader of the current header
        self.required = list(dict.fromkeys(["time_s", *required]))
        self._current: _Header | None = None
        self.check = check or SampleCheck()
        self._previous: _Header | None = None  # the header before the current one: the fallback
        self._buffer = bytearray()
        self._discarding = False

    @property
    def header(self) -> list[str] | None:
        """The columns of the current header (None before one arrived)."""
        return None if self._current is None else self._current.cells

    @property
    def columns(self) -> list[str] | None:
        """The columns of the current header (None before one arrived)."""
        return self.header

    def feed(self, data: bytes) -> list[Sample | SampleBlock | Fault]:
        """Parse the complete lines ``data`` makes; keep the partial last line."""
        buffer = self._buffer
        buffer += data
        out: list[Sample | SampleBlock | Fault] = []
        position = retry = 0  # retry: where the block path is tried again (the lines before go one by one)
        if self._run is not None:
            self._run.forget()  # the buffer changed
        while True:
            if self.blocks and position >= retry and self._current is not None and not self._discarding:
                block, step, retry = self._line_run().decode(buffer, position, self.check)
                if block is not None:
                    self._header_for(len(self._current.cells), out)  # what the block's first line does to the headers
                    out.append(block)
                    position += step
                    continue
            end = buffer.find(b"\n", position)
            if end < 0:
                break
            line = bytes(buffer[position:end])
            position = end + 1
            if self._discarding:
                self._discarding = False
                continue
            self._handle(line, out)
        del buffer[:position]
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

    def _line_run(self) -> LineRun:
        """The block reader of the current header."""
        if self._run is None or self._run.header is not self._current.cells:
            self._run = LineRun(self._current.cells, self.max_line_bytes)
        return self._run

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
        elif self._current is None or cells != self._current.cells:
            log.info("CSV header: %s", ",".join(cells))
            self._previous, self._current = self._current, _Header(cells, line)

    def _header_for(self, n_cells: int, out: list) -> list[str]:
        """The header a line of ``n_cells`` is read with.

        The current one when the line fits it; else the previous one when the line fits that:
        the header line in between was a stray, and the previous header is back. A line that fits
        neither is judged against the current header. A header that turns out a stray (left by
        such a return, or never fitted by a line while the next one was) is one ``bad_header``.
        """
        current, previous = self._current, self._previous
        if n_cells == len(current.cells):
            if previous is not None and not previous.fitted:
                self._stray(previous, out, "no line fitted it")
        elif previous is not None and n_cells == len(previous.cells):
            self._stray(current, out, "the next line fits the previous header; that one is back")
            self._current, self._previous = current, previous = previous, current
            log.info("CSV header: back to %s", ",".join(current.cells))
        else:
            return current.cells
        current.fitted = True
        return current.cells

    @staticmethod
    def _stray(header: "_Header", out: list, why: str) -> None:
        if not header.counted:
            out.append(Fault("bad_header", header.raw, why))
            header.counted = True

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


@dataclass
class _Header:
    """A header line the parser has taken, and what the lines after it said about it."""

    cells: list[str]
    raw: bytes
    fitted: bool = False  # a line of its length came after it
    counted: bool = False  # already counted as a bad_header


def _is_header(cells: list[str]) -> bool:
    """A header: unique names, ``time_s`` among them."""
    return "time_s" in cells and len(set(cells)) == len(cells) and all(_NAME.match(c) for c in cells)
