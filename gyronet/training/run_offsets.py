"""One constant per run and axis, fitted beside a drift model: the run-to-run bias as a nuisance parameter.

Each power-up of a MEMS gyro has its own turn-on bias, and each fixture orientation its own
g-sensitivity term. Fitted with the model (summing to zero over the runs, so the model keeps the
mean level), the offsets take what differs between runs, and the temperature model learns only
what the runs share. Closed-form models get them as extra dummy columns of their least squares
(computed here by Frisch-Waugh-Lovell, so any fit linear in its target works unchanged); an RBFNet
starts from the joint least-squares head and Adam refines both (``gyronet.training.train.fit``).
"""
from __future__ import annotations

import logging
from typing import Callable

import numpy as np
import torch
from torch import Tensor, nn

from gyronet.errors import GyronetError
from gyronet.model.baselines import lstsq

log = logging.getLogger(__name__)


class RunOffsets(nn.Module):
    """One constant per training run and axis, deg/s, summing to zero over the runs (the model keeps the mean).

    Parameters
    ----------
    run
        Position of each training block's run, shape (m,).
    n_runs
        Number of training runs.
    """

    def __init__(self, run: np.ndarray, n_runs: int):
        super().__init__()
        self.register_buffer("run", torch.as_tensor(np.asarray(run), dtype=torch.long))
        self.raw = nn.Parameter(torch.zeros(n_runs, 3, dtype=torch.float64))

    def values(self) -> Tensor:
        """The offsets, (n_runs, 3), deg/s, sum zero over runs."""
        return self.raw - self.raw.mean(0)

    def forward(self) -> Tensor:
        """Each training block's offset, (m, 3)."""
        return self.values()[self.run]

    @torch.no_grad()
    def estimate(self, fit_predict: Callable[[Tensor], Tensor], y: Tensor) -> None:
        """Offsets of the joint least-squares fit of model and offsets, for a model fitted linearly in its target.

        Frisch-Waugh-Lovell: with M = I - H the model fit's residual maker (H y = ``fit_predict(y)``),
        the offsets' coefficients are (R' M R)^-1 R' M y for the run indicators R (run 0's is the
        model's own constant). ``fit_predict`` is called on y and on the indicators, three at a time.
        """
        n_runs = self.raw.shape[0]
        indicators = nn.functional.one_hot(self.run, n_runs).to(y.dtype)[:, 1:]
        resid_y = y - fit_predict(y)
        resid_r = []
        for start in range(0, n_runs - 1, 3):
            chunk = indicators[:, start:start + 3]
            padded = torch.cat([chunk, torch.zeros(len(chunk), 3 - chunk.shape[1], dtype=y.dtype)], 1)
            resid_r.append((padded - fit_predict(padded))[:, :chunk.shape[1]])
        resid_r = torch.cat(resid_r, 1)
        coef = lstsq(resid_r, resid_y)
        self.raw.copy_(torch.cat([torch.zeros(1, 3, dtype=y.dtype), coef]))

    @torch.no_grad()
    def fit_closed_form(self, model: nn.Module, x: Tensor, y: Tensor) -> None:
        """Fit a closed-form model (``fit_closed_form``) and the offsets jointly: extra dummy columns, in effect."""
        if not getattr(model, "linear_in_target", True):
            raise GyronetError(f"{type(model).__name__} cannot fit run offsets (its fit is not linear in the data, "
                               "as Frisch-Waugh-Lovell needs): set data.run_offsets=false")
        def fit_predict(target: Tensor) -> Tensor:
            model.fit_closed_form(x, target)
            return model(x)

        self.estimate(fit_predict, y)
        model.fit_closed_form(x, y - self())

    @torch.no_grad()
    def init_from_data(self, model: nn.Module, x: Tensor, y: Tensor, seed: int) -> None:
        """Start an RBFNet and the offsets from their joint least-squares head fit (Adam refines both)."""
        def fit_predict(target: Tensor) -> Tensor:
            model.init_from_data(x, target, torch.Generator().manual_seed(seed))
            return model(x)

        self.estimate(fit_predict, y)
        model.init_from_data(x, y - self(), torch.Generator().manual_seed(seed))


__all__ = ["RunOffsets"]
