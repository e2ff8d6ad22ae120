"""``allan.py``'s recalibration check as the stream goes: 60 s means of the compensated rate against their bar.

On a still sensor (what the live Allan monitor assumes too) every finished 60 s block of the
compensated rate, from the end of the start-up window on, is held against its mean ``drift_sigma``
with the white noise of a 60 s mean added (``gyronet.model.recalibration.judge_blocks``, the same rule as
``allan.py`` on the output file). An axis that asks for a new calibration is named in one warning
when it first does over a full hour (a shorter record is judged whole, as ``allan.py`` does, but a
few blocks looked at every minute would cry wolf); the figures go to TensorBoard
(``recalibration/worst_hour_<axis>``) and the summary. A sample costs a few float additions (1.7 us);
the judgement, once a minute (once a chunk in a flood), 0.4 ms on a day of blocks, 4 ms on a month.
"""
from __future__ import annotations

import logging
from typing import Any

import numpy as np

from gyronet.model.error_bar import BLOCK_S
from gyronet.model.recalibration import HOUR_S, SUB_S, SubMeans, judge_blocks, summary_line
from gyronet.recordings.data import AXES

log = logging.getLogger(__name__)


class LiveRecalibration:
    """60 s blocks of a still stream's compensated rate and bar, judged as each one ends.

    Parameters
    ----------
    still_s
        The start-up window, s (``startup.still_s``): blocks start when it ends.
    writer
        A TensorBoard ``SummaryWriter``, or None.
    """

    def __init__(self, still_s: float = 0.0, writer: Any = None, block_s: float = BLOCK_S):
        self.still_s, self.block_s, self.writer = float(still_s), float(block_s), writer
        self._origin_s: float | None = None  # the first sample's time: the results count from it, as check's
        self._grid_s: float | None = None  # where the blocks start: the end of the (latest) start-up window
        self._shift_s = 0.0  # added to the sensor's time: a restarted clock continues after a break
        self._last_s: float | None = None
        self._block = -1
        self._sums = [0.0] * 7  # rate x, y, z, sigma x, y, z, samples outside the trained temperatures
        self._count = 0
        self._previous: list | None = None  # the last rate, for the white noise's first differences
        self._diff_sq, self._n_diff = [0.0, 0.0, 0.0], 0
        self._subs = SubMeans(block_s)  # a block mean's white noise, from its 10 s means
        self._blocks = np.empty((64, 9))  # per block: start s, mean rate (3), sigma (3) and outside share, samples
        self._n = 0
        self.last: dict[str, dict[str, Any]] = {}
        self.asked: set[str] = set()

    def add(self, time_s: float, rate_dps: list, sigma_dps: list, outside: bool) -> None:
        """One row in plain floats (the live path's lone frame): a few additions."""
        time_s += self._shift_s
        if self._grid_s is None:
            self._begin(time_s)
        self._last_s = time_s
        if time_s < self._grid_s:
            return
        self._subs.add_row(int((time_s - self._grid_s) // SUB_S), rate_dps)
        block = int((time_s - self._grid_s) // self.block_s)
        if block != self._block:
            if self._close():
                self._judge()
            self._block = block
        self._sums = [total + v for total, v in zip(self._sums, (*rate_dps, *sigma_dps, outside))]
        self._count += 1
        if self._previous is not None:
            self._diff_sq = [total + (v - p) ** 2 for total, v, p in zip(self._diff_sq, rate_dps, self._previous)]
            self._n_diff += 1
        self._previous = rate_dps

    def add_many(self, time_s: np.ndarray, rate_dps: np.ndarray, sigma_dps: np.ndarray, outside: np.ndarray) -> None:
        """Rows (n,), (n, 3), (n, 3), (n,) in stream order: the blocks of ``add`` on each in turn, to rounding."""
        time_s = np.asarray(time_s, dtype=np.float64) + self._shift_s
        if not len(time_s):
            return
        if self._grid_s is None:
            self._begin(float(time_s[0]))
        self._last_s = float(time_s[-1])
        keep = time_s >= self._grid_s
        if not keep.any():
            return
        time_s, rate_dps = time_s[keep], np.asarray(rate_dps, dtype=np.float64)[keep]
        rows = np.column_stack([rate_dps, np.asarray(sigma_dps, dtype=np.float64)[keep], np.asarray(outside)[keep]])
        first = rate_dps[:1] if self._previous is None else np.array([self._previous], dtype=np.float64)
        steps = np.diff(rate_dps, axis=0, prepend=first)
        self._diff_sq = (np.asarray(self._diff_sq) + np.sum(steps ** 2, axis=0)).tolist()
        self._n_diff += len(steps) - (self._previous is None)
        self._previous = rate_dps[-1].tolist()
        self._subs.add(((time_s - self._grid_s) // SUB_S).astype(np.int64), rate_dps)
        index = ((time_s - self._grid_s) // self.block_s).astype(np.int64)
        starts = np.flatnonzero(np.concatenate([[True], index[1:] != index[:-1]]))
        sums, counts = np.add.reduceat(rows, starts, axis=0), np.diff(np.append(starts, len(index)))
        closed = False
        for block, total, count in zip(index[starts].tolist(), sums.tolist(), counts.tolist()):
            if block != self._block:
                closed |= self._close()
                self._block = block
            self._sums = [a + b for a, b in zip(self._sums, total)]
            self._count += count
        if closed:  # once a chunk: a flood of many blocks is judged at its end
            self._judge()

    def new_segment(self, next_time_s: float) -> None:
        """The sensor clock restarted, and with it the compensator's start-up window: blocks start again after it."""
        if self._last_s is None:
            return
        if self._close():
            self._judge()
        self._shift_s = self._last_s + self.block_s - next_time_s  # a block's break, then the new clock
        self._grid_s, self._block, self._previous = None, -1, None
        self._subs.close()
        self._subs.previous = None  # no pair across the break

    def _begin(self, time_s: float) -> None:
        """The first sample of a clock: the start-up window runs from it."""
        if self._origin_s is None:
            self._origin_s = time_s
        self._grid_s = time_s + self.still_s

    def finish(self) -> dict[str, dict[str, Any]]:
        """Judge the last full block too, log one line per axis, and return the figures (empty under two blocks)."""
        self._subs.close()
        if self._close():
            self._judge()
        for axis, result in self.last.items():
            log.info("recalibration check, live: %s", summary_line(axis, result))
        return self.last

    def _close(self) -> bool:
        """End the open block; True when it is kept (two samples or more)."""
        count, sums = self._count, self._sums
        self._count, self._sums = 0, [0.0] * 7
        if count < 2:
            return False
        if self._n == len(self._blocks):
            self._blocks = np.resize(self._blocks, (2 * self._n, 9))
        self._blocks[self._n] = [self._grid_s + self._block * self.block_s, *(v / count for v in sums), count]
        self._n += 1
        return True

    def _judge(self) -> None:
        """Judge the blocks so far that hold half the samples of a full one (as ``check``); warn, write TensorBoard."""
        if self._n_diff < 2:
            return
        blocks = self._blocks[:self._n]
        since_s = blocks[:, 0] - self._origin_s
        judged = judge_blocks(since_s, blocks[:, 1:8], blocks[:, 8], np.asarray(self._diff_sq) / self._n_diff,
                              self.block_s, sub_avar=self._subs.avar())
        if not judged:
            return
        self.last = judged
        for axis, result in self.last.items():
            if result["recalibrate"] and result["window_s"] >= HOUR_S and axis not in self.asked:
                self.asked.add(axis)
                log.warning("recalibration check, live: %s", summary_line(axis, result))
        if self.writer is not None:
            try:
                for axis in AXES:
                    self.writer.add_scalar(f"recalibration/worst_hour_{axis}", self.last[axis]["worst_hour_rms_ratio"],
                                           int(round(since_s[-1] + self.block_s)))
            except OSError as err:  # a full disk must not stop the compensation
                log.error("TensorBoard: cannot write the recalibration check (%s)", err)


__all__ = ["LiveRecalibration"]
