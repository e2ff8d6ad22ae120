"""A steady sample clock estimated from the stamps: jitter and drift ignored, a rate change found, causally.

The feature filters run at one sample period at a time (``lfilter``, fixed coefficients). Stamp
jitter of +-30 % of the period and clock drift of 1 % cost nothing that way (1.00x on the
simulator, ``gyronet.analysis.rate_table``), while a rate that changes inside a recording (10 Hz, then
20 Hz) bends every dT/dt: features run at the wrong period. ``RateWatch`` finds such a change
from the stamps alone, as a time-sync filter would: the mean interval over ``SPAN`` intervals
(stamp jitter averages out, it telescopes) is compared with the current period, and a change is
declared where more than half of the last ``VOTES`` such spans lie more than ``TOLERANCE`` off on
the same side. A span votes only when its median interval (more than half of its intervals) is
off on that side too: lost samples lengthen the mean but not the median, stamp jitter moves the
median but not the mean, and a real rate change moves both. The new period is the mean interval since the first vote for it, or
exactly the nominal one when within the tolerance of it; ``SPAN`` rows later, unless snapped, it is
refined to the mean interval of those rows (a rate twice as fast is adopted after 8 intervals, whose
mean under +-25 % stamp jitter can miss the period by 6 %, inside the tolerance, so no vote corrects it).

The same votes are computed for a block (numpy) and one sample (plain floats, the live path), in
the same float64 operations, so a recording and a stream chunked any way find the same changes at
the same rows. The C compensator repeats them in double, but for the refinement: it cannot follow a
rate, so it flags the first change off the bundle's rate for good.
"""
from __future__ import annotations

import logging
import math
from collections import deque
from typing import NamedTuple

import numpy as np

log = logging.getLogger(__name__)

SPAN = 32  # intervals per span: stamp jitter of +-30 % of a period is at most 0.6 / 32 = 1.9 % of a span
VOTES = 32  # spans voting: a change is declared SPAN + VOTES / 2 samples after it, at the latest
TOLERANCE = 0.05  # a span this far off (relative) votes for a change; the bundle's own rate tolerance
# a rate at least twice as fast is plain sooner: FAST intervals in a row under half the period and above 0 (no loss
# makes an interval shorter, and jitter of +-30 % cannot make FAST of them in a row that short)
FAST = 8
FAST_FACTOR = 0.5
REFINED = 1e-6  # a refined period this close to the adopted one is no change
# an interval this many adopted periods long is a lost sample: stamp jitter of +-30 % makes an interval at
# most 1.6 periods, and an 8-interval estimate misses the period by at most 7.5 %: 1.6 / 0.925 = 1.73
LOST = 1.75


class RateChange(NamedTuple):
    """A rate change found at ``row`` (counted from the reset, 0-based); it began at most ``SPAN``
    rows before ``since_row``, the first row that voted for it. ``refined``: the last change's period,
    estimated again from the ``SPAN`` rows since it."""

    row: int
    time_s: float
    old_hz: float
    new_hz: float
    since_row: int
    since_time_s: float
    refined: bool = False


class RateWatch:
    """Causal estimate of the sample period from the stamps; reports where it changes.

    Parameters
    ----------
    fs_hz
        The nominal rate (the bundle's, or the data's): the period it starts at.
    snap_hz
        The rate a new one snaps to when within ``TOLERANCE`` of it (default ``fs_hz``): the
        bundle's. A data rate adopted by ``resample=true`` is a median over the whole file, which
        a part at another rate pulls off the true one, so it is not snapped to.
    """

    def __init__(self, fs_hz: float, snap_hz: float | None = None):
        self.nominal_s = 1.0 / float(fs_hz)
        self.snap_s = self.nominal_s if snap_hz is None else 1.0 / float(snap_hz)
        self.reset()

    def reset(self) -> None:
        """Forget the past: the nominal period, no samples seen."""
        self.period_s = self.nominal_s
        self.n_rows = 0  # rows seen since reset
        self._since = 0  # rows since the last change (or reset)
        self._times: deque[float] = deque(maxlen=SPAN + 1)
        self._votes: deque[int] = deque(maxlen=VOTES)  # +1 slow, -1 fast, 0 in tolerance or no vote
        self._vote_times: deque[float] = deque(maxlen=VOTES)  # the stamp of each voting row
        self._refine = False  # the period adopted at the last change is an estimate: refine it at SPAN rows

    def _vote(self, intervals_s: list[float], total_s: float) -> int:
        """+1 (slower), -1 (faster) or 0 for one span: its mean and its median both off on that side."""
        high_s, low_s = self.period_s * (1.0 + TOLERANCE), self.period_s * (1.0 - TOLERANCE)
        span_s = total_s / SPAN
        if span_s > high_s and 2 * sum(i > high_s for i in intervals_s) > SPAN:
            return 1
        return -1 if span_s < low_s and 2 * sum(i < low_s for i in intervals_s) > SPAN else 0

    def _decide(self, row: int, time_s: float) -> RateChange | None:
        """After a vote: the change, if the latest ``VOTES`` spans say so (and then the new period)."""
        if len(self._votes) < VOTES:
            return None
        slow, fast = self._votes.count(1), self._votes.count(-1)
        if max(slow, fast) * 2 <= VOTES:
            return None
        # every row since the first vote for the change is past it: their mean interval is the new period
        first = list(self._votes).index(1 if slow > fast else -1)
        times = list(self._vote_times)
        new_s = (times[-1] - times[first]) / (len(times) - 1 - first)
        return self._change(row, time_s, new_s, row - (len(times) - 1 - first), times[first])

    def _change(self, row: int, time_s: float, new_s: float, since_row: int, since_time_s: float,
                refined: bool = False) -> RateChange | None:
        """Adopt the period ``new_s`` (the snap one if within the tolerance of it) from ``row`` on; None (nothing
        changed) if ``new_s`` is no period: stamps that repeat or step back."""
        if not new_s > 0.0:
            return None
        snapped = abs(new_s / self.snap_s - 1.0) <= TOLERANCE
        if snapped:
            new_s = self.snap_s
        self._refine = not (refined or snapped)
        change = RateChange(row, time_s, 1.0 / self.period_s, 1.0 / new_s, since_row, since_time_s, refined)
        self.period_s = new_s
        self._since = 0
        self._votes.clear()
        self._vote_times.clear()
        return change

    def step(self, time_s: float) -> RateChange | None:
        """One sample's stamp: the change it completes, or None."""
        time_s = time_s if math.isfinite(time_s) else math.nan  # +-inf is no time either: no interval, no vote
        row = self.n_rows
        self.n_rows += 1
        self._times.append(time_s)
        self._since += 1
        change = None
        if self._refine and self._since == SPAN:
            change = self._refined(row, time_s)
        elif self._since > SPAN:
            times = list(self._times)
            self._votes.append(self._vote([b - a for a, b in zip(times, times[1:])], times[-1] - times[0]))
            self._vote_times.append(time_s)
            change = self._decide(row, time_s)
        if change is None and self._since > FAST:
            times = list(self._times)[-(FAST + 1):]
            half_s = 0.5 * FAST_FACTOR * self.period_s  # 0 < interval < FAST_FACTOR periods (a repeat is no rate)
            if all(abs(b - a - half_s) < half_s for a, b in zip(times, times[1:])):
                change = self._change(row, time_s, (times[-1] - times[0]) / FAST, row - FAST, times[0])
        return change

    def _refined(self, row: int, time_s: float) -> RateChange | None:
        """SPAN rows after a change: the mean interval they show (the change's own estimate had 8-32 intervals;
        stamp jitter of +-30 % is at most 0.6 / SPAN = 1.9 % here), unless a sample was lost among them."""
        self._refine = False
        times = list(self._times)
        new_s = (times[-1] - times[0]) / SPAN
        lost = any(b - a > LOST * self.period_s for a, b in zip(times, times[1:]))
        if lost or abs(new_s / self.period_s - 1.0) < REFINED:
            return None
        return self._change(row, time_s, new_s, row - SPAN, times[0], refined=True)

    def scan(self, time_s: np.ndarray) -> list[RateChange]:
        """The changes in a block of stamps: what ``step`` on each would report, vectorised."""
        time_s = np.asarray(time_s, dtype=np.float64)
        time_s = np.where(np.isfinite(time_s), time_s, np.nan)  # as step takes them
        changes: list[RateChange] = []
        pos, n, window = 0, len(time_s), 1024
        while pos < n:
            # a growing window: a block without a change costs O(n) once, each change O(1024)
            block = time_s[pos:pos + window]
            has_span, vote, fast_hit = self._block_votes(block)
            votes = np.concatenate([np.array(self._votes, dtype=np.int64), vote[has_span]])
            slow = np.concatenate([[0], np.cumsum(votes == 1)])
            fast = np.concatenate([[0], np.cumsum(votes == -1)])
            cast = len(self._votes) + np.cumsum(has_span)  # votes in the window after each row
            low = np.clip(cast - VOTES, 0, None)
            decides = has_span & (cast - low >= VOTES) & \
                (np.maximum(slow[cast] - slow[low], fast[cast] - fast[low]) * 2 > VOTES)
            refine_hit = self._refine & (self._since + np.arange(1, len(block) + 1) == SPAN)
            hits = np.flatnonzero(decides | fast_hit | refine_hit)
            upto = len(block) if len(hits) == 0 else int(hits[0])
            self._commit(block[:upto], has_span[:upto], vote[:upto])
            change = None
            if len(hits):  # the deciding row, by the scalar code
                change = self.step(float(block[upto]))
                # the vectorised votes and the deques agree; None: no refinement needed, or no period (stamps back)
                assert change is not None or refine_hit[upto] or decides[upto]
                if change is not None:
                    changes.append(change)
                upto += 1
            window = 1024 if len(hits) else 2 * window
            pos += upto
            if len(hits) and change is None:  # stamps that stop: every next row is a hit that decides nothing,
                tail = time_s[pos:pos + 1024]  # where the scalar code is cheaper than a window a row
                changes += [found for found in map(self.step, tail.tolist()) if found is not None]
                pos += len(tail)
        return changes

    def _block_votes(self, time_s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per new row at the current period: whether it votes, its vote (as ``_vote``), and whether it
        ends FAST short intervals (``step``'s fast path)."""
        past = np.array(self._times, dtype=np.float64)
        times = np.concatenate([past, time_s])
        ends = np.arange(len(past), len(times))
        since = self._since + np.arange(1, len(time_s) + 1)
        has_span = since > SPAN
        start = np.clip(ends - SPAN, 0, None)
        with np.errstate(invalid="ignore"):  # a stamp that is no time: NaN spans and intervals, which vote nothing
            span_s = (times[ends] - times[start]) / SPAN
            intervals = np.diff(times)
        high_s, low_s = self.period_s * (1.0 + TOLERANCE), self.period_s * (1.0 - TOLERANCE)
        # intervals above / below the band among the SPAN ending at each row: differences of running counts
        above = np.concatenate([[0], np.cumsum(intervals > high_s)])
        below = np.concatenate([[0], np.cumsum(intervals < low_s)])
        slow = (span_s > high_s) & (2 * (above[ends] - above[start]) > SPAN)
        fast = (span_s < low_s) & (2 * (below[ends] - below[start]) > SPAN)
        half_s = 0.5 * FAST_FACTOR * self.period_s  # 0 < interval < FAST_FACTOR periods, as step tests it
        short = np.concatenate([[0], np.cumsum(np.abs(intervals - half_s) < half_s)])
        fast_start = np.clip(ends - FAST, 0, None)
        fast_hit = (since > FAST) & (short[ends] - short[fast_start] == FAST)
        return has_span, np.where(slow, 1, np.where(fast, -1, 0)), fast_hit

    def _commit(self, time_s: np.ndarray, has_span: np.ndarray, vote: np.ndarray) -> None:
        """Take in rows whose votes are known: the state ``step`` on each would leave (but the decision)."""
        self.n_rows += len(time_s)
        self._since += len(time_s)
        self._times.extend(time_s[-(SPAN + 1):].tolist())
        self._votes.extend(vote[has_span][-VOTES:].tolist())
        self._vote_times.extend(time_s[has_span][-VOTES:].tolist())


def first_rate_change(time_s: np.ndarray, fs_hz: float) -> RateChange | None:
    """The first change in a record's stamps to a rate more than ``TOLERANCE`` off ``fs_hz``, or None (a file
    that needs one rate: the Kalman stage's identification, an Allan curve)."""
    return next((c for c in RateWatch(fs_hz).scan(time_s) if abs(c.new_hz / fs_hz - 1.0) > TOLERANCE), None)
