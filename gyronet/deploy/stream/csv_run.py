"""A run of complete CSV sample lines read at once: the CSV flood's fast path.

In a flood a read holds hundreds of lines, and reading them one by one (decode, strip, split, a
dict, a ``SampleCheck`` call and a ``Sample`` each) was most of the stream's CPU. Here the
complete lines in the buffer are looked at together, once a read: only the bytes of plain numbers
(digits, ``.eE+-``), commas and line ends (``\\n`` or ``\\r\\n``), the header's number of cells a
line (what is left without the number bytes, compared in one go), at most ``max_line_bytes``
bytes a line. A run of at least ``MIN_RUN_LINES`` such lines has its cells read by ``float`` in
one pass (the per-line path's own reading of such a line, so every value is the same to the bit;
``float`` refuses what is not a number: ``1.2.3``, an empty cell, a lone sign), and the leading
lines whose values are finite and whose times pass the check (increasing, no clock restart)
become one ``SampleBlock``. The first line that fails anything goes to the per-line parser, which
makes its fault (or its new segment, or the header it changes), so faults and their order are
the per-line path's; a shorter run goes line by line too.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np

from gyronet.deploy.stream.events import SampleBlock, SampleCheck, leading

# fewer complete lines than this in the buffer (a lone line at 1 kHz) go line by line: below it the arrays'
# fixed cost is more than the per-line parse saves
MIN_RUN_LINES = 16
_NUMBER_BYTES = b"0123456789.eE+-"


@dataclass
class _Lines:
    """The complete lines of a buffer from ``base`` on, looked at once: where they are and which have a good shape."""

    base: int  # where in the buffer the first line starts
    starts: np.ndarray  # each line's first byte, in the buffer
    ends: np.ndarray  # each line's b"\n", in the buffer
    text: bytes  # the lines, b"\r\n" ends as b"\n"
    text_starts: np.ndarray  # each line's first byte in ``text``
    text_ends: np.ndarray  # each line's b"\n" in ``text``
    run: np.ndarray  # good lines in a row from each line on (0: the line's shape is not good)
    long_runs: np.ndarray  # the lines where at least MIN_RUN_LINES good lines start


class LineRun:
    """The block reading of sample lines of one header (built once per header).

    The lines of a buffer are looked at once, from the first ``decode`` after ``forget``; later calls
    (after the per-line parser took a bad line) start from there. The owner calls ``forget`` whenever
    the buffer changes.

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
        self._lines: _Lines | None = None

    def forget(self) -> None:
        """The buffer changed: look at its lines again at the next ``decode``."""
        self._lines = None

    def decode(self, buffer: bytearray, position: int, check: SampleCheck) -> tuple[SampleBlock | None, int, int]:
        """The good lines from ``position`` (a line's start) on, up to the first that is not: a block (or None),
        its bytes, and, when None, where to try again (the lines before that go one by one).

        ``check.took`` the last good line's time, as ``SampleCheck.check`` does.
        """
        lines = self._lines
        first = -1
        if lines is not None and lines.base <= position <= lines.ends[-1]:
            first = int(np.searchsorted(lines.starts, position))
            first = first if first < len(lines.starts) and lines.starts[first] == position else -1
        if first < 0:
            end = buffer.rfind(b"\n", position) + 1
            if end == 0 or buffer.count(b"\n", position, end) < MIN_RUN_LINES:
                return None, 0, max(end, position)
            lines, first = self._look(bytes(buffer[position:end]), position), 0
            self._lines = lines
        n_good = int(lines.run[first])
        if n_good < MIN_RUN_LINES:  # too short a run to be worth it: line by line up to the next long one
            later = np.searchsorted(lines.long_runs, first + 1)
            retry = lines.starts[lines.long_runs[later]] if later < len(lines.long_runs) else lines.ends[-1] + 1
            return None, 0, int(retry)
        last = first + n_good - 1
        values, n_good = self._values(lines.text[lines.text_starts[first]:lines.text_ends[last]], n_good)
        if not np.isfinite(values).all():  # (one test in the usual case)
            n_good = min(n_good, leading(np.isfinite(values).all(axis=0)))
        if n_good:
            n_good = min(n_good, leading(check.times_ok(values[self.time_index, :n_good])))
        if n_good == 0:
            return None, 0, int(lines.ends[first]) + 1
        values = values[:, :n_good]
        columns = {"time_s": values[self.time_index],
                   **{name: values[i] for i, name in enumerate(self.header) if i != self.time_index}}
        check.took(values[self.time_index, -1])
        return SampleBlock(columns), int(lines.ends[first + n_good - 1]) + 1 - position, 0

    def _look(self, raw: bytes, base: int) -> _Lines:
        """The complete lines ``raw`` (from ``base`` in the buffer): where they are, which have a good shape."""
        codes = np.frombuffer(raw, dtype=np.uint8)
        ends = np.flatnonzero(codes == 10)  # each line's b"\n" in raw
        lengths = np.empty_like(ends)  # as the per-line path counts them: b"\r" in, b"\n" not
        lengths[0], lengths[1:] = ends[0], ends[1:] - ends[:-1] - 1
        text, text_ends = raw, ends
        if b"\r" in raw:  # lines that end in b"\r\n" (as Arduino's println sends them) lose the b"\r"
            text = raw.replace(b"\r\n", b"\n")
            text_ends = ends - np.cumsum(codes[np.maximum(ends - 1, 0)] == 13)
        n_lines = len(ends)
        rest = text.translate(None, _NUMBER_BYTES)  # the commas, line ends and any byte not of a number
        if rest == self._shape * n_lines and lengths.max() <= self.max_line_bytes:
            good = np.ones(n_lines, dtype=bool)  # the usual case: every line of the right shape
        else:
            good = self._shapes_ok(rest, lengths)
        # good lines in a row from each line on: up to the next line that is not good
        bad = np.append(np.flatnonzero(~good), n_lines)
        run = bad[np.searchsorted(bad, np.arange(n_lines))] - np.arange(n_lines)
        starts = np.empty_like(ends)
        starts[0], starts[1:] = 0, ends[:-1] + 1
        text_starts = np.empty_like(text_ends)
        text_starts[0], text_starts[1:] = 0, text_ends[:-1] + 1
        return _Lines(base, starts + base, ends + base, text, text_starts, text_ends, run,
                      np.flatnonzero(run >= MIN_RUN_LINES))

    def _shapes_ok(self, rest: bytes, lengths: np.ndarray) -> np.ndarray:
        """Per line: only number bytes, the header's number of cells, not too long (``rest``: the lines without
        their number bytes)."""
        codes = np.frombuffer(rest, dtype=np.uint8)
        line_ends = np.flatnonzero(codes == 10)
        # commas counted up to each line end, then line by line; the other bytes are the rest of the line
        commas = np.cumsum(codes == 44)[line_ends]
        commas[1:] -= commas[:-1].copy()
        widths = line_ends.copy()
        widths[1:] -= line_ends[:-1]
        widths[0] += 1
        others = widths - commas - 1  # less the line's own b"\n"
        return (others == 0) & (commas == self.n_cells - 1) & (lengths <= self.max_line_bytes)

    def _values(self, lines: bytes, n_lines: int) -> tuple[np.ndarray, int]:
        """The cells of ``n_lines`` lines (each of the right shape; the last without its b"\\n") as float64, one
        row a column, and how many lines they are: up to the first with a cell ``float`` refuses."""
        text = lines.replace(b"\n", b",")
        values = _all_numbers(text, n_lines * self.n_cells)
        if values is not None:  # the usual case: every cell a number
            return values.reshape(n_lines, self.n_cells).T.copy(), n_lines
        cells = text.split(b",")
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


def _all_numbers(text: bytes, count: int) -> np.ndarray | None:
    """The ``count`` comma-separated cells of ``text`` read by numpy at once (0.7 us a line against 1.1 for ``float``
    on each cell; both round with ``PyOS_string_to_double``, so the values are the same to the bit), or None when
    numpy stops short of them (a cell it refuses, ``1_0`` which ``float`` takes): then ``float`` reads them."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # numpy's warning where it stops short
        try:
            values = np.fromstring(text, dtype=np.float64, sep=",")
        except ValueError:
            return None
    return values if len(values) == count else None
