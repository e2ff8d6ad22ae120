"""Live Allan figures of the compensated rate: binned history, short gaps bridged, to TensorBoard.

Samples are averaged into bins of at least 0.1 s, so a 1 kHz stream keeps 10 values a second:
memory stays flat-ish (~1 MB/h) and a report takes milliseconds. A lost frame leaves a bin empty;
:func:`gyronet.allan.allan_report` never glues across a gap and would use only the longest
stretch without one (131 of 593 bins at 1 % frame loss). So a run of up to ``max_fill_s`` of
empty bins is bridged by linear interpolation between its neighbours before the report: a few
filled bins bias the short-tau deviation by about their share of the record (they carry no white
noise), where dropping the rest of the record would throw most of it away. Longer gaps (a port
down, a restarted sensor clock) stay breaks, and the report uses the longest stretch between them.
"""
from __future__ import annotations

import logging
import math
import os
import threading
from typing import Any

import numpy as np

from gyronet.recordings.data import AXES
from gyronet.errors import GyronetError
from gyronet.deploy.stream.allocator import trim_heap
from gyronet.deploy.stream.priority import normal_thread

log = logging.getLogger(__name__)


class LiveAllan:
    """Allan noise terms of the compensated rate, computed every ``every_s`` seconds of data.

    Parameters
    ----------
    writer
        A TensorBoard ``SummaryWriter`` (None: compute, log, keep the last report only).
    every_s
        Data seconds between reports.
    fs_hz
        Sampling rate of the stream, Hz.
    bin_s
        Averaging bin, s (default ``max(1 / fs_hz, 0.1)``).
    max_history_s
        History kept; past it the older half is dropped.
    max_fill_s
        Longest run of empty bins bridged, s (at least two bins).
    background
        Compute the reports due while streaming in a worker thread (at the lowest CPU priority), on
        the history as it was when each fell due, so that a report (up to ~0.1 s on a day of
        history) never holds up the next frame; one still running when the next falls due makes
        that one skipped. ``finish`` waits for it. False: in the caller's thread, at once.
    """

    def __init__(self, writer: Any, every_s: float, fs_hz: float, bin_s: float | None = None,
                 max_history_s: float = 86400.0, max_fill_s: float = 2.0, background: bool = False):
        self.writer, self.every_s, self.fs_hz = writer, float(every_s), float(fs_hz)
        self.bin_s = max(1.0 / self.fs_hz, 0.1) if bin_s is None else float(bin_s)
        self.max_bins = max(16, int(max_history_s / self.bin_s))
        self.max_fill_bins = max(2, int(round(max_fill_s / self.bin_s)))
        self._index = np.empty(1024, dtype=np.int64)
        self._rate_dps = np.empty((1024, 3))
        self._n = 0
        self._start_s: float | None = None
        self._shift_s = 0.0  # added to the sensor's time: a restarted clock continues after a break
        self._last_s: float | None = None
        self._bin = -1
        self._sum: list | np.ndarray = [0.0, 0.0, 0.0]  # of the open bin
        self._count = 0
        self.next_s: float | None = None
        self.last: dict[str, dict[str, float | None]] = {}
        self.bins: dict[str, int] = {}
        self.background = bool(background)
        self._worker: threading.Thread | None = None
        self.n_skipped = 0  # reports skipped because the one before was still running

    @property
    def time_s(self) -> np.ndarray:
        """Mid-times of the completed bins, s (on the monitor's own axis: see ``new_segment``)."""
        return self._start_s + (self._index[:self._n] + 0.5) * self.bin_s if self._n else np.empty(0)

    @property
    def rate_dps(self) -> np.ndarray:
        """Mean compensated rate of each completed bin, (n, 3), deg/s."""
        return self._rate_dps[:self._n]

    def add(self, time_s: float, rate_dps) -> None:
        """Add a sample (3 rates, deg/s) in plain floats; report when ``every_s`` of data has passed since the last report."""
        time_s = time_s + self._shift_s
        if self._start_s is None:
            self._start_s = float(time_s)
            self.next_s = time_s + self.every_s
        self._last_s = time_s
        # bin edges half a sample before the nominal ones: a sample on a regular grid never falls
        # on an edge, where float rounding would put two samples in one bin and none in the next
        index = int((time_s - self._start_s + 0.5 / self.fs_hz) // self.bin_s)
        if index != self._bin:
            self._close_bin()
            self._bin = index
        x, y, z = rate_dps
        total = self._sum
        self._sum = [total[0] + x, total[1] + y, total[2] + z]
        self._count += 1
        if time_s >= self.next_s:
            self._due(step=int(round(time_s - self._start_s)))
            self.next_s = time_s + self.every_s

    def add_many(self, time_s: np.ndarray, rate_dps: np.ndarray) -> None:
        """Add samples (n,) and (n, 3) in one go: the bins (to rounding) and reports of ``add`` on each in turn."""
        time_s = np.asarray(time_s, dtype=np.float64) + self._shift_s
        rate_dps = np.asarray(rate_dps, dtype=np.float64).reshape(-1, 3)
        if len(time_s) == 0:
            return
        if self._start_s is None:
            self._start_s = float(time_s[0])
            self.next_s = time_s[0] + self.every_s
        start = 0
        while start < len(time_s):
            # the first sample at or after next_s reports, once it is in its bin
            due = np.flatnonzero(time_s[start:] >= self.next_s)
            stop = start + int(due[0]) + 1 if len(due) else len(time_s)
            self._add_to_bins(time_s[start:stop], rate_dps[start:stop])
            self._last_s = float(time_s[stop - 1])
            if len(due):
                self._due(step=int(round(self._last_s - self._start_s)))
                self.next_s = self._last_s + self.every_s
            start = stop

    def new_segment(self, next_time_s: float) -> None:
        """The sensor clock restarted: the sample at ``next_time_s`` continues after a break."""
        if self._last_s is None:
            return
        self._close_bin()
        # one bin past the longest bridged gap: a break, never bridged
        self._shift_s = self._last_s + (self.max_fill_bins + 2) * self.bin_s - next_time_s

    def _close_bin(self) -> None:
        if self._count == 0:
            return
        self._append(np.array([self._bin]), (np.asarray(self._sum, dtype=np.float64) / self._count)[None])
        self._sum = [0.0, 0.0, 0.0]
        self._count = 0

    def _add_to_bins(self, time_s: np.ndarray, rate_dps: np.ndarray) -> None:
        """Sum samples (time increasing) into their bins; the last bin stays open, as in ``add``."""
        index = np.floor_divide(time_s - self._start_s + 0.5 / self.fs_hz, self.bin_s).astype(np.int64)
        starts = np.flatnonzero(np.concatenate([[True], index[1:] != index[:-1]]))
        counts = np.diff(np.append(starts, len(index)))
        first = 0
        if index[0] == self._bin:  # the open bin goes on
            self._sum = np.add.reduce(np.vstack([self._sum, rate_dps[:counts[0]]]), axis=0)
            self._count += int(counts[0])
            first = 1
        if first == len(starts):
            return
        self._close_bin()
        sums = np.add.reduceat(rate_dps, starts[first:], axis=0)
        # every run but the last is a complete bin; the last one is the new open bin
        self._append(index[starts[first:-1]], sums[:-1] / counts[first:-1, None])
        self._bin, self._sum, self._count = int(index[starts[-1]]), sums[-1].copy(), int(counts[-1])

    def _append(self, index: np.ndarray, means_dps: np.ndarray) -> None:
        """Append completed bins to the history, growing it, or dropping its older half once it holds ``max_bins``."""
        done = 0
        while done < len(index):
            if self._n == len(self._index):
                self._make_room()
            take = min(len(index) - done, len(self._index) - self._n)
            self._index[self._n:self._n + take] = index[done:done + take]
            self._rate_dps[self._n:self._n + take] = means_dps[done:done + take]
            self._n += take
            done += take

    def _make_room(self) -> None:
        if self._n >= self.max_bins:  # keep the newest half of the history
            # in new arrays, never in place: a background report may still read the old ones
            keep = self._n // 2
            index, rate_dps = np.empty_like(self._index), np.empty_like(self._rate_dps)
            index[:keep], rate_dps[:keep] = self._index[self._n - keep:self._n], self._rate_dps[self._n - keep:self._n]
            self._index, self._rate_dps, self._n = index, rate_dps, keep
        else:
            self._index = np.resize(self._index, 2 * self._n)
            self._rate_dps = np.resize(self._rate_dps, (2 * self._n, 3))

    def bridged(self) -> tuple[np.ndarray, np.ndarray, int]:
        """The longest stretch of bins with short gaps filled: mid-times, s, rates (n, 3), and how many were filled."""
        return self._bridged(self._index[:self._n], self._rate_dps[:self._n])

    def _bridged(self, index: np.ndarray, rate: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
        if len(index) < 2:
            return (self._start_s + (index + 0.5) * self.bin_s if len(index) else np.empty(0)), rate.copy(), 0
        steps = np.diff(index)
        breaks = np.flatnonzero(steps > self.max_fill_bins + 1) + 1
        edges = [0, *breaks.tolist(), len(index)]
        start, stop = max(zip(edges[:-1], edges[1:]), key=lambda s: index[s[1] - 1] - index[s[0]])
        index, rate = index[start:stop], rate[start:stop]
        full = np.arange(index[0], index[-1] + 1)
        filled = np.empty((len(full), 3))
        for axis in range(3):
            filled[:, axis] = np.interp(full, index, rate[:, axis])
        filled[index - index[0]] = rate  # the measured bins exactly as they are
        return self._start_s + (full + 0.5) * self.bin_s, filled, int(len(full) - len(index))

    def _due(self, step: int) -> None:
        """A report fell due: now, or in the worker on the history as it is now (views: it is only appended to).

        First the heap's free pages go back to the system: the last report's temporaries and the history's
        doublings leave them in the middle of the heap, where glibc keeps them (:mod:`.allocator`).
        """
        trim_heap()
        if not self.background:
            self.report(step)
            return
        if self._worker is not None and self._worker.is_alive():
            self.n_skipped += 1
            log.debug("Allan report at %d s skipped: the one before is still running", step)
            return
        history = (self._index[:self._n], self._rate_dps[:self._n])
        self._worker = threading.Thread(target=self._background_report, args=(step, history),
                                        name="live-allan", daemon=True)
        self._worker.start()

    def _background_report(self, step: int, history: tuple[np.ndarray, np.ndarray]) -> None:
        normal_thread()  # not the real-time priority a stream may run at: the reports must not delay frames
        try:
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), 19)  # this thread only (Linux)
        except (AttributeError, OSError):  # another OS: the thread runs at the stream's priority
            pass
        try:
            self.report(step, history=history)
        except Exception:  # noqa: BLE001 - a failed report must not stop the compensation
            log.exception("Allan report at %d s failed", step)

    def report(self, step: int, figure: bool = False, history: tuple[np.ndarray, np.ndarray] | None = None) -> None:
        """Compute N and B per axis on everything so far (or on ``history``: bin indices and means) and log
        them (and the curves, if asked)."""
        from gyronet.allan import allan_report

        time_s, rate_dps, n_filled = self.bridged() if history is None else self._bridged(*history)
        try:
            report = allan_report(time_s, rate_dps, 1.0 / self.bin_s)
        except GyronetError as err:  # too short so far
            log.debug("no Allan report yet: %s", err)
            return
        self.bins = {"used": int(len(time_s)), "filled": n_filled,
                     "measured": int(self._n if history is None else len(history[0]))}
        self.last = {axis: {"arw_deg_rthr": _finite_or_none(report[axis]["arw_deg_rthr"]),
                            "bias_instability_deg_hr": _finite_or_none(report[axis]["bias_instability_deg_hr"]),
                            # True: B is only an upper bound (the curve still falls at the last tau read)
                            "bias_instability_upper_bound": bool(report[axis]["bias_instability_upper_bound"])}
                     for axis in AXES}
        log.info("Allan at %d s of data (%d bins, %d of them filled): %s", step, len(time_s), n_filled, ", ".join(
            f"{axis}: N={_number(v['arw_deg_rthr'])} deg/rt-h B={'<=' if v['bias_instability_upper_bound'] else ''}"
            f"{_number(v['bias_instability_deg_hr'])} deg/h" for axis, v in self.last.items()))
        if self.writer is None:
            return
        try:
            self._to_tensorboard(report, step, figure)
        except OSError as err:  # a full disk must not stop the compensation
            log.error("TensorBoard: cannot write (%s); live Allan figures go to the log only", err)
            self.writer = None

    def _to_tensorboard(self, report: dict, step: int, figure: bool) -> None:
        from gyronet.allan import plot_allan

        for axis, values in self.last.items():
            for name, tag in (("arw_deg_rthr", "arw"), ("bias_instability_deg_hr", "bias_instability")):
                if values[name] is not None:
                    self.writer.add_scalar(f"allan/{tag}_{axis}", values[name], step)
            self.writer.add_scalar(f"allan/bias_instability_bound_{axis}", float(values["bias_instability_upper_bound"]),
                                   step)
        if figure:  # drawing takes a second or more: once, at the end, not between samples
            from gyronet.figures.tb import log_figure

            log_figure(self.writer, "allan/curves", plot_allan(report, title=f"live, {step} s of data"), step)
        self.writer.flush()

    def finish(self) -> None:
        """The last report, with the Allan curves as a figure (after a background one still running)."""
        if self._worker is not None:
            self._worker.join()
        self._close_bin()
        if self._n >= 3:
            self.report(step=int(round(self._last_s - self._start_s)), figure=True)


def _number(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.4g}"


def _finite_or_none(value: float) -> float | None:
    return float(value) if math.isfinite(value) else None
