"""``fit()``: train a drift model on block-averaged data (``evaluate()`` scores it on held-out data).

The loop is plain full-batch Adam with a cosine learning-rate schedule and early stopping on the
validation error, because a 12.7 h record averaged over 10 s is only ~4,600 points.
"""
from __future__ import annotations

import copy
import logging
import numbers
from typing import Any, Callable

import torch
from tqdm.auto import tqdm

from gyronet.errors import ConfigError, GyronetError
from gyronet.training import error_bar_fit
from gyronet.training.dataset import Blocks, DriftData, block_rmse  # noqa: F401 (Blocks, block_rmse: old imports)
from gyronet.training.evaluate import evaluate, residual_report
from gyronet.training.refit import continue_on_every_block, every_block, widen_box
from gyronet.training.starts import fit_every_start
from gyronet.training.steps import check_finite, lr_at, predict, validation_metrics

log = logging.getLogger(__name__)


def fit(model: torch.nn.Module, data: DriftData, optim: Callable | None = None, max_epochs: int = 3000,
        patience: int = 400, eval_every: int = 25, seed: int = 0, weight_decay: float = 0.0,
        writer: Any = None, progress: bool = True, threads: int | None = 1,
        stop_at_step: int | None = None, warm_start: bool = False, for_bundle: bool = False) -> dict[str, float]:
    """Fit ``model`` to ``data.train`` and return the final metrics (``val/rmse_dps`` first of all).

    Parameters
    ----------
    model
        An ``RBFNet`` (trained by Adam), or a model with ``fit_closed_form(x, y)`` (baselines).
    data
        Block-averaged training and validation data.
    optim
        A partial optimizer: ``optim(params) -> torch.optim.Optimizer``; Adam(lr=1e-2) by default.
    max_epochs, patience, eval_every
        Full-batch steps, and early stopping when validation has not improved for ``patience`` steps.
    seed
        Seeds the centre initialisation and torch, so a run is reproducible.
    weight_decay
        L2 penalty on the output weights, relative to the loss on normalised targets.
    writer
        Optional ``SummaryWriter`` for ``train/loss`` and ``val/rmse_dps`` curves.
    progress
        Show a tqdm bar while fitting, on a terminal only; a log gets one line per fit with its figures.
    threads
        Torch threads. One by default: the problem is a few thousand points, where more threads
        only add overhead; sweeps get their parallelism from jobs running side by side.
    stop_at_step
        Train exactly this many steps and keep the last state, without validation (the final fit
        on every run of a campaign, ``gyronet.training.runs.fit_by_run``).
    warm_start
        Start from the model's current state (its box widened to ``data``) instead of initialising it.
    for_bundle
        This fit makes the bundle: nothing is scored on ``data.val`` after it, so a model that asks
        for it (``RBFNet.refit_all``) continues on every block once validation has confirmed the
        fit. Off for fits that are themselves validated afterwards (the diagnosis's folds).
    """
    for name, value, least in (("max_epochs", max_epochs, 1), ("eval_every", eval_every, 1), ("patience", patience, 0)):
        if not (isinstance(value, numbers.Integral) and value >= least):  # 0 steps left nothing to report, 0 divided by zero
            raise ConfigError(f"train.{name} must be a whole number >= {least}, got {value!r}")
    if threads:
        torch.set_num_threads(threads)
    torch.manual_seed(seed)
    error_bar_fit.detach(model)  # a new fit: the error bar's statistics of an earlier one no longer apply
    x = torch.as_tensor(data.train.x, dtype=torch.float64)
    y = torch.as_tensor(data.train.y, dtype=torch.float64)
    offsets = getattr(data, "offsets", None)  # gyronet.training.runs.RunOffsets: one constant per training run and axis
    if hasattr(model, "fit_closed_form"):
        model.fit_closed_form(x, y) if offsets is None else offsets.fit_closed_form(model, x, y)
        pred = (model(x) if offsets is None else model(x) + offsets()).detach()
        metrics = {"train/loss": float(torch.mean((pred - y) ** 2)), **validation_metrics(model, data)}
        check_finite(metrics, "the closed-form fit")
        return metrics
    if (getattr(model, "validate_init", False) and not warm_start and stop_at_step is None and offsets is None
            and getattr(data, "held_out", None) is None):
        options = dict(max_epochs=max_epochs, patience=patience, eval_every=eval_every, seed=seed,
                       weight_decay=weight_decay, progress=progress, threads=threads)
        return fit_every_start(model, data, optim, {**options, "writer": writer}, for_bundle, fit)
    if warm_start:
        widen_box(model, x)
    elif offsets is None:
        model.init_from_data(x, y, torch.Generator().manual_seed(seed))
    else:
        offsets.init_from_data(model, x, y, seed)
    params = [p for p in model.parameters() if p.requires_grad] + ([] if offsets is None else [offsets.raw])
    optimizer = (optim or (lambda p: torch.optim.Adam(p, lr=1e-2)))(params)
    base_lrs = [g["lr"] for g in optimizer.param_groups]
    y_norm = (y - model.y_mean) / model.y_std
    best = {"val/rmse_dps": float("inf")}
    best_state, since_best = copy.deepcopy(model.state_dict()), 0
    drift = model.on_fixed_input(x) if hasattr(model, "on_fixed_input") else lambda: model(x)
    # a bar on a terminal only (None: tqdm asks stderr); a log file gets the one line per fit below
    bar = tqdm(range(max_epochs), desc="fit", disable=None if progress else True, leave=False, mininterval=1.0)
    for step in bar:
        for group, base in zip(optimizer.param_groups, base_lrs):
            group["lr"] = lr_at(step, max_epochs, base)
        optimizer.zero_grad(set_to_none=True)
        # loss on normalised targets, so every axis counts the same
        pred = drift() if offsets is None else drift() + offsets()
        loss = torch.mean(((pred - model.y_mean) / model.y_std - y_norm) ** 2)
        if weight_decay:
            loss = loss + weight_decay * (model.head.weight.pow(2).sum() + model.poly.weight.pow(2).sum())
        if not torch.isfinite(loss):
            raise GyronetError(f"training diverged at step {step}: the loss is {loss.item()} (lower optim.lr, "
                               "or check the recording for extreme values)")
        loss.backward()
        optimizer.step()
        if hasattr(model, "keep_widths_"):
            model.keep_widths_()
        if stop_at_step is not None:  # a fixed budget: no validation run to stop on
            if step + 1 >= stop_at_step:
                break
            continue
        if step % eval_every == 0 or step == max_epochs - 1:
            metrics = {"train/loss": loss.item(), **validation_metrics(model, data, full_rate=False)}
            if writer is not None:
                for tag, value in metrics.items():
                    writer.add_scalar(tag, value, step)
            bar.set_postfix(loss=f"{loss.item():.3g}", val=f"{metrics['val/rmse_dps']:.3g}")
            if metrics["val/rmse_dps"] < best["val/rmse_dps"]:
                best, best_state, since_best = ({**metrics, "train/best_step": step + 1},
                                                copy.deepcopy(model.state_dict()), 0)
            else:
                since_best += eval_every
                if since_best >= patience:
                    log.info("early stop at step %d (best val %.4g deg/s)", step, best["val/rmse_dps"])
                    break
    if stop_at_step is not None:
        final = {"train/loss": loss.item(), "train/steps": step + 1}
        check_finite(final, "the trained model")
        return final
    if "train/loss" not in best:  # the validation error was never a finite number
        raise GyronetError(f"training gave no finite validation error in {step + 1} steps (last "
                           f"val/rmse_dps {metrics['val/rmse_dps']}); check the validation recording")
    model.load_state_dict(best_state)
    chosen = _select_capacity(model, data) if getattr(model, "select_capacity", False) else {}
    final = {"train/loss": best["train/loss"], "train/steps": step + 1, "train/best_step": best["train/best_step"],
             **validation_metrics(model, data), **chosen}
    check_finite(final, "the trained model")
    log.info("fit: %d steps (best %d), held-out 60 s RMSE %s deg/s", final["train/steps"], final["train/best_step"],
             "/".join(f"{final.get(f'val/rmse_{a}_dps', float('nan')):.4g}" for a in ("x", "y", "z")))
    stats = None
    if for_bundle and getattr(model, "refit_all", False) and every_block(data) is not None:
        # the error bar's held-out blocks, before the refit sees them
        time_s, vx, vy = data.val_full
        stats = error_bar_fit.held_out_stats(model, None, time_s, vx, vy, data.train.x)
    if for_bundle:
        continue_on_every_block(model, data, final, optim, dict(
            max_epochs=max_epochs, patience=patience, eval_every=eval_every, seed=seed, weight_decay=weight_decay,
            progress=progress, threads=threads), fit)
    if stats is not None:  # attached after the refit, whose own fit() starts by detaching what an earlier fit left
        error_bar_fit.attach(model, stats)
    return final


def _select_capacity(model: torch.nn.Module, data: DriftData) -> dict[str, float]:
    """Every capacity level's held-out error per axis; on one recording, also keep each axis's best level.

    A fold of several runs only reports the errors: ``gyronet.training.runs.fit_by_run`` chooses from all folds.
    """
    from gyronet.training import capacity

    errors = capacity.level_errors(model, data)
    levels = None
    if getattr(data, "held_out", None) is None:
        levels = capacity.choose(errors)
        capacity.apply(model, data, levels)
    return capacity.as_metrics(errors, levels)


__all__ = ["Blocks", "DriftData", "block_rmse", "evaluate", "fit", "lr_at", "predict", "residual_report", "validation_metrics"]
