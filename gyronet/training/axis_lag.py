"""A thermal lag per axis: an axis that sees the die through a path of its own reads lagged inputs.

The temperature a gyro reports is its die's; each axis's sense element can sit behind it by a
thermal path of its own, seconds to tens of seconds, and then its drift is a function of
``lag(T, tau)`` and its rate, not of ``T``: on every ramp a lag of ``tau`` shifts a steep part of the
bias curve by ``tau * dT/dt``. Before the fit each axis's lag is chosen from the model's
``axis_lags_s`` (and none) by a closed-form screen: a least-squares fit of the default's form (a
cubic and Gaussians on a fixed grid in the lagged temperature, linear terms in its rate and their
product) on the 10 s blocks, cross-validated by 2 min chunks, scored by the RMS of the held-out
residual's 60 s means (the contract's residual). A lag
is kept only where it lowers that held-out error by ``LAG_GAIN`` or more; the network is then
built with the lagged columns in those axes' slots (``RBFNet.axis_columns``).

Only for one recording; a multi-run campaign keeps the inputs as they are (its runs' held-out
error includes each run's constant, which the screen does not model).
"""
from __future__ import annotations

import dataclasses
import logging
from typing import Any, Callable, Sequence

import numpy as np
import torch

from gyronet.recordings.data import AXES
from gyronet.training.dataset import DriftData, block_rmse

log = logging.getLogger(__name__)

LAG_GAIN = 0.02  # a lag is kept when its held-out error is at least 2 % below no lag's
GRID_STEP_C, GRID_WIDTH_C = 2.5, 3.0  # the screen's Gaussians: every 2.5 degC of the trained range, 3 degC wide
RIDGE = 1e-8
BLOCK_S = 60.0  # the screen's error: the RMS of the held-out residual's 60 s means
CHUNK_S, N_FOLDS = 120.0, 5  # cross-validation by 2 min chunks, every 5th held out in turn: a chunk is a few
# degC of a ramp, inside the trained temperatures (a held-out span of 10 degC would score extrapolation)


def lagged_specs(lag_s: float, rate_tau_s: float) -> list[dict[str, Any]]:
    """The temperature, dT/dt and T*dT/dt of an axis ``lag_s`` behind the die."""
    return [{"kind": "lag", "tau_s": float(lag_s)}, {"kind": "rate", "tau_s": float(rate_tau_s), "lag_s": float(lag_s)},
            {"kind": "product", "lag_s": float(lag_s)}]


def paper_slots(specs: Sequence[dict]) -> list[int] | None:
    """Where the unlagged temperature, rate and product are in ``specs``, or None without all three."""
    def first(kind: str) -> int | None:
        return next((i for i, s in enumerate(specs) if s["kind"] == kind and s.get("source", "temp_c") == "temp_c"
                     and not float(s.get("lag_s", 0.0))), None)

    slots = [first("temp"), first("rate"), first("product")]
    return None if None in slots else slots


def screen_errors(data: DriftData, lags_s: Sequence[float]) -> np.ndarray:
    """The screen's cross-validated error per candidate (none first, then ``lags_s``) and axis, (1 + len, 3), deg/s."""
    slots = paper_slots(data.features)
    rate_tau_s = float(data.features[slots[1]].get("tau_s", 5.0))
    extra = [spec for lag_s in lags_s for spec in lagged_specs(lag_s, rate_tau_s)]
    wide = dataclasses.replace(data, features=[*data.features, *extra])
    time_s = np.concatenate([wide.train.time_s, wide.val.time_s])
    order = np.argsort(time_s, kind="stable")
    time_s = time_s[order]
    x, y = np.concatenate([wide.train.x, wide.val.x])[order], np.concatenate([wide.train.y, wide.val.y])[order]
    fold = (np.floor((time_s - time_s[0]) / CHUNK_S) % N_FOLDS).astype(int)
    n = len(data.features)
    columns = [slots] + [[n + 3 * k, n + 3 * k + 1, n + 3 * k + 2] for k in range(len(lags_s))]
    low, high = data.temp_range_c
    centres = np.arange(low, high + 0.5 * GRID_STEP_C, GRID_STEP_C)
    errors = np.empty((len(columns), len(AXES)))
    for k, cols in enumerate(columns):
        basis, residual = _basis(x[:, cols], centres, low, high), np.empty_like(y)
        for f in range(N_FOLDS):
            held = fold == f
            gram = basis[~held].T @ basis[~held]
            ridge = RIDGE * np.trace(gram) / len(gram) * np.eye(len(gram))
            residual[held] = basis[held] @ np.linalg.solve(gram + ridge, basis[~held].T @ y[~held]) - y[held]
        errors[k] = block_rmse(time_s, residual, BLOCK_S)  # over 60 s, as scored: a 10 s mean is mostly noise
    return errors


def _basis(x: np.ndarray, centres: np.ndarray, low: float, high: float) -> np.ndarray:
    """The screen's regressors: 1, t, t^2, t^3, Gaussians on t (t clamped to the box), rate, product."""
    temp = np.clip(x[:, 0], low, high)
    t = (temp - 0.5 * (low + high)) / (0.5 * (high - low))
    gaussians = np.exp(-0.5 * ((temp[:, None] - centres[None]) / GRID_WIDTH_C) ** 2)
    rate, product = x[:, 1] * 60.0, x[:, 2] * 60.0 / max(abs(low), abs(high), 1.0)
    return np.column_stack([np.ones_like(t), t, t * t, t ** 3, gaussians, rate, product])


def choose_lags(errors: np.ndarray, lags_s: Sequence[float], gain: float = LAG_GAIN) -> list[float]:
    """Per axis: the candidate with the lowest held-out error if it beats none by ``gain``, else 0."""
    chosen = []
    for a in range(errors.shape[1]):
        best = int(np.argmin(errors[:, a]))
        chosen.append(float(lags_s[best - 1]) if best and errors[best, a] <= (1 - gain) * errors[0, a] else 0.0)
    return chosen


def with_axis_lags(data: Any, make_model: Callable[..., torch.nn.Module], model: torch.nn.Module) -> tuple[Any, Any]:
    """``data`` and ``model`` as the fit needs them: with each axis's lagged inputs where a lag pays.

    ``make_model(n_inputs, axis_columns)`` builds the network again for more inputs; nothing changes
    for a model without ``axis_lags_s``, or training data other than one recording.
    """
    lags_s = list(getattr(model, "axis_lags_s", None) or [])
    slots = paper_slots(getattr(data, "features", []))
    if not lags_s or not isinstance(data, DriftData) or slots is None:
        if lags_s and not isinstance(data, DriftData):
            log.info("axis lags: chosen on one recording only; the runs' inputs stay as they are")
        return data, model
    errors = screen_errors(data, lags_s)
    chosen = choose_lags(errors, lags_s)
    gains = ", ".join(f"{axis} {lag:g} s ({100 * (1 - errors[1 + lags_s.index(lag), a] / errors[0, a]):.0f} % "
                      "lower held-out error)" if lag else f"{axis} none" for a, (axis, lag) in enumerate(zip(AXES, chosen)))
    log.info("axis lags (screened: none, %s s): %s", ", ".join(f"{t:g}" for t in lags_s), gains)
    distinct = sorted({lag for lag in chosen if lag})
    if not distinct:
        return data, model
    rate_tau_s = float(data.features[slots[1]].get("tau_s", 5.0))
    n = len(data.features)
    features = [*data.features, *[spec for lag_s in distinct for spec in lagged_specs(lag_s, rate_tau_s)]]
    columns = []
    for lag in chosen:
        # the axis's own temperature, rate and product in the paper's slots and in every lag's: no axis
        # sees another's inputs (in the linear terms they would only add what that axis does not need)
        k = n + 3 * distinct.index(lag) if lag else None
        own = slots if k is None else [k, k + 1, k + 2]
        axis = list(range(n)) + own * len(distinct)
        for slot, column in zip(slots, own):
            axis[slot] = column
        columns.append(axis)
    model = make_model(len(features), columns)
    model.lag_by_axis_s = chosen
    return dataclasses.replace(data, features=features), model


__all__ = ["LAG_GAIN", "choose_lags", "lagged_specs", "paper_slots", "screen_errors", "with_axis_lags"]
