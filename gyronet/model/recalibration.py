"""When to recalibrate: a compensated still record held against its own error bar.

On a still sensor, once its start-up offset is applied, a 60 s mean of the compensated rate is the
drift the bundle left plus the white noise of a 60 s mean; divided by its bar (the block's mean
``drift_sigma`` with that noise added) it is about 1 in RMS while the bar describes the sensor. An
axis asks for a new calibration when that RMS exceeds ``HOUR_RMS_LIMIT`` over some hour: its error
is more than twice what the bundle claims, because the sensor has aged or its history has left
what the training saw.

The limit is set by measurement (docs/guides/error-bars.md#when-to-recalibrate): on held-out
simulated histories whose bar is calibrated, the worst hour is 0.95-1.45 (18 axes); where the bar
is wrong, 2.35-8.87 (the real tag's next run on a one-run bar, 6 axes) and 3.16 (x on a history
beyond the trained temperatures). Counting blocks beyond 2 sigma instead (three in a row, or one in
ten over an hour) flagged 13 of the 18 calibrated axes: a drift error wanders slowly, so its blocks
leave the bar together.

The white noise of a 60 s mean, added to the bar, is measured from consecutive 10 s means within
each block (their Allan variance at 10 s, scaled to 60 s), not from first differences: a low-pass
(the Kalman stage, a sensor's own filter) thins first differences several times over but leaves a
60 s mean's noise as it was, and on `kalman=ar` output the first differences called a bar that
holds 2.2-4.1x too narrow. A record too slow for two samples in 10 s (under 0.2 Hz) falls back to them.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from gyronet.model.error_bar import BLOCK_S
from gyronet.recordings.data import AXES

HOUR_S = 3600.0
SUB_S = 10.0  # the sub-blocks whose consecutive means measure a block mean's white noise
HOUR_RMS_LIMIT = 2.0  # an hour's RMS of (block mean / its bar) above this: recalibrate
CALIBRATED_QUANTILES = (0.05, 0.95)  # the range a calibrated bar's share falls in on 90 % of runs


def calibrated_range(z: np.ndarray, draws: int = 2000, seed: int = 0) -> tuple[float, float]:
    """Where a bar that holds could put one run's within-1-sigma share, on 9 runs in 10 (5th, 95th percentile).

    ``z`` is one axis's block errors over their bar, in time order. A run's blocks share most of their
    error: a constant (the start-up offset's error, the model's mean error over the run) and a slow
    wander, so one run holds fewer independent blocks than it has blocks, and how large the constant
    is one run draws once. The draws keep the run's wander (``z`` less its mean: its autocorrelation,
    its variance up to 1) and give the constant whatever variance is left of 1. So the range is the
    widest a holding bar allows: a share below it says the bar is too narrow; one run cannot show a
    bar too wide, as a small constant is always possible.
    """
    z = np.asarray(z, dtype=np.float64)
    m = len(z)
    if m == 0 or not np.any(z):
        return float("nan"), float("nan")
    wander = z - z.mean()
    variance = float(np.mean(wander ** 2))
    scale = min(1.0, variance) / variance if variance > 0 else 0.0
    # circulant embedding of the wander's sample autocovariance (Dietrich & Newsam 1997): its eigenvalues are
    # the periodogram of the wander padded to 2m, never negative, so every draw is exact for lags under m
    eigen = scale * np.abs(np.fft.fft(wander, 2 * m)) ** 2 / m
    constant_sd = np.sqrt(max(0.0, 1.0 - variance))
    rng = np.random.default_rng(seed)
    shares = []
    for _ in range(0, draws, 100):  # 50 complex draws (100 real series) at a time: memory stays small on long runs
        noise = rng.standard_normal((50, 2 * m)) + 1j * rng.standard_normal((50, 2 * m))
        series = np.fft.fft(np.sqrt(eigen / (2 * m)) * noise, axis=1)[:, :m]
        series = np.concatenate([series.real, series.imag]) + constant_sd * rng.standard_normal((100, 1))
        shares.append(np.mean(np.abs(series) <= 1.0, axis=1))
    low, high = np.quantile(np.concatenate(shares), CALIBRATED_QUANTILES)
    return float(low), float(high)


def check(time_s: np.ndarray, rate_dps: np.ndarray, sigma_dps: np.ndarray, outside: np.ndarray | None = None,
          still_s: float = 0.0, block_s: float = BLOCK_S) -> dict[str, dict[str, Any]]:
    """Per axis: the share of blocks within 1 and 2 sigma (and the range of the first where the bar holds,
    ``calibrated_range``), the worst hour's RMS ratio, and the verdict.

    ``time_s, rate_dps, sigma_dps``: a compensated still record (true rate zero once its start-up
    offset is applied, from ``still_s`` s on) and its ``drift_sigma`` columns; ``outside``: its
    ``out_of_range`` flags. Blocks of ``block_s`` run from ``still_s`` on; a lost frame only thins
    its block, and a block needs half the samples of a full one. A record shorter than an hour is
    judged as a whole. Times in the result are seconds from the record's first sample; empty when
    fewer than two blocks remain.
    """
    time_s = np.asarray(time_s, dtype=np.float64)
    sigma_dps = np.asarray(sigma_dps, dtype=np.float64)
    keep = (time_s - time_s[0] >= still_s) & np.all(np.isfinite(sigma_dps), axis=1)
    since_s, rate = time_s[keep] - time_s[0], np.asarray(rate_dps, dtype=np.float64)[keep]
    if len(since_s) < 3:
        return {}
    flags = np.zeros(len(since_s)) if outside is None else np.asarray(outside, dtype=np.float64)[keep]
    index = ((since_s - still_s) // block_s).astype(np.int64)
    starts = np.flatnonzero(np.concatenate([[True], index[1:] != index[:-1]]))
    counts = np.diff(np.append(starts, len(index)))
    means = np.add.reduceat(np.column_stack([rate, sigma_dps[keep], flags]), starts, axis=0) / counts[:, None]
    subs = SubMeans(block_s)
    subs.add(((since_s - still_s) // SUB_S).astype(np.int64), rate)
    subs.close()
    return judge_blocks(still_s + block_s * index[starts], means, counts, np.mean(np.diff(rate, axis=0) ** 2, axis=0),
                        block_s, ranges=True, sub_avar=subs.avar())


class SubMeans:
    """Consecutive ``SUB_S`` means within each block, the squares of their differences summed as they close."""

    def __init__(self, block_s: float = BLOCK_S):
        self.per_block = max(1, int(round(block_s / SUB_S)))
        self.index, self.sums, self.count = None, [0.0, 0.0, 0.0], 0
        self.previous: tuple | None = None  # the last closed sub-block: (index, mean, samples)
        self.squares, self.pairs = [0.0, 0.0, 0.0], 0

    def add_row(self, index: int, rate_dps: list, count: int = 1) -> None:
        """One sample of sub-block ``index`` (since the blocks' start, in ``SUB_S``), in plain floats (or the
        sum of ``count`` of them)."""
        if index != self.index:
            self.close()
            self.index = index
        self.sums = [total + v for total, v in zip(self.sums, rate_dps)]
        self.count += count

    def add(self, index: np.ndarray, rate_dps: np.ndarray) -> None:
        """Samples (n,) and (n, 3) in time order: ``add_row`` on each, to rounding."""
        if not len(index):
            return
        starts = np.flatnonzero(np.concatenate([[True], index[1:] != index[:-1]]))
        counts = np.diff(np.append(starts, len(index)))
        for sub, total, count in zip(index[starts].tolist(), np.add.reduceat(rate_dps, starts, axis=0).tolist(),
                                     counts.tolist()):
            self.add_row(sub, total, count)

    def close(self) -> None:
        """End the open sub-block; pair it with the one before when both lie in one block, side by side, and
        each holds half the samples of the other at least."""
        if self.count:
            mean = [v / self.count for v in self.sums]
            last = self.previous
            beside = last is not None and last[0] + 1 == self.index and last[0] // self.per_block == self.index // self.per_block
            # two samples each at least (one is no mean: below 0.2 Hz the first differences decide)
            if beside and min(last[2], self.count) >= 2 and 2 * min(last[2], self.count) >= max(last[2], self.count):
                self.squares = [s + (a - b) ** 2 for s, a, b in zip(self.squares, mean, last[1])]
                self.pairs += 1
            self.previous = (self.index, mean, self.count)
        self.index, self.sums, self.count = None, [0.0, 0.0, 0.0], 0

    def avar(self) -> np.ndarray | None:
        """The Allan variance at ``SUB_S`` per axis (3,), deg^2/s^2, from the pairs so far; None without one."""
        return 0.5 * np.asarray(self.squares) / self.pairs if self.pairs else None


def judge_blocks(start_s: np.ndarray, means: np.ndarray, counts: np.ndarray, mean_step_sq: np.ndarray,
                 block_s: float = BLOCK_S, ranges: bool = False, sub_avar: np.ndarray | None = None
                 ) -> dict[str, dict[str, Any]]:
    """:func:`judge` on the blocks that hold half the samples of a full one (the median), {} under two.

    ``means`` (m, 7): each block's mean rate (3), bar (3) and share outside the trained temperatures;
    ``counts`` (m,) its samples. A full block mean's white noise is ``sub_avar`` (3,), the Allan
    variance at ``SUB_S`` (:class:`SubMeans`), times ``SUB_S / block_s``; without it, half
    ``mean_step_sq`` (3,), the rate's mean squared first difference, over a full block's samples.
    """
    full_count = float(np.median(counts))
    full = counts >= 0.5 * full_count
    if full.sum() < 2:
        return {}
    start_s, means = start_s[full], means[full]
    noise_var = (0.5 * np.asarray(mean_step_sq) / full_count if sub_avar is None
                 else np.asarray(sub_avar) * SUB_S / block_s)
    return judge(start_s, start_s[-1] + block_s, means[:, :3], means[:, 3:6], means[:, 6] > 0, noise_var, ranges)


def judge(start_s: np.ndarray, end_s: float, rate_dps: np.ndarray, sigma_dps: np.ndarray, outside: np.ndarray,
          noise_var: np.ndarray, ranges: bool = False) -> dict[str, dict[str, Any]]:
    """:func:`check` on blocks already formed (the live stream forms them as it goes).

    ``start_s`` (m,) each block's start and ``end_s`` the record's end, s; ``rate_dps`` and
    ``sigma_dps`` (m, 3) the blocks' mean rate and bar; ``outside`` (m,) whether a block has a sample
    outside the trained temperatures; ``noise_var`` (3,) the variance of a block mean's white noise.
    ``ranges``: also each axis's :func:`calibrated_range` (a few hundredths of a second an axis; not live).
    """
    bar = np.sqrt(np.asarray(sigma_dps) ** 2 + noise_var)
    ratio = np.abs(rate_dps) / np.maximum(bar, 1e-12)  # a bar of 0 (no noise, no floor) and no error: 0
    window_s = min(HOUR_S, end_s - start_s[0])
    last = max(1, np.searchsorted(start_s, end_s - window_s, side="right"))  # the windows that fit the record
    end = np.searchsorted(start_s, start_s[:last] + window_s)
    n = end - np.arange(last)
    out: dict[str, dict[str, Any]] = {}
    for a, axis in enumerate(AXES):
        sums = np.concatenate([[0.0], np.cumsum(ratio[:, a] ** 2)])
        hour_rms = np.sqrt((sums[end] - sums[:last]) / n)
        worst = int(np.argmax(hour_rms))
        out[axis] = {"n_blocks": int(len(ratio)), "within_1_sigma": float(np.mean(ratio[:, a] <= 1.0)),
                     "within_2_sigma": float(np.mean(ratio[:, a] <= 2.0)),
                     "worst_hour_rms_ratio": float(hour_rms[worst]), "worst_hour_start_s": float(start_s[worst]),
                     "window_s": float(window_s), "blocks_out_of_range": int(np.sum(outside)),
                     "recalibrate": bool(hour_rms[worst] > HOUR_RMS_LIMIT)}
        if ranges:
            out[axis]["calibrated_range"] = list(calibrated_range(rate_dps[:, a] / np.maximum(bar[:, a], 1e-12)))
    return out


def summary_line(axis: str, result: dict[str, Any]) -> str:
    """One line for a person: the verdict, the worst hour, and the shares within 1 and 2 sigma."""
    verdict = "recalibrate" if result["recalibrate"] else "within its error bar"
    low, high = result.get("calibrated_range", (float("nan"),) * 2)
    luck = f", and {100 * low:.0f}-{100 * high:.0f} % within 1 on 9 runs in 10 like this one" if np.isfinite(low) else ""
    outside = (f"; {result['blocks_out_of_range']} blocks outside the trained temperatures, where the bar is "
               "extrapolated: calibrate over them (a chamber run that covers them)") if result["blocks_out_of_range"] else ""
    ratio = f"{result['worst_hour_rms_ratio']:.2f}"
    if float(ratio) == HOUR_RMS_LIMIT:  # "2.00x (limit 2)" would not say which side it is on
        ratio = f"{result['worst_hour_rms_ratio']:.6f}".rstrip("0")
    return (f"{axis}: {verdict}: over the {result['window_s'] / 60:.0f} min from {result['worst_hour_start_s']:.0f} s "
            f"after the record's start its 60 s means are {ratio}x the bar in RMS (limit {HOUR_RMS_LIMIT:g}); "
            f"{result['within_1_sigma']:.0%} of {result['n_blocks']} blocks within 1 sigma, "
            f"{result['within_2_sigma']:.0%} within 2 (where the bar holds: about 68 and 95 %{luck}){outside}")


__all__ = ["HOUR_RMS_LIMIT", "SUB_S", "SubMeans", "calibrated_range", "check", "judge", "judge_blocks", "summary_line"]
