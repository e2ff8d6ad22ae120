"""The loop's trained networks (``Stage``) and their trainer, kept apart so that loop.py stays short."""
from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any, Callable, Mapping, Sequence

import numpy as np
import torch

from gyronet.recordings.data import AXES, fold_count, time_blocks
from gyronet.training.dataset import DriftData, block_rmse
from gyronet.errors import GyronetError
from gyronet.training.train import fit

log = logging.getLogger(__name__)


@dataclass
class Stage:
    """One trained network, the data (inputs) it was trained on, and its held-out residual."""

    model: torch.nn.Module
    data: DriftData
    metrics: dict[str, float]
    held_out: dict[str, float] | None = None  # 60 s residual per axis (``Trainer.cross_validate``)

    def val_rmse(self) -> dict[str, float]:
        if self.held_out is None:
            raise RuntimeError("the stage has not been cross-validated")
        return dict(self.held_out)

    def gain_over(self, before: "Stage") -> float:
        """Score of this network's held-out residual against ``before``'s (positive parts summed)."""
        old, new = np.array(list(before.val_rmse().values())), np.array(list(self.val_rmse().values()))
        return float(np.clip(1.0 - new**2 / np.maximum(old**2, 1e-300), 0.0, None).sum())


class Trainer:
    """Builds the data for a list of inputs and trains a fresh network on it."""

    def __init__(self, data_options: Mapping[str, Any], make_model: Callable[[int], torch.nn.Module],
                 optim: Callable | None, train_cfg: Mapping[str, Any], seed: int, block_s: float = 60.0):
        self.data_options, self.make_model = dict(data_options), make_model
        self.optim, self.train_cfg, self.seed, self.block_s = optim, dict(train_cfg), seed, block_s

    def __call__(self, specs: Sequence[Mapping[str, Any]] | None = None, val_fold: int | None = None) -> Stage:
        options = dict(self.data_options)
        if specs is not None:
            options["features"] = [dict(s) for s in specs]
        if val_fold is not None:
            options["val_fold"] = val_fold
        data = DriftData(**options)
        model = self.make_model(data.n_features)
        metrics = fit(model, data, self.optim, seed=self.seed, **self.train_cfg)
        log.debug("trained on %s (fold %s): held-out 60 s RMSE %s deg/s", ", ".join(data.feature_names), val_fold,
                  ", ".join(f"{a}={metrics[f'val/rmse_{a}_dps']:.4g}" for a in AXES))
        return Stage(model, data, metrics)

    def cross_validate(self, stage: Stage) -> Stage:
        """Set ``stage.held_out``: the residual on the separate recording, or pooled over one network
        per cross-validation fold, each scored on the fold it did not see. Only blocks inside the
        temperatures the network was trained on count: held-out blocks at the record's coldest
        or hottest would otherwise score every network by the same extrapolation error."""
        data = stage.data
        k = fold_count(data.val_fraction)
        default = k // 2 if data.val_fold is None else data.val_fold % k
        folds = [None] if data.val_path else range(k)
        squares, weights = np.zeros(len(AXES)), 0
        for fold in folds:
            trained = stage if fold in (None, default) else self(data.features, val_fold=fold)
            rmse, n_inside = _held_out_inside(trained, self.block_s)
            squares, weights = squares + n_inside * rmse**2, weights + n_inside
        stage.held_out = dict(zip(AXES, np.sqrt(squares / max(weights, 1)).tolist()))
        log.info("trained on %s: held-out 60 s RMSE %s deg/s", ", ".join(data.feature_names),
                 ", ".join(f"{a}={v:.4g}" for a, v in stage.held_out.items()))
        return stage


def _held_out_inside(stage: Stage, block_s: float) -> tuple[np.ndarray, int]:
    """Block residual per axis on the stage's validation samples inside its trained temperatures, and their count."""
    time_s, x, y = stage.data.val_full
    inside = np.ones(len(time_s), bool)
    if "temp_c" in stage.data.feature_names:
        # whole blocks by their mean temperature: single samples left between noisy
        # readings at the edge would each count as a block of raw noise
        column = stage.data.feature_names.index("temp_c")
        trained_c = stage.data.train.x[:, column]
        block = time_blocks(time_s, block_s)
        mean_c = np.bincount(block, weights=x[:, column]) / np.maximum(np.bincount(block), 1)
        inside = ((mean_c >= trained_c.min()) & (mean_c <= trained_c.max()))[block]
    if inside.sum() < 2:
        raise GyronetError(f"{stage.data.path}: no held-out samples inside the trained temperature range")
    with torch.no_grad():
        residual = y[inside] - stage.model(torch.as_tensor(x[inside], dtype=torch.float64)).numpy()
    return block_rmse(time_s[inside], residual, block_s), int(inside.sum())
