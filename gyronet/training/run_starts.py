"""A campaign's starts: each start fitted in every leave-one-run-out fold, mixed per axis by the held-out runs.

One recording mixes its starts by its held-out time blocks (``gyronet.training.starts``). A
campaign's held-out data are whole runs, so each start (``RBFNet.validate_init``: k-means, OLS,
OLS narrow) is fitted in every fold, and one set of weights per axis is stacked on every fold's
held-out run at once. Each held-out run's residual is demeaned first: its turn-on bias is the same
for every start (70 mdps against a model error of 5 on the survey's sensors) and would otherwise
decide the weights. Each start with a weight is then trained on every run for the largest of its
folds' step counts and the fits are mixed with the same weights. Each fit estimates its own run
offsets; the mixture's are the same weighted sum of them.
"""
from __future__ import annotations

import copy
import logging
from typing import Any, Callable, Mapping, Sequence

import numpy as np
import torch
from torch import nn

from gyronet.training.dataset import residual_block_means
from gyronet.training.starts import fit_members, member_seeds, mix_into, stack_weights
from gyronet.training.steps import predict

log = logging.getLogger(__name__)


class Start:
    """One start of a campaign: an untrained model and the seeds of its members (averaged)."""

    def __init__(self, name: str, model: nn.Module, seeds: Sequence[int]):
        self.name, self.model, self.seeds = name, model, list(seeds)


def starts_of(model: nn.Module, data: Any, seed: int) -> list[Start]:
    """Every ``center_init`` with ``validate_init`` (widths set by the campaign's thermal history), else ``model`` alone."""
    if not getattr(model, "validate_init", False):
        return [Start(getattr(model, "center_init", type(model).__name__), copy.deepcopy(model), [seed])]
    from gyronet.model.rbf import CENTER_INITS
    from gyronet.training import two_way

    two_way.apply(model, data)
    starts = []
    for init in CENTER_INITS:
        start = copy.deepcopy(model)
        # the capacity is chosen once, on the folds' mixtures (fit_by_run): no start's own fit needs its levels' errors
        start.center_init, start.validate_init, start.select_capacity = init, False, False
        members = model.kmeans_members if init == "kmeans" else 1
        starts.append(Start(init, start, member_seeds(seed, members)))
    return starts


def fit_start(start: Start, data: Any, fit: Callable, optim: Callable | None, options: Mapping[str, Any],
              steps: int | None = None) -> tuple[list[dict[str, float]], nn.Module, torch.Tensor | None]:
    """One start's fit on ``data``: each member's figures, their equal-weight average and its run offsets' raw values."""
    offsets = []

    def fit_one(member: nn.Module, seed: int) -> dict[str, float]:
        figures = fit(member, data, optim, seed=seed, stop_at_step=steps, **options)
        if getattr(data, "offsets", None) is not None:
            offsets.append(data.offsets.raw.detach().clone())
        return figures

    figures, _, average = fit_members(start.model, start.seeds, fit_one)
    return figures, average, torch.stack(offsets).mean(0) if offsets else None


def fit_folds(starts: Sequence[Start], folds: Sequence[Any], fit: Callable, optim: Callable | None,
              options: Mapping[str, Any]) -> tuple[list[Start], list[list[list[dict]]], list[list[nn.Module]]]:
    """Every start fitted in every fold: the starts kept, ``figures[k][f]`` (each member's) and ``fits[k][f]``.

    A start that cannot be made on some fold's runs (too narrow a range for forward selection) is left out.
    """
    from gyronet.model.rbf_init import SelectionError

    kept, figures, fits = [], [], []
    for start in starts:
        try:
            results = [fit_start(start, fold, fit, optim, options)[:2] for fold in folds]
        except SelectionError as err:
            log.info("no %s start (%s)", start.name, err)
            continue
        kept.append(start)
        figures.append([r[0] for r in results])
        fits.append([r[1] for r in results])
    return kept, figures, fits


def most_steps(figures: Sequence[Sequence[dict]]) -> int | None:
    """The largest best step count over a start's folds and members (None for a closed-form model).

    The final fit has every run, more data than any fold, so it overfits no sooner than the fold
    that stopped last. The median undercounts where the folds disagree, and a fit stopped short
    extrapolates worse (survey sensors 102, 103 and 105 as two runs: the worst axis 1-5 % better).
    """
    best = [m["train/best_step"] for members in figures for m in members if "train/best_step" in m]
    return int(max(best)) if best else None


def fit_final(model: nn.Module, starts: Sequence[Start], weights: np.ndarray, steps: Sequence[int | None], data: Any,
              fit: Callable, optim: Callable | None, options: Mapping[str, Any]) -> tuple[list[nn.Module], float]:
    """Each start with a weight trained on every run for its steps, mixed into ``model`` with its run offsets.

    Returns the parts (the error bar's members) and the members' mean training loss.
    """
    parts, raws, losses = [], [], []
    for start, n in zip(starts, steps):
        member_figures, part, raw = fit_start(start, data, fit, optim, options, n)
        parts.append(part)
        raws.append(raw)
        losses += [m["train/loss"] for m in member_figures]
    mix_into(model, parts, weights)
    if getattr(data, "offsets", None) is not None:
        mix_offsets(data.offsets, raws, weights)
    return parts, float(np.mean(losses))


def demeaned_residuals(model: nn.Module, fold: Any) -> np.ndarray:
    """The held-out run's 60 s block means of measured minus predicted drift, less the run's mean (its turn-on bias)."""
    time_s, x, y = fold.val_full
    residual = y - predict(model, x)
    return residual_block_means(time_s, residual - residual.mean(0), 60.0)


def stack_by_run(fits: Sequence[Sequence[nn.Module]], folds: Sequence[Any]) -> np.ndarray:
    """(starts, axes) weights stacked on every fold's held-out run: ``fits[f][k]`` is start k's fit in fold f."""
    residuals = [np.concatenate([demeaned_residuals(fold_fits[k], fold) for fold_fits, fold in zip(fits, folds)])
                 for k in range(len(fits[0]))]
    return stack_weights(*residuals)


def mixed(parts: Sequence[nn.Module], weights: np.ndarray) -> nn.Module:
    """A new model whose output is ``sum_k weights[k, a] parts[k]`` on each axis (the one part itself when alone)."""
    if len(parts) == 1:
        return parts[0]
    model = copy.deepcopy(parts[0])
    mix_into(model, parts, weights)
    return model


@torch.no_grad()
def mix_offsets(offsets: Any, raws: Sequence[torch.Tensor], weights: np.ndarray) -> None:
    """``offsets`` (``RunOffsets``) becomes the per-axis weighted sum of the starts' final offsets."""
    scale = torch.as_tensor(np.asarray(weights), dtype=raws[0].dtype)  # (starts, axes)
    offsets.raw.copy_(sum(raw * w[None, :] for raw, w in zip(raws, scale)))


def describe(starts: Sequence[Start], weights: np.ndarray, held_out: Sequence[float], n_runs: int) -> str:
    """The log line: each start's mean held-out error over the folds and its weights per axis."""
    if len(starts) == 1:
        return (f"the {starts[0].name} start alone ({len(starts[0].seeds)} seeds averaged), mean held-out "
                f"{held_out[0]:.4g} deg/s on the {n_runs} held-out runs")
    return (f"starts mixed per axis on the {n_runs} held-out runs (mean held-out "
            + ", ".join(f"{s.name} {e:.4g}" for s, e in zip(starts, held_out)) + " deg/s): weights x/y/z "
            + ", ".join(f"{s.name} " + "/".join(f"{w:.2f}" for w in row) for s, row in zip(starts, weights)))


__all__ = ["Start", "demeaned_residuals", "describe", "fit_final", "fit_folds", "fit_start", "most_steps", "mix_offsets", "mixed",
           "stack_by_run", "starts_of"]
