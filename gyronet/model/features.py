"""Causal drift-model inputs, computed from samples up to now by one stateful extractor.

The batch path (training, ``compensate.py``) and the live path (``stream.py``) call the same
``FeatureExtractor.process`` with the same state, on a whole recording, on chunks of any size or
on one sample at a time, and get the same numbers. Every filter (``gyronet.model.filters``) is a linear
recursion run by ``scipy.signal.lfilter`` with explicit state, so a chunk of one sample costs
microseconds and a recording of a million samples costs milliseconds.

Lost samples and glitches:

- an interval longer than ``GAP_FACTOR`` sample periods is a gap. dT/dt predicts through a gap
  up to its time constant and restarts from the mean slope over a longer one; a lag relaxes over
  the gap exactly; no restart divides an error by the gap, so no loss pattern can make a feature
  diverge;
- a row whose temperature is impossible (outside the sensor's range, or a jump no thermal mass
  allows: ``gyronet.recordings.guard``) or that holds a NaN (or a stamp that is no time) is a lost
  sample too: it never enters a filter's state and its features are the prediction, so a glitch
  corrupts its own row only, flagged in ``rejected``. A step that later samples confirm restarts
  every filter.

Rates: the filters run at a steady sample clock estimated from the stamps (``gyronet.recordings.rate_watch``):
jitter and drift of the stamps are averaged out, and where the rate changes the filters are
rebuilt for the new period (same time constants in seconds) and carry their state over as across
a short gap, unless ``on_rate_change`` refuses the change (it may raise).

A feature is a small dict (a "spec", :mod:`gyronet.model.feature_specs` lists the kinds) that
``meta.json`` stores, so a bundle rebuilds exactly the extractor it was trained with.
"""
from __future__ import annotations

import logging
import math
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from gyronet.model.feature_specs import (PAPER_FEATURES, PRIOR_TEMP_C, feature_name, play_operator,
                                         power_on_rows, required_columns)
from gyronet.model.feature_kinds import row_values, segment_values
from gyronet.model.filters import Lag, LaggedRate, RateTracker
from gyronet.recordings.data import GAP_FACTOR
from gyronet.recordings.guard import MAX_TEMP_RATE_C_PER_S, TempGuard, in_sensor_range
from gyronet.recordings.rate_watch import RateChange, RateWatch

log = logging.getLogger(__name__)


class FeatureExtractor:
    """Turn recording columns into model inputs, causally, keeping state between calls.

    Parameters
    ----------
    specs
        Feature specs (see the module docstring); order is the column order of the output.
    fs_hz
        Nominal sampling rate the filters are designed for. An interval longer than
        ``GAP_FACTOR / fs_hz`` is a gap: each filter bridges or restarts (see ``Lag`` and
        ``RateTracker``); none carries an error over amplified.
    on_rate_change
        Called with each ``RateChange`` before the filters follow it; it may raise to refuse it.
        None: follow every change. ``rate_changes`` lists those since ``reset()``.

    Notes
    -----
    A row that ``gyronet.recordings.guard.TempGuard`` rejects (temperature outside the sensor's range or
    jumping faster than any thermal mass allows, or a NaN in any input) is a lost sample: it
    never enters a filter's state, and its features are the prediction, those of the last
    accepted row (time features at its own time). ``rejected`` holds the mask of the last call,
    ``n_rejected`` the count since ``reset()``.
    """

    def __init__(self, specs: Sequence[Mapping[str, Any]], fs_hz: float,
                 on_rate_change: Callable[[RateChange], None] | None = None, snap_hz: float | None = None):
        self.specs = [dict(s) for s in specs]
        self.names = [feature_name(s) for s in self.specs]
        if len(set(self.names)) != len(self.names):
            raise ValueError(f"duplicate feature names in {self.names}")
        self.fs_hz = float(fs_hz)
        self.dt_s = 1.0 / self.fs_hz
        self.columns = required_columns(self.specs)
        self._row_columns = [k for k in self.columns if k != "time_s"]
        self._filters: dict[int, Any] = {}
        self._play: dict[int, float] = {}
        self._time_index = [i for i, s in enumerate(self.specs) if s["kind"] == "time"]
        self.guard = TempGuard()
        self.watch = RateWatch(self.fs_hz, snap_hz)  # snap_hz: the bundle's rate when resampling
        self.on_rate_change = on_rate_change
        self.reset()

    def reset(self) -> None:
        """Forget the past, as at power-on."""
        self._last_time_s: float | None = None  # of the last accepted row
        self._start_time_s: float | None = None
        self._last_row: list[float] | None = None  # features of the last accepted row
        self.guard.reset()
        self.dt_s = 1.0 / self.fs_hz
        self.watch.reset()
        self.rate_changes: list[RateChange] = []
        self._rate_gap = False  # the next accepted row starts a segment at a new period
        self.rejected = np.zeros(0, dtype=bool)
        self.n_rejected = 0
        self._filters.clear()
        self._play.clear()
        unlagged: dict[tuple[str, float], RateTracker] = {}  # a lagged rate reads these rather than run its own
        for i, spec in enumerate(self.specs):
            if spec["kind"] == "rate":
                source, tau_s = spec.get("source", "temp_c"), float(spec.get("tau_s", 5.0))
                max_slope = MAX_TEMP_RATE_C_PER_S if source == "temp_c" else math.inf
                if float(spec.get("lag_s", 0.0)) > 0:
                    shared = unlagged.get((source, tau_s))
                    tracker = shared or RateTracker(tau_s, self.dt_s, max_slope)
                    self._filters[i] = LaggedRate(tracker, Lag(float(spec["lag_s"]), self.dt_s), shared is not None)
                else:
                    self._filters[i] = unlagged.setdefault((source, tau_s), RateTracker(tau_s, self.dt_s, max_slope))
            elif spec["kind"] == "lag" or (spec["kind"] == "column" and float(spec.get("tau_s", 0)) > 0):
                self._filters[i] = Lag(float(spec["tau_s"]), self.dt_s)

    def process(self, columns: Mapping[str, np.ndarray]) -> np.ndarray:
        """Features of the next samples.

        Parameters
        ----------
        columns
            At least ``self.columns``, each of shape (n,), in time order, continuing the previous call.

        Returns
        -------
        np.ndarray
            Shape (n, len(self.names)), float64. ``self.rejected`` (n,) marks the rows taken as lost.
        """
        time_s = np.asarray(columns["time_s"], dtype=np.float64)
        n = len(time_s)
        out = np.empty((n, len(self.specs)))
        if n == 0:
            self.rejected = np.zeros(0, dtype=bool)
            return out
        if n == 1:
            return self._process_one(float(time_s[0]), {k: float(columns[k][0]) for k in self._row_columns})
        first_row = self.watch.n_rows
        changes = self.watch.scan(time_s)
        if not changes:
            return self._process_block(time_s, columns, out)
        edges = [0, *[c.row - first_row for c in changes], n]
        rejected = []
        for change, start, stop in zip([None, *changes], edges[:-1], edges[1:]):
            if change is not None:
                self._follow(change)
            if stop > start:
                piece = {k: np.asarray(columns[k])[start:stop] for k in self.columns}
                out[start:stop] = self._process_block(time_s[start:stop], piece, out[start:stop])
                rejected.append(self.rejected)
        self.rejected = np.concatenate(rejected)
        return out

    def _follow(self, change: RateChange) -> None:
        """Run the filters at the new period from this row on (``on_rate_change`` may refuse: raise)."""
        if self.on_rate_change is not None:
            self.on_rate_change(change)
        log.info("the sampling rate %s from %.6g to %.6g Hz at time_s=%.6f: the feature filters follow",
                 "estimate is refined" if change.refined else "changes", change.old_hz, change.new_hz, change.time_s)
        self.rate_changes.append(change)
        self.dt_s = 1.0 / change.new_hz
        rebuilt: dict[int, Any] = {}  # id(old) -> new, so a shared tracker stays shared
        for i, old in self._filters.items():
            self._filters[i] = self._rebuilt(old, rebuilt)
        self._rate_gap = self._last_time_s is not None

    def _rebuilt(self, old: Any, rebuilt: dict[int, Any]) -> Any:
        """A filter at the new period carrying ``old``'s state over as across a short gap (once per object)."""
        if id(old) in rebuilt:
            return rebuilt[id(old)]
        if isinstance(old, LaggedRate):
            new = LaggedRate(self._rebuilt(old.tracker, rebuilt), self._rebuilt(old.lag, rebuilt), old.shared)
        elif isinstance(old, Lag):
            new = Lag(old.tau_s, self.dt_s)
            new.last_y = old.last_y
        else:
            new = RateTracker(old.tau_s, self.dt_s, old.max_slope)
            new.last_level, new.last_slope = old.last_level, old.last_slope
        rebuilt[id(old)] = new
        return new

    def _process_block(self, time_s: np.ndarray, columns: Mapping[str, np.ndarray], out: np.ndarray) -> np.ndarray:
        """``process`` on rows of one sample period."""
        n = len(time_s)
        clock_from = 0 if self._start_time_s is not None else int(np.argmax(np.append(np.isfinite(time_s), True)))
        if clock_from < n and self._start_time_s is None:  # the clock starts at the first finite stamp
            self._start_time_s = float(time_s[clock_from])
        source = {k: np.asarray(columns[k], dtype=np.float64) for k in self.columns if k != "time_s"}
        others = [v for k, v in source.items() if k != "temp_c"]
        # a stamp that is no time (NaN, inf) is a lost sample as a NaN reading is
        finite = np.isfinite(time_s) & (np.isfinite(np.column_stack(others)).all(1) if others else True)
        accepted, step = self.guard.check(time_s, source["temp_c"], finite)
        carry, carry_time_s = self._last_row, self._last_time_s
        if accepted.all():
            self._run_accepted(time_s, source, step, out)
        else:
            keep = np.flatnonzero(accepted)
            if len(keep):
                out[keep] = self._run_accepted(time_s[keep], {k: v[keep] for k, v in source.items()}, step[keep],
                                               np.empty((len(keep), len(self.specs))))
            self._fill_rejected(out, accepted, carry, source)
        self._time_features(time_s[clock_from:], out[clock_from:], accepted[clock_from:], carry_time_s)
        self.rejected = ~accepted
        self.n_rejected += n - int(accepted.sum())
        return out

    def _process_one(self, time_s: float, values: dict[str, float]) -> np.ndarray:
        """``process`` for one live sample, in plain floats: the same operations as a block."""
        row, rejected = self.process_row(time_s, values)
        self.rejected = np.array([rejected])
        return np.array([row])

    def process_row(self, time_s: float, values: Mapping[str, float]) -> tuple[list[float], bool]:
        """One sample in plain floats (``values``: at least ``self.columns`` but ``time_s``): its features and
        whether it was rejected. ``process`` on a one-row chunk, without arrays (``self.rejected`` is not set)."""
        if self._start_time_s is None and math.isfinite(time_s):
            self._start_time_s = time_s
        change = self.watch.step(time_s)
        if change is not None:
            self._follow(change)
        temp_c = values["temp_c"]
        valid = in_sensor_range(temp_c) and math.isfinite(time_s) and \
            all(math.isfinite(values[k]) for k in self._row_columns)
        accepted, step = self.guard.step(time_s, temp_c, valid)
        if accepted:
            gap_s = None if self._last_time_s is None else time_s - self._last_time_s
            event = "power_on" if gap_s is None or step else \
                ("gap" if gap_s > GAP_FACTOR * self.dt_s or self._rate_gap else None)
            self._rate_gap = False
            row = row_values(self.specs, self.names, self._filters, self._run_play, values, event,
                             None if event == "power_on" else gap_s)
            self._last_time_s, self._last_row = time_s, row
            row = list(row)
        elif self._last_row is not None:
            row = list(self._last_row)
        else:
            row = power_on_rows(self.specs, {k: np.array([values[k]]) for k in self._row_columns})[0].tolist()
        if self._time_index:  # as in a block
            one = np.array([row])
            self._time_features(np.array([time_s]), one, np.array([accepted]), self._last_time_s)
            row = one[0].tolist()
        self.n_rejected += not accepted
        return row, not accepted

    def _time_features(self, time_s: np.ndarray, out: np.ndarray, accepted: np.ndarray,
                       carry_time_s: float | None) -> None:
        """Time features at each row's time; a stamp that is no time takes the last accepted one's (carry_time_s)."""
        if not self._time_index or self._start_time_s is None:
            return
        clock_s = time_s
        if not np.isfinite(time_s).all():
            previous = np.maximum.accumulate(np.where(accepted, np.arange(len(time_s)), -1))
            last_good_s = np.where(previous >= 0, time_s[np.maximum(previous, 0)],
                                   self._start_time_s if carry_time_s is None else carry_time_s)
            clock_s = np.where(np.isfinite(time_s), time_s, last_good_s)
        elapsed_s = clock_s - self._start_time_s
        for i in self._time_index:  # hours since the start, or a decay with tau_s from it
            tau_s = self.specs[i].get("tau_s")
            out[:, i] = np.exp(-elapsed_s / float(tau_s)) if tau_s else elapsed_s / 3600.0

    def _run_accepted(self, time_s: np.ndarray, source: Mapping[str, np.ndarray], step: np.ndarray,
                      out: np.ndarray) -> np.ndarray:
        """Run the filters over accepted rows: segments between gaps and confirmed steps."""
        first_gap_s = None if self._last_time_s is None else float(time_s[0]) - self._last_time_s
        if len(time_s) == 1:
            edges = [0, 1]
        else:
            breaks = np.flatnonzero((np.diff(time_s) > GAP_FACTOR * self.dt_s) | step[1:]) + 1
            edges = [0, *breaks.tolist(), len(time_s)]
        for start, stop in zip(edges[:-1], edges[1:]):
            gap_s = first_gap_s if start == 0 else float(time_s[start] - time_s[start - 1])
            if gap_s is None or step[start]:
                event = "power_on"
            else:
                event = "gap" if gap_s > GAP_FACTOR * self.dt_s or (start == 0 and self._rate_gap) else None
            chunk = {k: v[start:stop] for k, v in source.items()}
            out[start:stop] = segment_values(self.specs, self.names, self._filters, self._run_play, chunk, event, gap_s)
        self._rate_gap = False
        self._last_time_s = float(time_s[-1])
        self._last_row = out[-1].tolist()
        return out

    def _fill_rejected(self, out: np.ndarray, accepted: np.ndarray, carry: np.ndarray | None,
                       source: Mapping[str, np.ndarray]) -> None:
        """Rejected rows get the last accepted row's features (this call's or the one before)."""
        previous = np.maximum.accumulate(np.where(accepted, np.arange(len(accepted)), -1))
        later = ~accepted & (previous >= 0)
        out[later] = out[previous[later]]
        before = ~accepted & (previous < 0)
        if before.any():
            out[before] = carry if carry is not None else power_on_rows(self.specs, {k: v[before] for k, v in source.items()})

    def _run_play(self, i: int, x: np.ndarray, width: float, power_on: bool) -> np.ndarray:
        """Play operator, its state kept per feature between calls."""
        out, self._play[i] = play_operator(float(x[0]) if power_on or i not in self._play else self._play[i], x, width)
        return out


__all__ = ["FeatureExtractor", "GAP_FACTOR", "PAPER_FEATURES", "PRIOR_TEMP_C", "feature_name", "required_columns"]
