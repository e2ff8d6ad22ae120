"""Three starts of the default network, mixed per axis by held-out stacking (``RBFNet.validate_init``).

On one recording the early-stopped fit runs from the k-means centres and from two forward-selected
(OLS) sets: candidates 4 degC wide and more, and candidates down to 2.5 degC. No start is better on
every sensor, and on one cooling pass the held-out blocks cannot always tell which one carries over
to another thermal history: at temperatures passed only on a ramp, Gaussians can stand in for the
dT/dt terms, and every block of that pass agrees. So rather than keep one start, the bundle is
their convex combination per axis, with the weights that minimise the held-out blocks' error
(stacked regression, weights at least 0 and summing to one), scored as a start-up offset would
leave it (``held_out_residuals``, ``data.val_startup_s``). Keeping one start is the special case
of a weight 1, so on the held-out blocks the mixture is never worse than the best start; where the
starts fit the blocks alike it hedges.

The mixture is itself one ``RBFNet``: the starts' Gaussians side by side, each output row weighted.
The fits normalise by the same data and share the trained box, so the sum is exact, and the bundle,
its TorchScript and a C export compute it like any other network. A start whose weight is zero on
every axis is left out, so the bundle keeps 12 centres when one start wins everywhere.

References
----------
L. Breiman, "Stacked regressions", Machine Learning 24(1), 1996.
"""
from __future__ import annotations

import copy
import itertools
import logging
from typing import Any, Callable, Mapping, Sequence

import numpy as np
import torch
from torch import nn

from gyronet.recordings.data import AXES
from gyronet.training import error_bar_fit
from gyronet.training.dataset import DriftData, residual_block_means
from gyronet.training.refit import continue_on_every_block
from gyronet.training.run_data import scored_after_startup
from gyronet.training.steps import predict, validation_metrics

log = logging.getLogger(__name__)

_SHARED_BUFFERS = ("x_mean", "x_std", "z_low", "z_high", "rbf_index")
EDGE_SHARE = 0.1  # a power-up window in the outer tenth of the temperature range: a soak's, not a deployment's


def stack_weights(*residuals: np.ndarray) -> np.ndarray:
    """Per axis, weights w_k >= 0 summing to one that minimise |sum_k w_k residuals[k]|^2.

    Parameters
    ----------
    residuals
        Each model's held-out residuals, (m, axes): block means of measured minus predicted.

    Returns
    -------
    numpy.ndarray
        (models, axes) weights. Every support is tried (a handful of models): on a support the
        optimum with the sum fixed is w ~ G^-1 1 (G the residuals' Gram matrix), kept if no weight
        is negative; at a tie the earlier models win, so identical residuals give the first all.
    """
    stacked = np.stack(residuals)  # (models, m, axes)
    weights = np.zeros((len(residuals), stacked.shape[2]))
    supports = [list(s) for size in range(1, len(residuals) + 1)
                for s in itertools.combinations(range(len(residuals)), size)]
    for a in range(stacked.shape[2]):
        best = np.inf
        for support in supports:
            r = stacked[support, :, a].T  # (m, |support|)
            w = np.linalg.lstsq(r.T @ r, np.ones(len(support)), rcond=None)[0]
            if w.sum() <= 0 or (w < 0).any():
                continue
            w = w / w.sum()
            error = float(np.sum((r @ w) ** 2))
            if error < best * (1 - 1e-12):  # a tie (to rounding) keeps the smaller, earlier support
                best = error
                weights[:, a] = 0.0
                weights[support, a] = w
    return weights


@torch.no_grad()
def mix_into(model: nn.Module, parts: Sequence[nn.Module], weights: np.ndarray) -> None:
    """Write into ``model`` the network whose output is ``sum_k weights[k, a] * parts[k]`` on each axis ``a``.

    ``weights`` is (len(parts), axes), each column summing to one; the parts must share the input
    normalisation and box (fits on the same data). Their output scales may differ (a campaign's
    fits subtract their own run offsets): the mixture takes the first part's and rescales the others.
    ``model`` takes every part's Gaussians.
    """
    for name in _SHARED_BUFFERS:
        if not all(torch.equal(getattr(p, name), getattr(parts[0], name)) for p in parts):
            raise ValueError(f"the fits to mix normalise differently ({name}): they must share their data")
    weight = torch.as_tensor(np.asarray(weights), dtype=torch.float64)  # (parts, axes)
    y_mean, y_std = parts[0].y_mean.clone(), parts[0].y_std.clone()
    scale = [w * (p.y_std / y_std) for p, w in zip(parts, weight)]  # each part's output rows in the first's units
    bias = sum(p.head.bias * s for p, s in zip(parts, scale))
    if not all(torch.equal(p.y_mean, y_mean) for p in parts):
        bias = bias + (sum(p.y_mean * w for p, w in zip(parts, weight)) - y_mean) / y_std
    dtype = parts[0].centers.dtype
    model.n_centers = sum(p.n_centers for p in parts)
    model.centers = nn.Parameter(torch.cat([p.centers.detach() for p in parts]))
    model.raw_width = nn.Parameter(torch.cat([p.raw_width.detach() for p in parts]))
    model.head = nn.Linear(model.n_centers, model.n_outputs, dtype=dtype)
    model.head.weight.copy_(torch.cat([p.head.weight * s[:, None] for p, s in zip(parts, scale)], dim=1))
    model.head.bias.copy_(bias)
    for layer in ("linear", "poly"):
        getattr(model, layer).weight.copy_(sum(getattr(p, layer).weight * s[:, None] for p, s in zip(parts, scale)))
    for name in _SHARED_BUFFERS:
        getattr(model, name).copy_(getattr(parts[0], name))
    model.y_mean.copy_(y_mean)
    model.y_std.copy_(y_std)
    model.train_min_width = min(p.train_min_width for p in parts)


def held_out_residuals(model: nn.Module, data: DriftData) -> np.ndarray:
    """The held-out 60 s block means of measured minus predicted drift, (m, axes): what the starts are mixed on.

    With ``data.val_startup_s`` they are scored as deployed with a start-up offset over that many
    seconds: less the model's mean residual over the first ``val_startup_s`` s of the validation
    recording (``data.val_path``), or on time blocks of the training record itself, whose power-up
    is the only one a recording has (in sample). The offset carries that window's error into every
    later sample, so a start that misfits the power-up loses where it would in use.
    """
    time_s, x, y = data.val_full
    residual = y - predict(model, x)
    startup_s = deployed_window_s(data)
    if startup_s > 0 and data.val_path:  # scored after the window, whose own rows the offset zeroes
        scored, residual = scored_after_startup(time_s, residual, startup_s)
        time_s, residual = time_s[scored], residual[scored]
    elif startup_s > 0:
        residual = residual - _startup_residual(model, data, startup_s)
    return residual_block_means(time_s, residual, 60.0)


def deployed_window_s(data: DriftData) -> float:
    """``data.val_startup_s``, or 0 where the training record powered up at an edge of its temperatures.

    A hot or cold soak before power-up (the paper's 60 degC start, PX4's cold start) puts the
    record's first minutes where no deployment powers up, so they cannot stand for one: the
    window's median temperature must lie inside the middle of the record's range (``EDGE_SHARE``).
    """
    startup_s = float(getattr(data, "val_startup_s", 0.0) or 0.0)
    if startup_s <= 0 or data.val_path:
        return startup_s
    time_s, temp_c = data.recording.time_s, data.recording.temp_c
    low, high = data.temp_range_c
    share = (float(np.nanmedian(temp_c[time_s < time_s[0] + startup_s])) - low) / max(high - low, 1e-9)  # a glitch row is NaN
    return startup_s if EDGE_SHARE <= share <= 1.0 - EDGE_SHARE else 0.0


def _startup_residual(model: nn.Module, data: DriftData, startup_s: float) -> np.ndarray:
    """The model's mean residual (axes,) over the training record's first ``startup_s`` s (its blocks; 0: none)."""
    blocks = [b for b in (data.train, data.val) if len(b)]
    window = np.concatenate([b.time_s for b in blocks]) < data.recording.time_s[0] + startup_s
    if not window.any():
        return np.zeros(len(AXES))
    x, y = (np.concatenate([getattr(b, k) for b in blocks])[window] for k in ("x", "y"))
    return (y - predict(model, x)).mean(0)


def member_seeds(seed: int, members: int) -> list[int]:
    """The seeds of a start's members: disjoint for different ``seed``, the first one ``seed`` itself."""
    return [seed] + [seed * members + j + 1_000_003 for j in range(1, members)]


def fit_members(template: nn.Module, seeds: Sequence[int], fit_one: Callable[[nn.Module, int], dict]
                ) -> tuple[list[dict], list[nn.Module], nn.Module]:
    """A deep copy of ``template`` fitted per seed (``fit_one(member, seed)`` returns its figures), and their average.

    Returns each member's figures, the members and their equal-weight average (the member itself when one).
    """
    figures, members = [], []
    for seed in seeds:
        member = copy.deepcopy(template)
        figures.append(fit_one(member, seed))
        members.append(member)
    if len(members) == 1:
        return figures, members, members[0]
    average = copy.deepcopy(template)
    _average_into(average, members)
    return figures, members, average


def _fit_start(model: nn.Module, init: str, data: DriftData, optim: Callable | None,
               options: Mapping[str, Any], fit: Callable) -> tuple[dict[str, float], list[tuple[dict, nn.Module]], nn.Module]:
    """One start's validated fits (``kmeans_members`` seeds for k-means) and their equal-weight average."""
    seeds = member_seeds(options["seed"], getattr(model, "kmeans_members", 1)) if init == "kmeans" else [options["seed"]]
    template = copy.deepcopy(model)
    template.center_init, template.validate_init = init, False
    figures, members, average = fit_members(template, seeds,
                                            lambda member, seed: fit(member, data, optim, **{**options, "seed": seed}))
    runs = list(zip(figures, members))
    if len(runs) == 1:
        return figures[0], runs, average
    metrics = {**min(figures, key=lambda f: f["val/rmse_dps"]), **validation_metrics(average, data)}
    for axis in AXES:
        levels = [f.get(f"model/level_{axis}") for f in figures]
        if None not in levels:
            metrics[f"model/level_{axis}"] = float(max(levels))
    return metrics, runs, average


def _average_into(model: nn.Module, members: Sequence[nn.Module]) -> None:
    """``model`` becomes the members' equal-weight average on every axis."""
    mix_into(model, members, np.full((len(members), len(AXES)), 1.0 / len(members)))


def fit_every_start(model: nn.Module, data: DriftData, optim: Callable | None, options: Mapping[str, Any],
                    for_bundle: bool, fit: Callable) -> dict[str, float]:
    """A validated fit from each ``center_init``, mixed per axis by the held-out blocks, into ``model``.

    With ``for_bundle`` each fit continues on every block (``RBFNet.refit_all``) before the mixing,
    with the weights and capacity its validation chose; the returned validation figures are the
    mixture's before that, as for a single start. The returned ``val/spread_*`` figures are the
    spread of the held-out error over every fit tried (``spread_figures``).
    """
    from gyronet.model.rbf import CENTER_INITS, SelectionError
    from gyronet.training import two_way

    two_way.apply(model, data)
    trials, tried = [], []
    for init in CENTER_INITS:
        try:
            metrics, members, start = _fit_start(model, init, data, optim, options, fit)
        except SelectionError as err:  # a narrow range: the other starts alone
            log.info("no %s start (%s)", init, err)
            continue
        trials.append((metrics, init, start, members))
        tried += [f for f, _ in members]
    weights = stack_weights(*(held_out_residuals(t, data) for _, _, t, _ in trials))
    used = [k for k in range(len(trials)) if weights[k].any()]
    parts = [trials[k][2] for k in used]
    mix_into(model, parts, weights[used])
    final = {**min((t[0] for t in trials), key=lambda f: f["val/rmse_dps"]), **validation_metrics(model, data)}
    for a, axis in enumerate(AXES):
        levels = [trials[k][0].get(f"model/level_{axis}") for k in used if weights[k, a] > 0]
        if None not in levels:
            final[f"model/level_{axis}"] = float(max(levels))
    if len(trials) > 1:
        log.info("starts mixed per axis%s (held-out %s deg/s): weights x/y/z %s; mixture %.4g deg/s", _how_mixed(data),
                 ", ".join(f"{i} {f['val/rmse_dps']:.4g}" for f, i, _, _ in trials),
                 ", ".join(f"{i} " + "/".join(f"{w:.2f}" for w in row) for (_, i, _, _), row in zip(trials, weights)),
                 final["val/rmse_dps"])
    # the error bar's held-out blocks (gyronet.training.error_bar_fit), taken before any refit sees them; its
    # members are the validated fits: their spread is what the held-out blocks calibrate
    val_full = getattr(data, "val_full", None)
    stats = None if val_full is None else error_bar_fit.held_out_stats(model, parts, *val_full, data.train.x)
    validated = [copy.deepcopy(p) for p in parts] if for_bundle else parts
    if for_bundle:  # each start continued on every block, then mixed again with the same weights
        plain = {k: v for k, v in options.items() if k != "writer"}
        for k in used:
            _, _, start, members = trials[k]
            for metrics, member in members:
                continue_on_every_block(member, data, metrics, optim, plain, fit)
            if len(members) > 1:
                _average_into(start, [m for _, m in members])
        mix_into(model, parts, weights[used])
    error_bar_fit.attach(model, stats, validated)
    weight_of = dict(zip((i for _, i, _, _ in trials), weights))
    final.update({f"model/{init}_weight_{axis}": float(weight_of[init][a]) if init in weight_of else 0.0
                  for init in CENTER_INITS for a, axis in enumerate(AXES)})
    final.update(spread_figures(tried))
    return final


def _how_mixed(data: DriftData) -> str:
    """How the starts were scored, for the log: as deployed, or as is and why."""
    if deployed_window_s(data):
        return f" as deployed after {data.val_startup_s:g} s"
    if getattr(data, "val_startup_s", 0.0):
        return f" as is (its first {data.val_startup_s:g} s lie at an edge of its temperatures: a soak's, no deployment's)"
    return ""


def spread_figures(tried: Sequence[Mapping[str, float]]) -> dict[str, float]:
    """Per axis, the held-out 60 s RMSE's lowest and highest over the fits tried, and the spread in %.

    ``val/spread_{axis}_pct`` is (highest - lowest) / lowest: how much the held-out figure moves
    with the start and the seed, which train.py prints beside the bundle's figure.
    """
    out: dict[str, float] = {"val/fits_tried": float(len(tried))}
    for axis in AXES:
        values = [f[f"val/rmse_{axis}_dps"] for f in tried]
        low, high = min(values), max(values)
        out.update({f"val/lowest_{axis}_dps": low, f"val/highest_{axis}_dps": high,
                    f"val/spread_{axis}_pct": 100.0 * (high - low) / low if low > 0 else 0.0})
    return out


__all__ = ["deployed_window_s", "fit_every_start", "fit_members", "held_out_residuals", "member_seeds", "mix_into", "spread_figures", "stack_weights"]
