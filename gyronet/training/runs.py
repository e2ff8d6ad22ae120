"""Calibration campaigns: several runs of one unit in one training, each run a thing of its own.

Real calibration comes in runs (one chamber run, one power-up, one orientation), each with its own
turn-on bias. A ``Run`` keeps its recording, its causal features (a fresh extractor per run, so no
filter state leaks across a run's edge) and its drift targets; 10 s blocks are formed within each
run. With two or more runs the held-out data are whole runs, leave-one-run-out (``fit_by_run``):
the only honest answer to "does it transfer to another thermal history". Optionally one constant
per run and axis (``RunOffsets``) is fitted beside the model, as a nuisance parameter, so the
temperature model learns only what the runs share. A model with ``select_capacity`` gets each
axis's capacity from every fold's held-out run (``gyronet.training.capacity``): what repeats from run to run.
A model with ``validate_init`` gets every start, mixed per axis by the held-out runs (``.run_starts``).
"""
from __future__ import annotations

import hashlib
import logging
import math
from typing import Any, Callable, Sequence

import numpy as np
from torch import nn

from gyronet.errors import ConfigError, GyronetError
from gyronet.model.features import PAPER_FEATURES
from gyronet.recordings.data import AXES, held_out_span
from gyronet.training.capacity import MIN_IN_BOX_S, inside_box
from gyronet.training.dataset import MIN_TRAIN_BLOCKS, DriftData, TrainingData
from gyronet.training.run_data import Run, RunBlocks, check_long_enough, load_runs, scored_after_startup, run_name, stack_runs
from gyronet.training.run_offsets import RunOffsets

log = logging.getLogger(__name__)


class RunsData(TrainingData):
    """Several runs as training data: ``fit`` trains on every run but ``held_out`` and validates on it.

    Parameters
    ----------
    runs
        The campaign's runs (``load_runs``).
    features, block_s, static_rate_dps
        As in ``DriftData``.
    held_out
        Index of the run held out for validation; None: train on every run (the final fit, whose
        "validation" is then the longest run, in sample, and only there for ``fit``'s interface).
    run_offsets
        Fit one constant per training run and axis beside the model (with two or more training runs).
    val_startup_s
        Score the held-out run as deployed with ``startup.still_s`` of this many seconds: its residual
        minus its mean over the first ``val_startup_s`` s (0: as is). A run's turn-on bias is
        otherwise part of the score, the same for every model and unknowable from the other runs.
    """

    def __init__(self, runs: Sequence[Run], features: list, block_s: float = 10.0,
                 static_rate_dps: Sequence[float] | None = None, held_out: int | None = None,
                 run_offsets: bool = False, val_startup_s: float = 0.0):
        self.runs, self.features, self.block_s = list(runs), [dict(s) for s in features], float(block_s)
        self.static_rate_dps, self.held_out, self.run_offsets = static_rate_dps, held_out, bool(run_offsets)
        self.val_startup_s = float(val_startup_s or 0.0)
        self.train_runs = [r for r in self.runs if r.index != held_out]
        self.paths = [r.path for r in self.runs]
        self.path = self.paths[0]
        self.fs_hz = self.runs[0].recording.fs_hz
        self.train = stack_runs(self.train_runs, self.block_s)
        # the longest run, ties broken by path so that the order of data.paths does not choose the Kalman stage's record
        val_run = (self.runs[held_out] if held_out is not None
                   else max(self.train_runs, key=lambda r: (len(r.time_s), str(r.path))))
        self.recording = (val_run if held_out is None else self.train_runs[0]).recording  # the Kalman stage's record
        self.val = val_run.blocks(self.block_s)
        self.val_full = (val_run.time_s, val_run.features, val_run.targets)
        lows, highs = zip(*(r.temp_range_c for r in self.train_runs))
        self.temp_range_c = (min(lows), max(highs))  # the union of the training runs' ranges
        self.offsets = (RunOffsets(self.train.run, len(self.train_runs))
                        if self.run_offsets and len(self.train_runs) >= 2 else None)
        for run, blocks in zip(self.train_runs, (r.blocks(self.block_s) for r in self.train_runs)):
            if len(blocks) < MIN_TRAIN_BLOCKS:
                raise GyronetError(f"{run.path}: too short to train on ({len(blocks)} blocks of {self.block_s} s)")
        log.info("training runs %s, %d blocks of %g s%s", ", ".join(r.name for r in self.train_runs), len(self.train),
                 self.block_s, f"; validation run {val_run.name}" if held_out is not None else "")

    def holding_out(self, index: int) -> "RunsData":
        """The same runs with run ``index`` held out (one fold of leave-one-run-out)."""
        return RunsData(self.runs, self.features, self.block_s, self.static_rate_dps, index, self.run_offsets,
                        self.val_startup_s)

    def val_adjust(self, time_s: np.ndarray, residual: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The held-out residual as a start-up offset over the first ``val_startup_s`` s would leave it, and the
        rows that offset applies to (those after the window; the window's own are zero-mean by construction)."""
        if self.held_out is None or self.val_startup_s <= 0:
            return np.ones(len(time_s), dtype=bool), residual
        return scored_after_startup(time_s, residual, self.val_startup_s)

    @property
    def n_runs(self) -> int:
        return len(self.runs)


    def bundle_meta(self) -> dict[str, Any]:
        """``meta.json`` fields of a multi-run training: every run, a checksum over them, the fitted offsets."""
        described = [r.describe() for r in self.train_runs]
        meta: dict[str, Any] = {"runs": described, "data_sha256": hashlib.sha256(
            "".join(d["sha256"] for d in described).encode()).hexdigest()}
        if self.offsets is not None:
            values = self.offsets.values().detach().numpy()
            meta["run_offsets_dps"] = {r.name: v.tolist() for r, v in zip(self.train_runs, values)}
        return meta


def _say_held_out_share(val_fraction: float, n_blocks: int, val_fold: int | None) -> None:
    """Refuse a split that holds out nothing or everything; say the share held out when it is not ``val_fraction``."""
    if not 0.0 < val_fraction < 1.0:
        raise ConfigError(f"data.val_fraction must be in (0, 1), got {val_fraction}")
    k, which = held_out_span(val_fraction, val_fold)
    held = sum(1 for span in range(n_blocks) if span % k == which)
    if not 0 < held < n_blocks:  # was refused as "too short to train on", which the recording was not
        raise ConfigError(f"data.n_blocks={n_blocks} with data.val_fraction={val_fraction:g} (one span in {k} held out) "
                          f"leaves {'no span to validate on' if held == 0 else 'no span to train on'}")
    if abs(held / n_blocks - val_fraction) > 0.01:
        log.warning("data.val_fraction=%g holds out one span in %d of data.n_blocks=%d: %d spans, %.0f %% of the "
                    "record", val_fraction, k, n_blocks, held, 100.0 * held / n_blocks)


def training_data(path: str | None = None, paths: Sequence[str] | None = None, run_offsets: bool = False,
                  val_startup_s: float = 0.0, features: list | None = None, block_s: float = 10.0,
                  val_fraction: float = 0.2, n_blocks: int = 10, val_fold: int | None = None,
                  val_path: str | None = None, static_rate_dps: Sequence[float] | None = None,
                  rate_tau_s: float | None = None) -> DriftData | RunsData:
    """``conf/data``'s target: one recording (``path``, interleaved time blocks) or several (``paths``, by run).

    The options after ``val_startup_s`` are ``DriftData``'s; ``val_fraction``, ``n_blocks``,
    ``val_fold`` and ``val_path`` apply to one recording only, ``val_startup_s`` to both (as
    deployed: by run, or the starts' mixing on one recording, ``gyronet.training.starts``).
    """
    if rate_tau_s is not None and not rate_tau_s > 0:  # 0 divides by zero, a negative one diverges the fit
        raise ConfigError(f"data.rate_tau_s must be > 0 s (the dT/dt tracker's time constant), got {rate_tau_s}")
    if not (block_s > 0 and math.isfinite(block_s)):  # a negative one averaged nothing, silently; 0 a cryptic error
        raise ConfigError(f"data.block_s must be > 0 s (the averaging block the model is fitted on), got {block_s}")
    if val_startup_s is not None and not (val_startup_s >= 0 and math.isfinite(val_startup_s)):
        # a negative one was taken as 0 but written to the bundle, which then never widened the bar for the offset
        raise ConfigError(f"data.val_startup_s must be >= 0 s (the start-up window held-out runs are scored after; "
                          f"0: none), got {val_startup_s}")
    if path is not None and paths:
        raise GyronetError("give data.path=F.csv (one recording) or data.paths=[A.csv,B.csv] (several runs), not both")
    if path is None and not paths:
        raise GyronetError("no training data: give data.path=F.csv or data.paths=[A.csv,B.csv]")
    features = [dict(s) for s in (features or PAPER_FEATURES)]
    if path is not None or len(paths) == 1:
        if not val_path:
            _say_held_out_share(val_fraction, n_blocks, val_fold)
        if run_offsets:
            log.debug("data.run_offsets needs two or more runs: off for one recording")
        return DriftData(path=str(path if path is not None else paths[0]), features=features, block_s=block_s,
                         val_fraction=val_fraction, n_blocks=n_blocks, val_fold=val_fold, val_path=val_path,
                         static_rate_dps=static_rate_dps, rate_tau_s=rate_tau_s, val_startup_s=val_startup_s)
    if val_path:
        raise GyronetError("data.val_path and data.paths: with several runs the held-out data are the runs "
                           "themselves (leave-one-run-out); drop data.val_path")
    if rate_tau_s is not None:
        for spec in features:
            if spec["kind"] == "rate":
                spec["tau_s"] = float(rate_tau_s)
    runs = load_runs([str(p) for p in paths], features, static_rate_dps)
    check_long_enough(runs, float(val_startup_s or 0.0), block_s)
    return RunsData(runs, features, block_s, static_rate_dps, run_offsets=run_offsets, val_startup_s=val_startup_s)


def fit_by_run(model: nn.Module, data: RunsData, optim: Callable | None = None, seed: int = 0, writer: Any = None,
               **fit_kwargs: Any) -> tuple[dict[str, float], list[dict[str, Any]]]:
    """Leave-one-run-out, then the final fit on every run.

    Each run is held out in turn; a fresh copy of ``model`` is fitted on the others (early stopping
    on the held-out run) and scored on it. ``val/*`` are the means over the folds. The final model
    is trained on every run for the largest of the folds' best step counts: with no run left to
    stop on, the folds say how long a fit on one run fewer trains before it overfits, and with more
    data the final fit overfits no sooner (a closed-form model needs no count, nor one whose chosen
    capacity keeps no Gaussians). With ``validate_init`` every start is fitted so and mixed per
    axis by the held-out runs (``gyronet.training.run_starts``).

    Returns
    -------
    metrics, folds
        The metrics (``val/rmse_dps`` first of all) and each fold's figures.
    """
    from gyronet.training import error_bar_fit, run_starts
    from gyronet.training.starts import spread_figures
    from gyronet.training.train import fit

    fold_data = [data.holding_out(run.index) for run in data.runs]
    starts, figures, fits = run_starts.fit_folds(run_starts.starts_of(model, data, seed), fold_data, fit, optim,
                                                 fit_kwargs)
    by_fold = [list(f) for f in zip(*fits)]  # by_fold[f][k]: start k's fit in fold f
    plain = len(starts) == 1 and len(starts[0].seeds) == 1  # one fit per fold, as any model without starts
    weights = run_starts.stack_by_run(by_fold, fold_data) if len(starts) > 1 else np.ones((1, len(AXES)))
    used = [k for k in range(len(starts)) if weights[k].any()]
    fold_parts = [[fold_fits[k] for k in used] for fold_fits in by_fold]
    fold_models = [run_starts.mixed(parts, weights[used]) for parts in fold_parts]
    steps = [run_starts.most_steps(f) for f in figures]
    folds = [_fold_record(run, fold, fold_model, figures[0][f][0] if plain else _mixture_figures(
                 model, fold, fold_model, starts, [s[f] for s in figures]))
             for f, (run, fold, fold_model) in enumerate(zip(data.runs, fold_data, fold_models))]

    levels = None
    if getattr(model, "select_capacity", False):  # each axis's level, from every fold's held-out run
        from gyronet.training import capacity

        errors = capacity.from_metrics(folds)
        levels = capacity.choose(errors)
        if max(levels) < len(capacity.LEVELS) - 1:  # no axis keeps its Gaussians: the refit below replaces
            steps = [None if n is None else 1 for n in steps]  # all a trained final fit would learn
            log.info("no axis keeps its Gaussians (%s): the final fit is least squares at those levels (%s)",
                     "/".join(capacity.LEVELS[v] for v in levels), capacity.INERT)
    parts = None
    if plain:
        final = fit(model, data, optim, seed=seed, writer=writer, stop_at_step=steps[0], **fit_kwargs)
    else:
        parts, loss = run_starts.fit_final(model, [starts[k] for k in used], weights[used], [steps[k] for k in used],
                                           data, fit, optim, fit_kwargs)
        final = {"train/loss": loss}
        log.info(run_starts.describe(starts, weights, [np.mean([m["val/rmse_dps"] for members in figures[k]
                                                                for m in members]) for k in range(len(starts))],
                                     data.n_runs))
    out = {"train/loss": final["train/loss"]}
    for key in [f"val/rmse_{a}_dps" for a in AXES] + ["val/rmse_dps"]:
        out[key] = float(np.mean([f[key] for f in folds]))
    if plain and steps[0] is not None:
        out["train/steps"] = steps[0]
    if not plain:
        out.update({f"train/steps_{s.name}": float(n) for s, n in zip(starts, steps) if n is not None})
        out.update({f"model/{s.name}_weight_{a}": float(weights[k, j]) for k, s in enumerate(starts)
                    for j, a in enumerate(AXES)})
        # the spread over what was tried: each start's members, their held-out figures averaged over the folds
        out.update(spread_figures([{f"val/rmse_{a}_dps": float(np.mean([members[j][f"val/rmse_{a}_dps"]
                                                                          for members in figures[k]])) for a in AXES}
                                   for k in range(len(starts)) for j in range(len(starts[k].seeds))]))
    if levels is not None:
        for part in parts or []:  # the bar's members as deployed
            capacity.refit(part, data, levels)
        capacity.apply(model, data, levels)
        for fold_model, fold, members in zip(fold_models, fold_data, fold_parts):  # the bar is calibrated on what
            for m in {id(m): m for m in [fold_model, *members]}.values():  # is deployed: the chosen levels
                capacity.refit(m, fold, levels)
        out.update(capacity.as_metrics(errors, levels))
    fold_stats = [error_bar_fit.held_out_stats(m, members if len(members) > 1 else None, *d.val_full, d.train.x,
                                               d.val_adjust) for m, d, members in zip(fold_models, fold_data, fold_parts)]
    pooled, by_run = error_bar_fit.cross_check(fold_stats)
    error_bar_fit.attach(model, error_bar_fit.merge_stats(fold_stats, {
        "held_out": [r.name for r in data.runs], "startup_s": data.val_startup_s, "cross_within_1_sigma": pooled,
        "cross_within_1_sigma_by_run": dict(zip((r.name for r in data.runs), by_run))}),
        parts if parts and len(parts) > 1 else None)
    out.update({f"val/cross_within_1_sigma_{a}": v for a, v in zip(AXES, pooled)})
    counted = [n for n in steps if n is not None]
    how = (" by least squares" if counted and max(counted) <= 1  # no Gaussians kept: one step, the refit
           else f" for {'/'.join(map(str, counted))} steps" if counted else "")
    log.info("leave-one-run-out over %d runs: mean held-out 60 s RMSE %.4g deg/s; final fit on every run%s",
             data.n_runs, out["val/rmse_dps"], how)
    return out, folds


def _mixture_figures(model: nn.Module, fold: RunsData, fold_model: nn.Module, starts: Sequence[Any],
                     figures: Sequence[Sequence[dict]]) -> dict[str, float]:
    """A fold's figures for the mixture of its starts: its held-out errors, each start's steps, the capacity evidence."""
    from gyronet.training.steps import validation_metrics

    metrics = {**validation_metrics(fold_model, fold), **{
        f"train/best_step_{s.name}": float(np.median([m["train/best_step"] for m in members]))
        for s, members in zip(starts, figures) if all("train/best_step" in m for m in members)}}
    if getattr(model, "select_capacity", False):
        from gyronet.training import capacity

        metrics.update(capacity.as_metrics(capacity.level_errors(fold_model, fold)))
    return metrics


def _fold_record(run: Run, fold: RunsData, fold_model: nn.Module, metrics: dict[str, float]) -> dict[str, Any]:
    """``report.json``'s record of one fold; a held-out run mostly outside the others' temperatures is named."""
    from gyronet.training.dataset import block_rmse
    from gyronet.training.steps import predict

    time_s, x, y = fold.val_full
    residual = y - predict(fold_model, x)
    low, high = fold.temp_range_c
    temp = run.temp_c
    inside, in_box_s = inside_box(run.time_s, temp, (low, high))
    if in_box_s < MIN_IN_BOX_S and inside.mean() < 0.5:  # a short run wholly inside (bursts) is no extrapolation
        log.warning("run %s spends %.0f min inside the other runs' temperatures (%.1f to %.1f degC): its fold "
                    "measures extrapolation, and the capacity, step count and error bar taken from the folds "
                    "follow it; give every run the campaign's range, or train on the run that covers it "
                    "(data.path)", run.name, in_box_s / 60.0, low, high)
    log.info("fold %s held out: 60 s RMSE %s deg/s", run.name,
             ", ".join(f"{a}={metrics[f'val/rmse_{a}_dps']:.4g}" for a in AXES))
    return {"held_out": run.name, "path": run.path, "in_box_s": in_box_s,
            "train_runs": [r.name for r in fold.train_runs],
            **{k: v for k, v in metrics.items() if k.startswith(("val/", "train/"))},
            # the held-out run's own constant removed: what a perfect start-up offset would leave
            "val/rmse_demeaned_dps": block_rmse(time_s, residual - residual.mean(0)).tolist(),
            "out_of_range_fraction": float(np.mean((temp < low) | (temp > high)))}


__all__ = ["Run", "RunBlocks", "RunOffsets", "RunsData", "fit_by_run", "load_runs", "run_name",
           "training_data"]
