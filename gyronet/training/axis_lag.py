"""A thermal lag per axis: an axis that sees the die through a path of its own reads lagged inputs.

The temperature a gyro reports is its die's; each axis's sense element can sit behind it by a
thermal path of its own, seconds to tens of seconds, and then its drift is a function of
``lag(T, tau)`` and its rate, not of ``T``: on every ramp a lag of ``tau`` shifts a steep part of the
bias curve by ``tau * dT/dt``. Before the fit each axis's lag is chosen from the model's
``axis_lags_s`` (and none) by a closed-form screen: a least-squares fit of the default's form (a
cubic and Gaussians on a fixed grid in the lagged temperature, linear terms in its rate and their
product) on the 10 s blocks, cross-validated by 2 min chunks, scored by the RMS of the held-out
residual's 60 s means (the contract's residual). A lag is kept only where it lowers that
held-out error by ``LAG_GAIN`` or more; the network is then built with the lagged columns in
those axes' slots (``RBFNet.axis_columns``). Each lag is also screened with only dT/dt and T*dT/dt
lagged and the temperature as reported: where that does as well, the axis wants a smoother, later
rate rather than a thermal lag, and gets only those columns lagged.

Several runs (``data.paths``) are screened together, with a constant per run beside the form (each
run's turn-on bias), their 2 min chunks held out in turn; deployed with a start-up offset
(``data.val_startup_s``), each run is held out whole instead, each lag at its best capacity level,
and scored as that offset leaves it, since the offset is measured where the features are at their
least settled (a ramp just after power-up), and a lag that fits within runs can cost every later
sample of the next.
"""
from __future__ import annotations

import dataclasses
import logging
from typing import Any, Callable, Sequence

import numpy as np
import torch

from gyronet.recordings.data import AXES
from gyronet.training.dataset import DriftData, residual_block_means
from gyronet.training.run_data import load_runs, scored_after_startup, stack_runs
from gyronet.training.runs import RunsData

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


def _with_lags(features: Sequence[dict], slots: Sequence[int], lags_s: Sequence[float]) -> list[dict]:
    """``features`` and after them each lag's three (``lagged_specs``, dT/dt at the features' own time constant)."""
    rate_tau_s = float(features[slots[1]].get("tau_s", 5.0))
    return [*features, *[spec for lag_s in lags_s for spec in lagged_specs(lag_s, rate_tau_s)]]


def paper_slots(specs: Sequence[dict]) -> list[int] | None:
    """Where the unlagged temperature, rate and product are in ``specs``, or None without all three."""
    def first(kind: str) -> int | None:
        return next((i for i, s in enumerate(specs) if s["kind"] == kind and s.get("source", "temp_c") == "temp_c"
                     and not float(s.get("lag_s", 0.0))), None)

    slots = [first("temp"), first("rate"), first("product")]
    return None if None in slots else slots


def screen_errors(data: Any, lags_s: Sequence[float], rate_only: bool = False) -> np.ndarray:
    """The screen's cross-validated error per candidate (none first, then ``lags_s``) and axis, (1 + len, 3), deg/s.

    With ``rate_only``, ``len(lags_s)`` more rows: each lag's dT/dt and T*dT/dt with the temperature
    unlagged, the control that tells a thermal lag (the bias curve shifted on every ramp) from a
    dT/dt that only wants more smoothing or delay.
    """
    slots = paper_slots(data.features)
    wide = with_features(data, _with_lags(data.features, slots, lags_s))
    time_s, x, y, run = _every_block(wide)
    by_run = _deployed(data)
    if by_run:  # a campaign deployed with a start-up offset: each run held out in turn, scored as deployed
        fold = run
    else:
        chunk = np.zeros(len(time_s), dtype=np.int64)
        for r in np.unique(run):  # 2 min chunks of each run, numbered on across the runs
            mine = run == r
            chunk[mine] = chunk.max() + 1 + np.floor((time_s[mine] - time_s[mine].min()) / CHUNK_S).astype(np.int64)
        fold = chunk % N_FOLDS
    runs = (run[:, None] == np.unique(run)[None]).astype(np.float64)  # a constant per run (each run's turn-on bias)
    n = len(data.features)
    columns = [slots] + [[n + 3 * k, n + 3 * k + 1, n + 3 * k + 2] for k in range(len(lags_s))]
    if rate_only:
        columns += [[slots[0], n + 3 * k + 1, n + 3 * k + 2] for k in range(len(lags_s))]
    low, high = data.temp_range_c
    centres = np.arange(low, high + 0.5 * GRID_STEP_C, GRID_STEP_C)
    errors = np.empty((len(columns), len(AXES)))
    for k, cols in enumerate(columns):
        basis = np.column_stack([runs, _basis(x[:, cols], centres, low, high)])
        if by_run:  # each candidate at its best capacity level: the network may keep any of them
            constants = list(range(runs.shape[1]))
            errors[k] = np.min([_score_by_run(time_s, x[:, slots[0]], _held_out(basis[:, constants + level], y, fold),
                                              run, data.val_startup_s)
                                for level in _levels(len(constants), basis.shape[1])], axis=0)
        else:
            residual = _held_out(basis, y, fold)
            # over 60 s, as scored (a 10 s mean is mostly noise), each run's blocks apart
            means = np.concatenate([residual_block_means(time_s[run == r], residual[run == r], BLOCK_S)
                                    for r in np.unique(run)])
            errors[k] = np.sqrt(np.mean(means ** 2, axis=0))
    return errors


def _held_out(basis: np.ndarray, y: np.ndarray, fold: np.ndarray) -> np.ndarray:
    """Each fold's residual from a ridge least-squares fit on the other folds."""
    residual = np.empty_like(y)
    for f in np.unique(fold):
        held = fold == f
        gram = basis[~held].T @ basis[~held]
        ridge = RIDGE * np.trace(gram) / len(gram) * np.eye(len(gram))
        residual[held] = basis[held] @ np.linalg.solve(gram + ridge, basis[~held].T @ y[~held]) - y[held]
    return residual


def _levels(n_runs: int, n_columns: int) -> list[list[int]]:
    """``_basis``'s columns (after the run constants) of each capacity level: 1; + t, rate, product; + t^2, t^3; all."""
    one, t, t2, t3, rate, product = n_runs, n_runs + 1, n_runs + 2, n_runs + 3, n_columns - 2, n_columns - 1
    return [[one], [one, t, rate, product], [one, t, t2, t3, rate, product], list(range(n_runs, n_columns))]


def _deployed(data: Any) -> bool:
    """Screen by run, as deployed: several runs and a start-up window to score them after (``data.val_startup_s``)."""
    return isinstance(data, RunsData) and data.n_runs >= 2 and data.val_startup_s > 0


def _score_by_run(time_s: np.ndarray, temp_c: np.ndarray, residual: np.ndarray, run: np.ndarray,
                  startup_s: float) -> np.ndarray:
    """RMS of every held-out run's 60 s residual means as a start-up offset leaves them, in the other runs' box.

    The offset is the residual's mean over a run's first ``startup_s``: a model that is wrong there
    (a ramp just after power-up, say) carries that error into every later sample.
    """
    means = []
    for held in np.unique(run):
        mine, others = run == held, run != held
        t, res, temp = time_s[mine], residual[mine], temp_c[mine]
        scored, res = scored_after_startup(t, res, startup_s)
        keep = scored & (temp >= temp_c[others].min()) & (temp <= temp_c[others].max())
        means.append(residual_block_means(t[keep], res[keep], BLOCK_S))
    return np.sqrt(np.mean(np.concatenate(means) ** 2, axis=0))


def _every_block(data: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Time, features, targets and run of every 10 s block of the training data, in time order per run."""
    if isinstance(data, RunsData):
        blocks = stack_runs(data.runs, data.block_s)
        return blocks.time_s, blocks.x, blocks.y, blocks.run
    time_s = np.concatenate([data.train.time_s, data.val.time_s])
    order = np.argsort(time_s, kind="stable")
    return (time_s[order], np.concatenate([data.train.x, data.val.x])[order],
            np.concatenate([data.train.y, data.val.y])[order], np.zeros(len(time_s), dtype=np.int64))


def with_features(data: Any, features: list) -> Any:
    """The same training data (one recording or several runs, the same split) with other features; what
    loading it says (its size, its glitches) was said the first time, so only errors are logged again."""
    level = logging.root.manager.disable  # every logger, a child with its own level too (hydra.verbose=...)
    logging.disable(max(level, logging.WARNING))
    try:
        if isinstance(data, RunsData):
            runs = load_runs(data.paths, features, data.static_rate_dps)
            return RunsData(runs, features, data.block_s, data.static_rate_dps, data.held_out, data.run_offsets,
                            data.val_startup_s)
        return dataclasses.replace(data, features=features)
    finally:
        logging.disable(level)


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


def choose_inputs(errors: np.ndarray, lags_s: Sequence[float], gain: float = LAG_GAIN) -> list[tuple[float, bool]]:
    """Per axis of :func:`screen_errors` with ``rate_only``: (lag, only dT/dt lagged), (0, False) for none.

    The lowest held-out error of every row wins if it beats none by ``gain``: where lagging the
    temperature too earns nothing more, only the dT/dt and T*dT/dt columns are lagged (a smoother,
    later rate), and the bias curve stays on the temperature as reported.
    """
    n = len(lags_s)
    chosen = []
    for a in range(errors.shape[1]):
        best = int(np.argmin(errors[:1 + 2 * n, a]))
        if not best or errors[best, a] > (1 - gain) * errors[0, a]:
            chosen.append((0.0, False))
        else:
            chosen.append((float(lags_s[(best - 1) % n]), best > n))
    return chosen


def with_axis_lags(data: Any, make_model: Callable[..., torch.nn.Module], model: torch.nn.Module) -> tuple[Any, Any]:
    """``data`` and ``model`` as the fit needs them: with each axis's lagged inputs where a lag pays.

    ``make_model(n_inputs, axis_columns)`` builds the network again for more inputs; nothing changes
    for a model without ``axis_lags_s``, features without the paper's three, or where no lag pays.
    """
    lags_s = list(getattr(model, "axis_lags_s", None) or [])
    slots = paper_slots(getattr(data, "features", []))
    if not lags_s or not isinstance(data, (DriftData, RunsData)) or slots is None:
        return data, model
    errors = screen_errors(data, lags_s, rate_only=True)
    inputs = choose_inputs(errors, lags_s)
    chosen = [lag for lag, _ in inputs]

    def gain(row: int, a: int) -> float:
        return 100 * (1 - errors[row, a] / errors[0, a])

    def said(a: int, lag: float, rate_only: bool) -> str:
        row = 1 + lags_s.index(lag)
        full, rate = f"{gain(row, a):.1f} %", f"{gain(row + len(lags_s), a):.1f} %"
        if rate_only:
            return f"{AXES[a]} dT/dt {lag:g} s ({rate} lower held-out error; {full} with the temperature lagged too)"
        return f"{AXES[a]} {lag:g} s ({full} lower held-out error; {rate} with only dT/dt lagged)"

    gains = ", ".join(said(a, lag, rate_only) if lag else f"{AXES[a]} none" for a, (lag, rate_only) in enumerate(inputs))
    how = f"by run, as deployed after {data.val_startup_s:g} s" if _deployed(data) else "within the records"
    log.info("axis lags (screened %s: none, %s s): %s", how, ", ".join(f"{t:g}" for t in lags_s), gains)
    distinct = sorted({lag for lag in chosen if lag})
    if not distinct:
        return data, model
    n = len(data.features)
    features = _with_lags(data.features, slots, distinct)
    columns = []
    for lag, rate_only in inputs:
        # the axis's own temperature, rate and product in the paper's slots and in every lag's: no axis
        # sees another's inputs (in the linear terms they would only add what that axis does not need)
        k = n + 3 * distinct.index(lag) if lag else None
        own = slots if k is None else [slots[0] if rate_only else k, k + 1, k + 2]
        axis = list(range(n)) + own * len(distinct)
        for slot, column in zip(slots, own):
            axis[slot] = column
        columns.append(axis)
    model = make_model(len(features), columns)
    model.lag_by_axis_s = chosen
    model.rate_lag_only_by_axis = [rate_only for _, rate_only in inputs]
    return with_features(data, features), model


__all__ = ["LAG_GAIN", "choose_inputs", "choose_lags", "lagged_specs", "paper_slots", "screen_errors", "with_axis_lags"]
