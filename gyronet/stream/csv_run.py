"""A run of complete CSV sample lines read at once: the CSV flood's fast path.

In a flood a read holds hundreds of lines, and reading them one by one (decode, strip, split, a
dict, a ``SampleCheck`` call and a ``Sample`` each) was most of the stream's CPU. Here the
complete lines in the buffer are checked together: only the bytes of plain numbers (digits,
``.eE+-``), commas and line ends (``\n`` or ``\r\n``), the header's number of cells a line
(compared with one bytes comparison of the commas and line ends), at most ``max_line_bytes``
bytes a line. Their cells are read by ``float`` in one pass (the per-line path's own reading of
such a line, so every value is the same to the bit; ``float`` refuses what is not a number:
``1.2.3``, an empty cell, a lone sign). The leading lines that pass become one ``SampleBlock``
once their values are finite and their times pass the check (increasing, no clock restart); the
first line that fails anything goes to the per-line parser, which makes its fault (or its new
segment), so faults and their order are the per-line path's.
"""
from __future__ import annotations

import numpy as np

from gyronet.stream.events import SampleBlock, SampleCheck, leading

# fewer complete lines than this in the buffer (a lone line at 1 kHz) go line by line: below it the arrays'
# fixed cost is more than the per-line parse saves
MIN_RUN_LINES = 16
_NUMBER_BYTES = b"0123456789.eE+-"
_LINE_BYTES = _NUMBER_BYTES + b",\n"
_ALLOWED = np.zeros(256, dtype=bool)
_ALLOWED[list(_LINE_BYTES)] = True


class LineRun:
    """The block reading of sample lines of one header (built once per header).

    Parameters
    ----------
    header
        The columns, in line order (``time_s`` among them).
    max_line_bytes
        A longer line is the per-line parser's (a ``garbage`` fault).
    """

    def __init__(self, header: list[str], max_line_bytes: int):
        self.header = header
        self.n_cells = len(header)
        self.time_index = header.index("time_s")
        self.max_line_bytes = max_line_bytes
        self._shape = b"," * (self.n_cells - 1) + b"\n"  # what is left of a good line without its numbers

    def decode(self, buffer: bytearray, position: int, check: SampleCheck) -> tuple[SampleBlock | None, int, int]:
        """The good lines from ``position`` on, up to the first that is not: a block (or None), its bytes,
        and, when None, where to try again (the lines before that go one by one).

        ``check.last_time_s`` moves to the last good line's time, as ``SampleCheck.check`` does.
        """
        end = buffer.rfind(b"\n", position) + 1
        if end == 0 or buffer.count(b"\n", position, end) < MIN_RUN_LINES:
            return None, 0, max(end, position)
        raw = bytes(buffer[position:end])
        codes = np.frombuffer(raw, dtype=np.uint8)
        line_ends = np.flatnonzero(codes == 10)  # each line's b"\n" in raw
        lengths = np.empty_like(line_ends)  # as the per-line path counts them: b"\r" in, b"\n" not
        lengths[0], lengths[1:] = line_ends[0], line_ends[1:] - line_ends[:-1] - 1
        text, text_ends = raw, line_ends
        if b"\r" in raw:  # lines that end in b"\r\n" (as Arduino's println sends them) lose the b"\r"
            text = raw.replace(b"\r\n", b"\n")
            text_ends = line_ends - np.cumsum(codes[np.maximum(line_ends - 1, 0)] == 13)
        n_lines = len(line_ends)
        if (not text.translate(None, _LINE_BYTES) and text.translate(None, _NUMBER_BYTES) == self._shape * n_lines
                and lengths.max() <= self.max_line_bytes):
            n_good = n_lines  # the usual case: every line of the right shape
        else:
            good = self._shapes_ok(text, lengths)
            n_good = leading(good)
            if n_good < MIN_RUN_LINES:  # too short a run to be worth it: line by line up to the next long one
                return None, 0, position + _next_run(good, line_ends, n_good)
        values, n_good = self._values(text[:int(text_ends[n_good - 1])], n_good)
        n_good = min(n_good, leading(np.isfinite(values).all(axis=0)))
        if n_good:
            n_good = min(n_good, leading(check.times_ok(values[self.time_index, :n_good])))
        if n_good == 0:
            return None, 0, position + int(line_ends[0]) + 1
        values = values[:, :n_good]
        columns = {"time_s": values[self.time_index],
                   **{name: values[i] for i, name in enumerate(self.header) if i != self.time_index}}
        check.last_time_s = float(values[self.time_index, -1])
        return SampleBlock(columns), int(line_ends[n_good - 1]) + 1, 0

    def _shapes_ok(self, text: bytes, lengths: np.ndarray) -> np.ndarray:
        """Per line: only number bytes, the header's number of cells, not too long."""
        codes = np.frombuffer(text, dtype=np.uint8)
        line_ends = np.flatnonzero(codes == 10)
        n_lines = len(line_ends)
        bad = np.bincount(np.searchsorted(line_ends, np.flatnonzero(~_ALLOWED[codes])), minlength=n_lines)
        commas = np.bincount(np.searchsorted(line_ends, np.flatnonzero(codes == 44)), minlength=n_lines)
        return (bad[:n_lines] == 0) & (commas[:n_lines] == self.n_cells - 1) & (lengths <= self.max_line_bytes)

    def _values(self, lines: bytes, n_lines: int) -> tuple[np.ndarray, int]:
        """The cells of ``n_lines`` lines (each of the right shape; the last without its b"\\n") as float64, one
        row a column, and how many lines they are: up to the first with a cell ``float`` refuses."""
        cells = lines.replace(b"\n", b",").split(b",")
        try:
            values = np.fromiter(map(float, cells), dtype=np.float64, count=len(cells))
        except ValueError:  # a cell that is not a number: the lines before the first one
            parsed = []
            for cell in cells:
                try:
                    parsed.append(float(cell))
                except ValueError:
                    break
            n_lines = len(parsed) // self.n_cells
            values = np.array(parsed[:n_lines * self.n_cells])
        return values.reshape(n_lines, self.n_cells).T.copy(), n_lines


def _next_run(good: np.ndarray, line_ends: np.ndarray, start: int) -> int:
    """Bytes (from the first line) up to the first of ``MIN_RUN_LINES`` good lines in a row after line ``start``,
    else to the end of the last line."""
    n = len(good)
    if n - start - 1 >= MIN_RUN_LINES:
        # runs[i]: good lines in a row from line i on
        window = np.convolve(good[start + 1:].astype(np.int32), np.ones(MIN_RUN_LINES, dtype=np.int32), "valid")
        found = np.flatnonzero(window == MIN_RUN_LINES)
        if len(found):
            first = start + 1 + int(found[0])
            return int(line_ends[first - 1]) + 1
    return int(line_ends[-1]) + 1
