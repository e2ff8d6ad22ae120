"""Capacity per axis, chosen on held-out data: what a calibration learns must carry over to the next run.

The default model is a nested family per output axis (``LEVELS``): a constant; + the linear terms
in every input; + the powers of temperature; + the Gaussians (the full network). Within one
run a richer model always fits better, but a gyro axis whose bias does not repeat from run to
run (events, hysteresis, handling) gets the first run's events added to the next. So each axis
keeps the smallest level whose held-out error is within ``TOLERANCE`` of the best level's:

- several runs: leave-one-run-out, each held-out run scored inside the fold's trained
  temperatures (what the final model is asked to do) with its own constant removed (its turn-on
  bias, which no model can know); the errors are averaged over the folds. Not as deployed with
  ``data.val_startup_s``: that score rests on each held-out run's first minutes, and choosing on it
  was worse on held-out simulated runs (docs/results/real-data.md);
- one recording: its held-out time blocks (``gyronet.training.dataset.DriftData``), as for early stopping.

A lower level only zeroes rows of the network's output layers (refitted in closed form), so the
bundle, its TorchScript and its C export are the same function of the same features.
"""
from __future__ import annotations

import copy
import logging
from typing import Any, Sequence

import numpy as np
import torch
from torch import nn

from gyronet.recordings.data import AXES
from gyronet.training.dataset import block_rmse

log = logging.getLogger(__name__)

LEVELS = ("constant", "linear", "cubic", "full")
TOLERANCE = 0.01  # a lower level is kept when its held-out error is at most 1 % above the best
MIN_IN_BOX_S = 3600.0  # less held-out time inside the trained temperatures than this: score the whole run


def fit_level(model: nn.Module, x: torch.Tensor, y: torch.Tensor, level: int, axes: Sequence[int],
              offsets: Any = None) -> None:
    """Refit the output rows of ``axes`` at ``level`` by least squares (with the run offsets, if any)."""
    if offsets is not None:
        def fit_predict(target: torch.Tensor) -> torch.Tensor:
            trial = copy.deepcopy(model)
            trial.refit_head(x, target, level=level)
            return trial(x)

        before = offsets.raw.detach().clone()
        offsets.estimate(fit_predict, y)
        with torch.no_grad():
            keep = [a for a in range(y.shape[1]) if a not in set(axes)]
            offsets.raw[:, keep] = before[:, keep]
        y = y - offsets().detach()
    model.refit_head(x, y, level=level, axes=list(axes))


def inside_box(time_s: np.ndarray, temp_c: np.ndarray, temp_range_c: Sequence[float]) -> tuple[np.ndarray, float]:
    """Which samples lie inside the trained temperatures, and the seconds they span (count x median period)."""
    low, high = temp_range_c
    inside = (temp_c >= low) & (temp_c <= high)
    return inside, float(inside.sum() * np.median(np.diff(time_s)))


def held_out_error(model: nn.Module, data: Any) -> np.ndarray:
    """Per-axis 60 s RMS of the held-out residual, deg/s; a held-out run's in the trained box, demeaned."""
    time_s, x, y = data.val_full
    with torch.no_grad():
        residual = y - model(torch.tensor(x, dtype=torch.float64)).numpy()
    if getattr(data, "held_out", None) is None:  # one recording's held-out blocks: the constant is shared
        return block_rmse(time_s, residual, 60.0)
    inside, inside_s = inside_box(time_s, x[:, getattr(model, "temp_index", 0)], data.temp_range_c)
    if inside_s >= MIN_IN_BOX_S:
        time_s, residual = time_s[inside], residual[inside]
    return block_rmse(time_s, residual - residual.mean(0), 60.0)


def level_errors(model: nn.Module, data: Any) -> np.ndarray:
    """Held-out error of every level, (len(LEVELS), 3): the trained ``model`` is the full level."""
    x = torch.as_tensor(data.train.x, dtype=torch.float64)
    y = torch.as_tensor(data.train.y, dtype=torch.float64)
    errors = []
    for level in range(len(LEVELS) - 1):
        trial = copy.deepcopy(model)
        offsets = copy.deepcopy(getattr(data, "offsets", None))
        fit_level(trial, x, y, level, range(y.shape[1]), offsets)
        errors.append(held_out_error(trial, data))
    errors.append(held_out_error(model, data))
    return np.asarray(errors)


def choose(errors: np.ndarray, tolerance: float = TOLERANCE) -> list[int]:
    """Per axis, the lowest level whose error is within ``tolerance`` of that axis's best."""
    best = errors.min(0)
    return [int(np.flatnonzero(errors[:, a] <= best[a] * (1 + tolerance))[0]) for a in range(errors.shape[1])]


def refit(model: nn.Module, data: Any, levels: Sequence[int]) -> None:
    """Refit the axes whose chosen level is below full on ``data.train`` (the full axes keep their fit)."""
    x = torch.as_tensor(data.train.x, dtype=torch.float64)
    y = torch.as_tensor(data.train.y, dtype=torch.float64)
    for level in sorted(set(levels) - {len(LEVELS) - 1}):
        fit_level(model, x, y, level, [a for a, v in enumerate(levels) if v == level], getattr(data, "offsets", None))


# said where no axis keeps its Gaussians: a sweep over these searches nothing on this record
INERT = "model.n_centers, model.width_init, optim.lr and seed change nothing here"


def apply(model: nn.Module, data: Any, levels: Sequence[int]) -> None:
    """``refit`` the model that will be deployed, and say what each axis got."""
    refit(model, data, levels)
    log.info("capacity per axis: %s%s", ", ".join(f"{a}={LEVELS[v]}" for a, v in zip(AXES, levels)),
             f" (no axis keeps its Gaussians: {INERT})" if max(levels) < len(LEVELS) - 1 else "")


def as_metrics(errors: np.ndarray, levels: Sequence[int] | None = None) -> dict[str, float]:
    """``val/capacity_<level>_<axis>_dps`` for every level and axis, and ``model/level_<axis>`` when chosen."""
    out = {f"val/capacity_{name}_{a}_dps": float(errors[k, j]) for k, name in enumerate(LEVELS)
           for j, a in enumerate(AXES)}
    if levels is not None:
        out.update({f"model/level_{a}": float(v) for a, v in zip(AXES, levels)})
    return out


def from_metrics(folds: Sequence[dict]) -> np.ndarray:
    """The folds' mean level errors, (len(LEVELS), 3), from their ``as_metrics`` figures."""
    return np.asarray([[np.mean([f[f"val/capacity_{name}_{a}_dps"] for f in folds]) for a in AXES] for name in LEVELS])


__all__ = ["LEVELS", "MIN_IN_BOX_S", "TOLERANCE", "apply", "as_metrics", "choose", "fit_level", "from_metrics",
           "held_out_error", "inside_box", "level_errors", "refit"]
