"""The pieces every fit shares: the learning-rate schedule, prediction, validation error, finiteness."""
from __future__ import annotations

import math
from typing import Mapping

import numpy as np
import torch

from gyronet.errors import GyronetError
from gyronet.recordings.data import AXES
from gyronet.training.dataset import DriftData, block_rmse


def lr_at(step: int, total_steps: int, base_lr: float, warmup_steps: int = 50, final_fraction: float = 0.05) -> float:
    """Linear warm-up then cosine decay to ``final_fraction`` of ``base_lr``; a pure function of the step."""
    if step < warmup_steps:
        return base_lr * (step + 1) / warmup_steps
    progress = min(1.0, (step - warmup_steps) / max(1, total_steps - warmup_steps))
    return base_lr * (final_fraction + (1 - final_fraction) * 0.5 * (1 + math.cos(math.pi * progress)))


def predict(model: torch.nn.Module, x: np.ndarray) -> np.ndarray:
    """The model's drift (deg/s, (n, axes)) on feature rows ``x``, without building a graph."""
    dtype = next((p.dtype for p in model.parameters() if p.is_floating_point()), torch.float64)
    with torch.no_grad():
        # a copy: the cached full-rate features are read-only, which torch warns about
        return model(torch.tensor(x, dtype=dtype)).numpy()


def validation_metrics(model: torch.nn.Module, data: DriftData, full_rate: bool = True) -> dict[str, float]:
    """Validation error: RMS of 60 s block means of gyro minus predicted drift, per axis.

    ``full_rate`` evaluates the model on every validation sample, as deployed; otherwise on the
    10 s training blocks (a cheap stand-in used for early stopping). Without ground truth the
    residual still holds the sensor noise; 60 s blocks average most of it away, and what is left
    is the same for every model, so comparisons stay fair.
    """
    if full_rate:
        time_s, x, y = data.val_full
    else:
        time_s, x, y = data.val.time_s, data.val.x, data.val.y
    residual = y - predict(model, x)
    if getattr(data, "val_adjust", None) is not None:  # e.g. the held-out run's start-up offset (gyronet.training.runs)
        scored, residual = data.val_adjust(time_s, residual)
        time_s, residual = time_s[scored], residual[scored]
    rmse = block_rmse(time_s, residual, 60.0)
    metrics = {f"val/rmse_{a}_dps": float(v) for a, v in zip(AXES, rmse)}
    metrics["val/rmse_dps"] = float(np.mean(rmse))
    return metrics


def check_finite(metrics: Mapping[str, float], what: str) -> None:
    """A diverged fit is an error naming its non-finite figures, never a silent NaN model."""
    bad = sorted(k for k, v in metrics.items() if not math.isfinite(v))
    if bad:
        raise GyronetError(f"{what} gives non-finite {', '.join(bad)} ({metrics[bad[0]]}): the fit diverged")
