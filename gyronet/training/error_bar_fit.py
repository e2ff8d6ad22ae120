"""Fit a bundle's error bar (``gyronet.model.error_bar``) from what training already holds out.

Training fits the starts, validates them on held-out time blocks (or runs) and only then, for
the bundle, continues on every block. The held-out residuals are taken before that
(:func:`held_out_stats`, attached to the model by the fit), and :func:`fit_error_bar` turns them
into the bar's floor and spread scale once the bundle's members are final.
"""
from __future__ import annotations

import logging
from typing import Any, Callable, Mapping, Sequence

import numpy as np
import torch

from gyronet.model.error_bar import BLOCK_S, EDGE_FRACTION, ErrorBar, stack_members
from gyronet.training.dataset import residual_block_means

log = logging.getLogger(__name__)

STATS_ATTR = "_error_bar_stats"  # held-out statistics a fit attaches to its model (taken before any refit)
MEMBERS_ATTR = "_error_bar_members"  # the bundle's members (the starts it mixes), when more than one
CACHE_ATTR = "_error_bar_meta"  # (data, the meta.json block) once computed
# beyond the box, a straight-line continuation is taken to be off by this share of its slope (per
# normalised unit of distance); set on calibration sensors 10-27 with the posterior floor (docs/guides/error-bars.md),
# never on the sensors the table and the survey score
EXTRAPOLATION_SHARE = 0.05
MIN_BLOCKS = 4  # fewer held-out blocks than this: the floor is their RMS, the spread scale 1
_FLOOR_GRID = np.geomspace(1e-3, 3.0, 200)  # times the held-out blocks' RMS
_SCALE_GRID = np.concatenate([[0.0], np.geomspace(0.05, 30.0, 60)])


def box_of(model: torch.nn.Module, x_train: np.ndarray) -> tuple[np.ndarray, ...]:
    """The trained box: an ``RBFNet``'s own normalisation and clamp box, else the training features'."""
    if hasattr(model, "z_low") and hasattr(model, "x_mean"):
        return tuple(getattr(model, k).detach().double().numpy().copy() for k in ("x_mean", "x_std", "z_low", "z_high"))
    mean, std = x_train.mean(0), np.maximum(x_train.std(0), 1e-12)
    z = (x_train - mean) / std
    return mean, std, z.min(0), z.max(0)


def edge_slopes(model: torch.nn.Module, x_train: np.ndarray, box: Sequence[np.ndarray],
                extrapolation_share: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(3, n_features): how much the drift's slope (deg/s per normalised unit) changes where each edge of the box is crossed.

    Over the training rows within ``EDGE_FRACTION`` of the box's width of that edge: the slope just
    inside (a one-sided difference pointing into the box) minus the slope a quarter of the box's
    width beyond the edge, RMS. A model that holds its edge value there (a clamped input) loses its
    whole slope; one that continues a straight line (the rate terms) loses what it curved, and is
    taken to be off by ``extrapolation_share`` (default ``EXTRAPOLATION_SHARE``) of its slope besides:
    a slope fitted on one side of the data only is not known beyond it.
    """
    share = EXTRAPOLATION_SHARE if extrapolation_share is None else float(extrapolation_share)
    from gyronet.training.steps import predict

    mean, std, low, high = box
    z = (x_train - mean) / std
    width = np.maximum(high - low, 1e-9)
    slopes = np.zeros((2, 3, x_train.shape[1]))
    for f in range(x_train.shape[1]):
        step = 1e-3 * width[f]
        for side, (rows, edge, sign) in enumerate(((z[:, f] <= low[f] + EDGE_FRACTION * width[f], low[f], 1.0),
                                                   (z[:, f] >= high[f] - EDGE_FRACTION * width[f], high[f], -1.0))):
            x = x_train[rows]
            if not len(x):
                continue

            def slope(at: np.ndarray) -> np.ndarray:
                moved = at.copy()
                moved[:, f] += sign * step * std[f]
                return (predict(model, moved) - predict(model, at)) / (sign * step)

            beyond = x.copy()
            beyond[:, f] = mean[f] + std[f] * (edge - sign * 0.25 * width[f])
            inside, outside = slope(x), slope(beyond)
            slopes[side, :, f] = np.sqrt(np.mean((inside - outside) ** 2 + (share * outside) ** 2, axis=0))
    return slopes[0], slopes[1]


def shape_of(model: torch.nn.Module, parts: Sequence[torch.nn.Module] | None, x_train: np.ndarray) -> ErrorBar:
    """The bar's form for ``model`` (box, edge slopes, members) with floor 0 and spread scale 1."""
    box = box_of(model, x_train)
    low_dps, high_dps = edge_slopes(model, x_train, box)
    members = stack_members(parts) if parts else None
    return ErrorBar(np.zeros(3), np.ones(3), *box, low_dps, high_dps, members)


def white_noise_var(time_s: np.ndarray, y: np.ndarray, block_s: float = BLOCK_S) -> np.ndarray:
    """(3,) variance of a ``block_s`` mean of the white noise in ``y``: var(first difference) / 2 per sample."""
    dt = float(np.median(np.diff(time_s))) if len(time_s) > 1 else 1.0
    per_sample = 0.5 * np.var(np.diff(y, axis=0), axis=0) if len(y) > 2 else np.zeros(y.shape[1])
    return per_sample / max(block_s / dt, 1.0)


def held_out_stats(model: torch.nn.Module, parts: Sequence[torch.nn.Module] | None, time_s: np.ndarray,
                   x: np.ndarray, y: np.ndarray, x_train: np.ndarray,
                   adjust: Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]] | None = None
                   ) -> dict[str, np.ndarray]:
    """Held-out 60 s blocks: residual (measured - predicted), members' spread, box term, and the noise variance.

    ``time_s, x, y`` are held-out samples at the full rate; ``model`` and ``parts`` the fits validated
    on them, before any refit; ``x_train`` the features they were trained on; ``adjust(time_s,
    residual)`` the rows scored and the residual as deployed (a held-out run's start-up offset removed, the
    window's own rows left out: ``RunsData.val_adjust``).
    """
    from gyronet.training.steps import predict

    bar = shape_of(model, parts, x_train)
    residual = y - predict(model, x)
    if adjust is not None:
        scored, residual = adjust(time_s, residual)
        time_s, x, y, residual = time_s[scored], x[scored], y[scored], residual[scored]
    return {"residual": residual_block_means(time_s, residual, BLOCK_S),
            "spread": residual_block_means(time_s, bar.spread(x), BLOCK_S),
            "outside": residual_block_means(time_s, bar.outside_dps(x), BLOCK_S),
            "noise_var": white_noise_var(time_s, y)}


def merge_stats(stats: Sequence[Mapping[str, np.ndarray]], info: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """Several held-out sets (folds) as one: blocks stacked, the noise variance averaged; ``info`` for the record."""
    out: dict[str, Any] = {k: np.concatenate([s[k] for s in stats]) for k in ("residual", "spread", "outside")}
    out["noise_var"] = np.mean([s["noise_var"] for s in stats], axis=0)
    if info:
        out["info"] = dict(info)
    return out


def cross_check(folds: Sequence[Mapping[str, np.ndarray]]) -> tuple[list[float], list[list[float]]] | None:
    """Per axis, the share of each held-out run's blocks within a bar calibrated on the other runs' blocks only.

    The bundle's floor is fitted on every fold's blocks, so its own coverage is in sample; this is
    the bar's coverage on a run it was not calibrated on. Returns the share over every fold's
    blocks and each fold's own (None with fewer than two folds): runs that differ can cancel in
    the first, one too wide and one too narrow, and show in the second.
    """
    if len(folds) < 2:
        return None
    hits, sizes = [], []
    for k, own in enumerate(folds):
        floor, scale, _ = calibrate(merge_stats([s for i, s in enumerate(folds) if i != k]))
        var = floor ** 2 + (scale * own["spread"]) ** 2 + own["outside"] ** 2 + own["noise_var"]
        hits.append(np.sum(own["residual"] ** 2 <= var, axis=0))
        sizes.append(max(len(own["residual"]), 1))
    pooled = np.sum(hits, axis=0) / max(sum(sizes), 1)
    return pooled.tolist(), [(h / n).tolist() for h, n in zip(hits, sizes)]


def calibrate(stats: Mapping[str, np.ndarray], fit_scale: bool = False,
              posterior: bool = True) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """Per axis, the floor (and with ``fit_scale`` the spread scale) from the Gaussian likelihood of the held-out blocks.

    Block b's residual has variance floor^2 + (scale spread_b)^2 + outside_b^2 + noise: the noise
    of a 60 s mean is known and the box term fixed, so the free numbers are found on a grid. The
    floor is the square root of floor^2's posterior mean under a flat prior on the floor
    (``posterior``; else the likelihood's maximum): where a 60 s mean's noise swamps the drift
    error, the maximum sits at 0 although the blocks only bound the floor, and the mean keeps what
    they allow. The scale stays 1 (the members' spread taken as it is) unless ``fit_scale`` (both by
    maximum likelihood): the held-out blocks of one recording are two or three spans, too few to
    tell a floor from a scale. Both choices were made on calibration sensors 10-15
    (``scripts/sigma_variants.py``, docs/guides/error-bars.md).

    Returns
    -------
    floor_dps, spread_scale, info
        (3,) each; ``info``: the blocks used and the share of them within the bar plus the noise.
    """
    residual, spread, outside = (np.asarray(stats[k], dtype=np.float64) for k in ("residual", "spread", "outside"))
    noise = np.asarray(stats["noise_var"], dtype=np.float64)
    floor, scale, within = np.zeros(3), np.ones(3), np.zeros(3)
    for a in range(3):
        r2 = residual[:, a] ** 2
        rms = float(np.sqrt(np.mean(r2))) if len(r2) else 0.0
        if len(r2) < MIN_BLOCKS or rms == 0.0:
            floor[a] = rms
            continue
        fixed = outside[:, a] ** 2 + noise[a]
        # var[i, j, b] for floor i, scale j, block b
        scales = _SCALE_GRID if fit_scale else np.ones(1)
        grid = _FLOOR_GRID * rms
        var = (grid ** 2)[:, None, None] + (scales ** 2)[None, :, None] * (spread[:, a] ** 2)[None, None] \
            + fixed[None, None]
        nll = np.sum(np.log(var) + r2[None, None] / var, axis=2)
        i, j = np.unravel_index(int(np.argmin(nll)), nll.shape)
        floor[a], scale[a] = grid[i], scales[j]
        if posterior and not fit_scale:
            weight = np.exp(-0.5 * (nll[:, 0] - nll[i, 0])) * np.gradient(grid)  # flat prior on the geometric grid
            floor[a] = float(np.sqrt(np.sum(weight * grid ** 2) / np.sum(weight)))
        within[a] = np.mean(r2 <= floor[a] ** 2 + (scale[a] * spread[:, a]) ** 2 + fixed)
    info = {"block_s": BLOCK_S, "n_blocks": int(len(residual)), "within_1_sigma": within.tolist(),
            "noise_block_dps": np.sqrt(noise).tolist()}
    return floor, scale, info


def fit_error_bar(model: torch.nn.Module, x_train: np.ndarray, stats: Mapping[str, np.ndarray] | None,
                  parts: Sequence[torch.nn.Module] | None = None) -> ErrorBar | None:
    """The bundle's error bar: its form from the final ``model`` and ``parts``, its scales from ``stats``.

    None when nothing was held out (``stats`` None): a bar without evidence would be a guess.
    """
    if stats is None or not len(stats["residual"]):
        log.warning("no held-out blocks to calibrate the error bar on: the bundle has none (drift_sigma is NaN)")
        return None
    bar = shape_of(model, parts, x_train)
    bar.floor_dps, bar.spread_scale, bar.calibration = calibrate(stats)
    bar.calibration.update(stats.get("info", {}))  # a campaign's held-out runs and their cross-check
    log.info("error bar (%d members, %d held-out %g s blocks): floor %s deg/s, spread scale %s; within 1 sigma "
             "on those blocks %s", bar.n_members, bar.calibration["n_blocks"], BLOCK_S,
             "/".join(f"{v:.3g}" for v in bar.floor_dps), "/".join(f"{v:.3g}" for v in bar.spread_scale),
             "/".join(f"{v:.0%}" for v in bar.calibration["within_1_sigma"]))
    by_run = bar.calibration.get("cross_within_1_sigma_by_run")
    if by_run:
        narrow = bar.narrow_axes()
        (log.warning if narrow else log.info)(
            "error bar cross-check: each held-out run's blocks within 1 sigma of a floor fitted on the other runs "
            "only: %s; %s (goal 60-76 %%)%s", "/".join(f"{v:.0%}" for v in bar.calibration["cross_within_1_sigma"]),
            ", ".join(f"{name} " + "/".join(f"{v:.0%}" for v in shares) for name, shares in by_run.items()),
            f": too narrow on {', '.join(narrow)}, expect larger errors on a next run" if narrow else "")
    return bar


def error_bar_meta(model: torch.nn.Module, data: Any) -> dict[str, Any] | None:
    """The ``meta.json`` ``error_bar`` block of a fitted ``model`` (computed once, then kept on the model).

    The held-out statistics are those the fit attached (:func:`attach`, before any refit); a fit that
    attached none did not refit, so the final model's own validation blocks are held out.
    """
    if CACHE_ATTR in model.__dict__ and model.__dict__[CACHE_ATTR][0] is data:
        return model.__dict__[CACHE_ATTR][1]
    if getattr(getattr(data, "train", None), "x", None) is None:
        log.warning("no training features to place the error bar's box on: the bundle has none (drift_sigma is NaN)")
        return None
    x_fit = np.asarray(data.train.x, dtype=np.float64)
    if STATS_ATTR in model.__dict__:
        stats, parts = model.__dict__[STATS_ATTR], model.__dict__.get(MEMBERS_ATTR)
    else:
        stats, parts = None, None
        if getattr(data, "val_full", None) is not None and getattr(data, "held_out", None) is None \
                and not getattr(data, "n_runs", 1) > 1:
            time_s, x, y = data.val_full
            stats = held_out_stats(model, None, time_s, x, y, x_fit)
    if getattr(data, "val", None) is not None and not getattr(data, "val_path", None) and getattr(data, "n_runs", 1) == 1:
        x_fit = np.concatenate([x_fit, np.asarray(data.val.x, dtype=np.float64)])  # every block of the recording
    bar = fit_error_bar(model, x_fit, stats, parts)
    out = None if bar is None else bar.to_dict()
    model.__dict__[CACHE_ATTR] = (data, out)
    return out


def attach(model: torch.nn.Module, stats: Mapping[str, np.ndarray] | None,
           parts: Sequence[torch.nn.Module] | None = None) -> None:
    """Keep a fit's held-out statistics (and members) on ``model`` until the bundle is written."""
    model.__dict__[STATS_ATTR] = stats
    model.__dict__[MEMBERS_ATTR] = list(parts) if parts else None
    model.__dict__.pop(CACHE_ATTR, None)


def detach(model: torch.nn.Module) -> tuple[dict | None, list | None, bool]:
    """What :func:`attach` kept (removed from ``model``), and whether anything was attached."""
    attached = STATS_ATTR in model.__dict__
    model.__dict__.pop(CACHE_ATTR, None)
    return model.__dict__.pop(STATS_ATTR, None), model.__dict__.pop(MEMBERS_ATTR, None), attached


__all__ = ["attach", "calibrate", "cross_check", "detach", "error_bar_meta", "fit_error_bar", "held_out_stats", "merge_stats", "shape_of",
           "white_noise_var"]
