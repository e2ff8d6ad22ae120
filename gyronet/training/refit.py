"""``RBFNet.refit_all``: a validated fit continues on every block of its recording, keeping its capacity.

The trainer's ``fit`` is passed in, so this module and ``starts`` sit below ``train`` (no import circle).
"""
from __future__ import annotations

import copy
import logging
from typing import Any, Callable, Mapping

import numpy as np
import torch

from gyronet.recordings.data import AXES
from gyronet.training.dataset import Blocks, DriftData

log = logging.getLogger(__name__)


def continue_on_every_block(model: torch.nn.Module, data: DriftData, final: Mapping[str, float],
                            optim: Callable | None, options: Mapping[str, Any], fit: Callable) -> None:
    """``RBFNet.refit_all``: continue a validated fit on every block of its recording, keeping its capacity."""
    everything = every_block(data) if getattr(model, "refit_all", False) else None
    if everything is None:
        return
    fit(model, everything, optim, **options, stop_at_step=options["max_epochs"], warm_start=True)
    if "model/level_x" in final:
        from gyronet.training import capacity

        capacity.apply(model, everything, [int(final[f"model/level_{a}"]) for a in AXES])
    log.info("continued on every block (%d) for %d steps", len(everything.train), options["max_epochs"])


def widen_box(model: torch.nn.Module, x: torch.Tensor) -> None:
    """Widen an RBFNet's trained box to hold ``x`` (a warm start on more data)."""
    if hasattr(model, "z_low"):
        with torch.no_grad():
            z = (x - model.x_mean) / model.x_std
            model.z_low.copy_(torch.minimum(model.z_low, z.min(0).values))
            model.z_high.copy_(torch.maximum(model.z_high, z.max(0).values))


def every_block(data: DriftData) -> DriftData | None:
    """One recording's data with every block to train on (None: validation is another recording, or runs)."""
    if not isinstance(data, DriftData) or data.val_path:
        return None
    everything = copy.copy(data)
    everything.train = Blocks(*(np.concatenate([getattr(data.train, k), getattr(data.val, k)])
                                for k in ("x", "y", "time_s")))
    return everything
