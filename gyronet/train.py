"""``fit()`` and ``evaluate()``: train a drift model on block-averaged data, score it on held-out data.

The loop is plain full-batch Adam with a cosine learning-rate schedule and early stopping on the
validation error, because a 12.7 h record averaged over 10 s is only ~4,600 points.
"""
from __future__ import annotations

import copy
import logging
import math
from typing import Any, Callable, Mapping

import numpy as np
import torch
from tqdm.auto import tqdm

from gyronet.data import AXES
from gyronet.dataset import Blocks, DriftData, block_rmse
from gyronet.errors import GyronetError

log = logging.getLogger(__name__)


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
    if getattr(data, "val_adjust", None) is not None:  # e.g. the held-out run's start-up offset (gyronet.runs)
        residual = data.val_adjust(time_s, residual)
    rmse = block_rmse(time_s, residual, 60.0)
    metrics = {f"val/rmse_{a}_dps": float(v) for a, v in zip(AXES, rmse)}
    metrics["val/rmse_dps"] = float(np.mean(rmse))
    return metrics


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
        Show a tqdm bar.
    threads
        Torch threads. One by default: the problem is a few thousand points, where more threads
        only add overhead; sweeps get their parallelism from jobs running side by side.
    stop_at_step
        Train exactly this many steps and keep the last state, without validation (the final fit
        on every run of a campaign, ``gyronet.runs.fit_by_run``).
    warm_start
        Start from the model's current state (its box widened to ``data``) instead of initialising it.
    for_bundle
        This fit makes the bundle: nothing is scored on ``data.val`` after it, so a model that asks
        for it (``RBFNet.refit_all``) continues on every block once validation has confirmed the
        fit. Off for fits that are themselves validated afterwards (the diagnosis's folds).
    """
    if threads:
        torch.set_num_threads(threads)
    torch.manual_seed(seed)
    from gyronet.error_bar_fit import detach

    detach(model)  # a new fit: the error bar's statistics of an earlier one no longer apply
    x = torch.as_tensor(data.train.x, dtype=torch.float64)
    y = torch.as_tensor(data.train.y, dtype=torch.float64)
    offsets = getattr(data, "offsets", None)  # gyronet.runs.RunOffsets: one constant per training run and axis
    if hasattr(model, "fit_closed_form"):
        model.fit_closed_form(x, y) if offsets is None else offsets.fit_closed_form(model, x, y)
        pred = (model(x) if offsets is None else model(x) + offsets()).detach()
        metrics = {"train/loss": float(torch.mean((pred - y) ** 2)), **validation_metrics(model, data)}
        _check_finite(metrics, "the closed-form fit")
        return metrics
    if (getattr(model, "validate_init", False) and not warm_start and stop_at_step is None and offsets is None
            and getattr(data, "held_out", None) is None):
        options = dict(max_epochs=max_epochs, patience=patience, eval_every=eval_every, seed=seed,
                       weight_decay=weight_decay, progress=progress, threads=threads)
        from gyronet.starts import fit_every_start

        return fit_every_start(model, data, optim, {**options, "writer": writer}, for_bundle)
    if warm_start:
        _widen_box(model, x)
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
    bar = tqdm(range(max_epochs), desc="fit", disable=not progress, leave=False, mininterval=1.0)
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
        _check_finite(final, "the trained model")
        return final
    if "train/loss" not in best:  # the validation error was never a finite number
        raise GyronetError(f"training gave no finite validation error in {step + 1} steps (last "
                           f"val/rmse_dps {metrics['val/rmse_dps']}); check the validation recording")
    model.load_state_dict(best_state)
    chosen = _select_capacity(model, data) if getattr(model, "select_capacity", False) else {}
    final = {"train/loss": best["train/loss"], "train/steps": step + 1, "train/best_step": best["train/best_step"],
             **validation_metrics(model, data), **chosen}
    _check_finite(final, "the trained model")
    if for_bundle and getattr(model, "refit_all", False) and _every_block(data) is not None:
        from gyronet import error_bar_fit  # the error bar's held-out blocks, before the refit sees them

        time_s, vx, vy = data.val_full
        error_bar_fit.attach(model, error_bar_fit.held_out_stats(model, None, time_s, vx, vy, data.train.x))
    if for_bundle:
        _continue_on_every_block(model, data, final, optim, dict(
            max_epochs=max_epochs, patience=patience, eval_every=eval_every, seed=seed, weight_decay=weight_decay,
            progress=progress, threads=threads))
    return final


def _continue_on_every_block(model: torch.nn.Module, data: DriftData, final: Mapping[str, float],
                             optim: Callable | None, options: Mapping[str, Any]) -> None:
    """``RBFNet.refit_all``: continue a validated fit on every block of its recording, keeping its capacity."""
    everything = _every_block(data) if getattr(model, "refit_all", False) else None
    if everything is None:
        return
    fit(model, everything, optim, **options, stop_at_step=options["max_epochs"], warm_start=True)
    if "model/level_x" in final:
        from gyronet import capacity

        capacity.apply(model, everything, [int(final[f"model/level_{a}"]) for a in AXES])
    log.info("continued on every block (%d) for %d steps", len(everything.train), options["max_epochs"])


def _widen_box(model: torch.nn.Module, x: torch.Tensor) -> None:
    """Widen an RBFNet's trained box to hold ``x`` (a warm start on more data)."""
    if hasattr(model, "z_low"):
        with torch.no_grad():
            z = (x - model.x_mean) / model.x_std
            model.z_low.copy_(torch.minimum(model.z_low, z.min(0).values))
            model.z_high.copy_(torch.maximum(model.z_high, z.max(0).values))


def _every_block(data: DriftData) -> DriftData | None:
    """One recording's data with every block to train on (None: validation is another recording, or runs)."""
    if not isinstance(data, DriftData) or data.val_path:
        return None
    everything = copy.copy(data)
    everything.train = Blocks(*(np.concatenate([getattr(data.train, k), getattr(data.val, k)])
                                for k in ("x", "y", "time_s")))
    return everything


def _select_capacity(model: torch.nn.Module, data: DriftData) -> dict[str, float]:
    """Every capacity level's held-out error per axis; on one recording, also keep each axis's best level.

    A fold of several runs only reports the errors: ``gyronet.runs.fit_by_run`` chooses from all folds.
    """
    from gyronet import capacity

    errors = capacity.level_errors(model, data)
    levels = None
    if getattr(data, "held_out", None) is None:
        levels = capacity.choose(errors)
        capacity.apply(model, data, levels)
    return capacity.as_metrics(errors, levels)


def _check_finite(metrics: Mapping[str, float], what: str) -> None:
    bad = sorted(k for k, v in metrics.items() if not math.isfinite(v))
    if bad:
        raise GyronetError(f"{what} gives non-finite {', '.join(bad)} ({metrics[bad[0]]}): the fit diverged")


def residual_report(time_s: np.ndarray, compensated_dps: np.ndarray, truth: Mapping[str, np.ndarray],
                    block_s: float = 60.0) -> dict[str, Any]:
    """Score a compensated record against the simulator's ground truth, per axis.

    The residual is compensated minus true rate; the noise floor is the same block statistic of
    the noise the simulator actually added, so a ratio of 1 means "drift fully removed".
    """
    true_rate = np.column_stack([truth[f"true_rate_{a}_dps"] for a in AXES])
    noise = np.column_stack([truth[f"noise_{a}_dps"] for a in AXES])
    residual = block_rmse(time_s, compensated_dps - true_rate, block_s)
    floor = block_rmse(time_s, noise, block_s)
    return {
        "residual_dps": dict(zip(AXES, residual.tolist())),
        "noise_floor_dps": dict(zip(AXES, floor.tolist())),
        "ratio_to_floor": dict(zip(AXES, (residual / floor).tolist())),
    }


def evaluate(compensator: Any, recording: Any, truth: Mapping[str, np.ndarray] | None = None,
             block_s: float = 60.0) -> dict[str, Any]:
    """Run a compensator over a whole recording and score it: Allan N and B raw and compensated,
    and, with ground truth, the residual against the true rate and the noise floor.

    Returns the report dict and keeps the arrays for plots under the private key ``_arrays``.
    """
    from gyronet.allan import allan_report

    compensator.reset()
    out = compensator.process(recording.columns)
    raw = recording.gyro_dps
    report: dict[str, Any] = {
        "path": recording.path,
        "n_samples": len(recording),
        "n_out_of_range": int(out.out_of_range.sum()),
        "allan": {"raw": _allan_summary(allan_report(recording.time_s, raw)),
                  "compensated": _allan_summary(allan_report(recording.time_s, out.rate_dps))},
    }
    arrays = {"time_s": recording.time_s, "temp_c": recording.temp_c, "raw_dps": raw,
              "compensated_dps": out.rate_dps, "drift_hat_dps": out.drift_dps, "drift_sigma_dps": out.drift_sigma_dps}
    if truth is not None:
        report["truth"] = residual_report(recording.time_s, out.rate_dps, truth, block_s)
        noise = np.column_stack([truth[f"noise_{a}_dps"] for a in AXES])
        report["allan"]["noise_only"] = _allan_summary(allan_report(recording.time_s, noise))
        arrays["drift_true_dps"] = np.column_stack([truth[f"drift_{a}_dps"] for a in AXES])
    if out.drift_sigma_dps is not None and np.isfinite(out.drift_sigma_dps).all():
        from gyronet.sigma_table import error_bar_summary

        report["error_bar"] = error_bar_summary(recording.time_s, out, arrays.get("drift_true_dps"), block_s)
    report["_arrays"] = arrays
    return report


def _allan_summary(report: Mapping[str, Any]) -> dict[str, Any]:
    keys = ("arw_deg_rthr", "bias_instability_deg_hr", "rrw_deg_hr_rthr", "taus_s", "adev_dps")
    return {axis: {k: report[axis][k] for k in keys if k in report[axis]} for axis in AXES}
