"""The CSV line protocol: a header line, then one sample a line, the columns of CONTRACT.md section 1.

Lines end in ``\\n`` (a ``\\r`` before it is ignored); ``#`` lines are metadata and skipped. A
sender that reconnects may send its header again: the same header is skipped, a different one
(a line of unique names that include ``time_s``) replaces it.
"""
from __future__ import annotations

import logging
import re
from typing import Mapping, Sequence

from gyronet.stream.events import Fault, Sample, SampleCheck

log = logging.getLogger(__name__)

_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*\Z")
MAX_LINE_BYTES = 4096


def encode_csv_header(columns: Sequence[str]) -> bytes:
    """The header line."""
    return (",".join(columns) + "\n").encode("ascii")


def encode_csv_line(sample: Sample | Mapping[str, float], columns: Sequence[str]) -> bytes:
    """One sample line, values in ``columns`` order, each written so that it reads back exactly."""
    row = sample.row() if isinstance(sample, Sample) else sample
    return (",".join(repr(float(row[c])) for c in columns) + "\n").encode("ascii")


class CsvLineParser:
    """Incremental parser of the CSV line protocol: feed bytes in any chunks.

    Parameters
    ----------
    max_line_bytes
        A longer line is one ``garbage`` fault (bytes are dropped up to the next newline).
    """

    def __init__(self, max_line_bytes: int = MAX_LINE_BYTES):
        self.max_line_bytes = max_line_bytes
        self.header: list[str] | None = None
        self.check = SampleCheck()
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
            text = line.decode("ascii").strip()
        except UnicodeDecodeError:
            out.append(Fault("garbage", line, "not ASCII text"))
            return
        if not text or text.startswith("#"):
            return
        cells = [cell.strip() for cell in text.split(",")]
        if _is_header(cells):
            if cells != self.header:
                log.info("CSV header: %s", ",".join(cells))
                self.header = cells
            return
        if self.header is None:
            out.append(Fault("no_header", line))
            return
        out.append(self._sample(cells, line))

    def _sample(self, cells: list[str], line: bytes) -> Sample | Fault:
        header = self.header or []
        if len(cells) < len(header):
            return Fault("truncated", line, f"{len(cells)} of {len(header)} cells")
        if len(cells) > len(header):
            return Fault("bad_field_count", line, f"{len(cells)} cells, header has {len(header)}")
        values: dict[str, float] = {}
        for name, cell in zip(header, cells):
            try:
                values[name] = float(cell)
            except ValueError:
                return Fault("non_numeric", line, f"{name}={cell[:20]!r}")
        time_s = values.pop("time_s")
        return self.check.check(time_s, values, line)


def _is_header(cells: list[str]) -> bool:
    """A header: unique names, ``time_s`` among them."""
    return "time_s" in cells and len(set(cells)) == len(cells) and all(_NAME.match(c) for c in cells)
