"""Narrower Gaussians where a record heats and cools through its temperatures (``RBFNet.two_way_width_init``).

On one pass through the temperatures (a cooling staircase) each degC is seen at one rate, so a
narrow Gaussian on temperature can stand in for the dT/dt terms or fit the noise of a minute of
the record: Table 1's sensor gets worse with narrower starts (x 1.09x -> 1.14x). Where the record
passes the same temperatures heating and cooling, the static curve is pinned from both sides and
the narrow Gaussians a sharp knee needs can be identified: on a chamber cycle the survey's ten
worst sensors went from 1.41x to 1.13x (mean worst axis, as deployed). The held-out blocks of one
record do not tell the two cases apart (their errors differ by less than their noise), so the
record's thermal history decides.
"""
from __future__ import annotations

import logging

import numpy as np

from gyronet.recordings.data import time_blocks

log = logging.getLogger(__name__)

SEGMENT_S = 60.0             # temperature averaged over this before its rate is taken
MIN_RATE_C_PER_MIN = 0.1     # slower is a dwell, neither heating nor cooling
BIN_C = 1.0                  # temperatures counted per degC
MIN_TWO_WAY_SHARE = 0.5      # the share of the record's degC bins passed both ways that makes it two-way


def two_way_share(time_s: np.ndarray, temp_c: np.ndarray, run: np.ndarray | None = None) -> float:
    """The share of the record's 1 degC bins it passes both heating and cooling (faster than 0.1 degC/min).

    With ``run`` (each sample's run in a campaign) rates are taken within runs, and a degC heated
    through in one run and cooled through in another counts as both.
    """
    time_s, temp_c = np.asarray(time_s, dtype=float), np.asarray(temp_c, dtype=float)
    run = np.zeros(len(time_s), dtype=np.int64) if run is None else np.asarray(run)
    heating, cooling, every = set(), set(), set()
    for r in np.unique(run):
        ok = (run == r) & np.isfinite(time_s) & np.isfinite(temp_c)
        if ok.sum() < 2:
            continue
        ids, inverse = np.unique(time_blocks(time_s[ok], SEGMENT_S), return_inverse=True)
        mean_c = np.bincount(inverse, temp_c[ok]) / np.bincount(inverse)
        adjacent = np.diff(ids) == 1  # no rate across a gap (a held-out span, lost data)
        rate = np.diff(mean_c)[adjacent] * 60.0 / SEGMENT_S
        bins = np.floor(0.5 * (mean_c[1:] + mean_c[:-1])[adjacent] / BIN_C)
        every.update(np.floor(mean_c / BIN_C).tolist())
        heating.update(bins[rate > MIN_RATE_C_PER_MIN].tolist())
        cooling.update(bins[rate < -MIN_RATE_C_PER_MIN].tolist())
    return len(heating & cooling) / len(every) if every else 0.0


def apply(model, data) -> None:
    """Set ``model.width_init`` to its ``two_way_width_init`` when ``data``'s training blocks heat and cool through
    at least half their temperatures; otherwise leave it."""
    width = getattr(model, "two_way_width_init", None)
    if width is None:
        return
    share = two_way_share(data.train.time_s, data.train.x[:, model.temp_index], getattr(data.train, "run", None))
    if share >= MIN_TWO_WAY_SHARE:
        log.info("the record heats and cools through %.0f %% of its temperatures: Gaussians start %g x as wide "
                 "(model.two_way_width_init)", 100 * share, width)
        model.width_init = float(width)
