"""One training run end to end: fit, bundle, evaluate on held-out recordings, log, report.

``scripts/train.py`` and ``scripts/diagnose.py`` call ``train_run`` with plain Python objects, so
the same run works from a test or a notebook without Hydra.
"""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np
import torch

from gyronet.atomic import write_json
from gyronet.bundle.compensator import RATE_TOLERANCE, Compensator, build_meta
from gyronet.bundle.io import save_bundle
from gyronet.errors import GyronetError
from gyronet.recordings.data import AXES, Recording, load_recording, load_truth, truth_path
from gyronet.training import coverage
from gyronet.training.dataset import DriftData, block_rmse, static_rate_dps
from gyronet.training.run_data import run_name
from gyronet.training.train import evaluate, fit

log = logging.getLogger(__name__)

# how far to trust an error bar calibrated within one recording (the survey filters exactly this warning)
ONE_RECORDING_BAR_NOTE = ("error bar: calibrated on %s; on a real sensor's "
                          "next run the error was 3-15x the bar (docs/results/error-bars.md). Train on two or more "
                          "runs (data.paths) for a bar checked on a run it was not calibrated on")
# what one training of the default on one recording is worth: how far the shipped mixture (not the fits it mixes)
# moved with the seed on another history, docs/results/default-model.md
SEED_NOTE = ("; the bundle is their mixture, whose residual on another history moved with the seed by at most 5 % "
             "on 46 of 48 simulated sensors (5.6 % at most), by 9-10 % on 3 of 10 picked for a sharp bend where they "
             "power up (docs/results/default-model.md)")


def model_info(model: torch.nn.Module) -> dict[str, Any]:
    """Class and constructor settings of a model, for ``meta.json`` and hparams."""
    info: dict[str, Any] = {"class": type(model).__name__}
    for key in ("n_centers", "width_init", "rbf_inputs", "use_linear", "temp_degree", "clamp", "degree", "lag_by_axis_s",
                "rate_lag_only_by_axis"):
        if hasattr(model, key):
            info[key] = getattr(model, key)
    info["n_parameters"] = int(sum(p.numel() for p in model.parameters()) + sum(
        b.numel() for n, b in model.named_buffers() if n in ("coef", "weight")))
    return info


def kalman_stage(kalman_cfg: Mapping[str, Any] | None, model: torch.nn.Module, data: DriftData) -> dict | None:
    """Identify the Kalman stage from the network's residual on the training record, if enabled."""
    if not kalman_cfg or not kalman_cfg.get("enabled", False):
        return None
    from gyronet.model.kalman import KalmanStage, identify

    options = {k: v for k, v in kalman_cfg.items() if k != "enabled"}
    recording = data.recording
    _refuse_rate_changes(recording, data.fs_hz)
    compensator = Compensator(model, _meta(model, data))
    residual = recording.gyro_dps - compensator.drift(recording.columns)
    # a rejected row (gyronet.recordings.guard) is a lost sample: the noise model is identified without it
    residual = residual[~compensator.extractor.rejected]
    return KalmanStage(identify(residual, data.fs_hz), **options).to_dict()


def _refuse_rate_changes(recording: Any, fs_hz: float) -> None:
    """The Kalman stage is identified per sample at one rate: a rate change in the record is one line."""
    from gyronet.recordings.rate_watch import first_rate_change

    change = first_rate_change(recording.time_s, fs_hz)
    if change is not None:
        raise GyronetError(f"{recording.path}: near {recording.line_of(change.since_row)} (time_s="
                           f"{change.since_time_s:.6g}): the sampling rate changes from {change.old_hz:.4g} Hz to "
                           f"{change.new_hz:.4g} Hz, and the Kalman stage is identified per sample at one rate; "
                           "train with kalman=disabled, or split the file there")


def _meta(model: torch.nn.Module, data: DriftData) -> dict[str, Any]:
    from gyronet.bundle.schema import gyro_source_of
    from gyronet.model.features import required_columns
    from gyronet.recordings.data import GYRO_COLUMNS

    inputs = list(dict.fromkeys([*required_columns(data.features), *GYRO_COLUMNS]))
    meta = build_meta(data.features, data.feature_names, data.fs_hz, data.temp_range_c, inputs,
                      data.recording.checksum(), model_info(model))
    meta.update(getattr(data, "bundle_meta", dict)())  # several runs (gyronet.training.runs): each run, its checksum
    runs = getattr(data, "runs", None) or []
    source = gyro_source_of([r.recording.meta for r in runs] or [data.recording.meta])
    if source is not None:  # issue 13: raw (LP-BUS) or host-corrected (an LPMS-Control log) gyro
        meta["gyro_source"] = source
    from gyronet.training.error_bar_fit import error_bar_meta

    bar = error_bar_meta(model, data)
    if bar is not None:
        meta["error_bar"] = bar
    return meta


def load_held_out(paths: Sequence[str], fs_hz: float | None = None) -> dict[str, tuple[Recording, dict | None]]:
    """Each held-out recording with its ground truth when it has one: read before training, so that a missing or
    malformed file, or one at another rate than the training data's ``fs_hz``, is one line at once, not after the
    fit."""
    held_out = {}
    names = [run_name(str(p)) for p in paths]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:  # their figures and plots are filed under the name: one would replace the other
        raise GyronetError(f"eval.paths: two held-out recordings are named {twice[0]!r}; give each its own file name")
    for path in paths:
        recording = load_recording(path)
        if fs_hz is not None and abs(recording.fs_hz / fs_hz - 1.0) > RATE_TOLERANCE:
            raise GyronetError(f"eval.paths: {path} is sampled at {recording.fs_hz:g} Hz, the training data at "
                               f"{fs_hz:g} Hz; a held-out recording must have the training rate (after training, "
                               "compensate.py resample=true can run the bundle at another)")
        held_out[str(path)] = (recording, load_truth(path).columns if truth_path(path).is_file() else None)
    return held_out


def evaluate_paths(bundle_dir: Path, held_out: Mapping[str, tuple[Recording, dict | None]],
                   block_s: float) -> dict[str, dict]:
    """Evaluate a saved bundle on each held-out recording (:func:`load_held_out`'s, by path).

    Each result also holds ``residual_rms_dps``: the ``block_s`` block RMS of the compensated rate
    minus the recording's static rate, per axis (the figure there is without a truth). Each
    recording's share outside the trained temperature range and its figures are logged, so that
    they reach the console and not only ``report.json``.
    """
    results = {}
    for path, (recording, truth) in held_out.items():
        compensator = Compensator.load(bundle_dir)
        compensator.rate_source, compensator.row_name = str(path), recording.line_of  # a message names the file
        result = evaluate(compensator, recording, truth, block_s)
        arrays = result["_arrays"]
        residual = block_rmse(arrays["time_s"], arrays["compensated_dps"] - static_rate_dps(recording), block_s)
        result["residual_rms_dps"] = dict(zip(AXES, residual.tolist()))
        _log_held_out(Path(path).name, result, compensator.temp_range_c, block_s)
        results[str(path)] = result
    return results


def _log_held_out(name: str, result: Mapping[str, Any], temp_range_c: Sequence[float], block_s: float) -> None:
    """Out-of-range share (a warning when any) and the held-out figures, one line each."""
    low, high = temp_range_c
    n_out, n = result["n_out_of_range"], result["n_samples"]
    if n_out:
        log.warning("held-out %s: %d of %d samples (%.1f %%) outside the trained temperature range "
                    "[%.2f, %.2f] degC; the model holds its edge value there, and the figures below include "
                    "them", name, n_out, n, 100.0 * n_out / max(n, 1), low, high)
    else:
        log.info("held-out %s: all %d samples inside the trained temperature range [%.2f, %.2f] degC",
                 name, n, low, high)

    def per_axis(values: Mapping[str, float]) -> str:
        return ", ".join(f"{a}={values[a]:.4g}" for a in AXES)

    allan = {stage: result["allan"][stage] for stage in ("raw", "compensated")}
    nb = "; ".join(f"{stage} N {per_axis({a: allan[stage][a]['arw_deg_rthr'] for a in AXES})} deg/sqrt(h), B "
                   + ", ".join(f"{a}={'<=' if allan[stage][a].get('bias_instability_upper_bound') else ''}"
                               f"{allan[stage][a]['bias_instability_deg_hr']:.4g}" for a in AXES) + " deg/h"
                   for stage in ("compensated", "raw"))
    if "truth" in result:
        log.info("held-out %s: residual / noise floor %s (residual %s deg/s, %g s blocks, against the truth); %s",
                 name, per_axis(result["truth"]["ratio_to_floor"]), per_axis(result["truth"]["residual_dps"]),
                 block_s, nb)
    else:
        log.info("held-out %s: %g s residual RMS %s deg/s (no truth: compensated minus the static rate); %s",
                 name, block_s, per_axis(result["residual_rms_dps"]), nb)


def train_run(data: DriftData, model: torch.nn.Module, optim: Callable | None, out_dir: str | Path,
              train_cfg: Mapping[str, Any], seed: int = 0, kalman_cfg: Mapping[str, Any] | None = None,
              eval_paths: Sequence[str] = (), eval_block_s: float = 60.0, writer: Any = None,
              hparams: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """Fit ``model`` on ``data``, write ``out_dir/compensator`` and ``out_dir/report.json``, log to ``writer``.

    Returns the final metrics; ``val/rmse_dps`` is what a sweep minimises.
    """
    out_dir = Path(out_dir)
    held_out = load_held_out(eval_paths, data.fs_hz)
    trained = ({r.recording.checksum() for r in getattr(data, "runs", None) or []} or {data.recording.checksum()}
               if held_out else set())  # hashed only when there is something to compare
    for path in (p for p, (recording, _) in held_out.items() if recording.checksum() in trained):
        log.warning("eval.paths: %s holds the training data: its figures below are in sample, not held out", path)
    folds = None
    if getattr(data, "n_runs", 1) > 1:  # several runs: leave-one-run-out, then the final fit on every run
        from gyronet.training.runs import fit_by_run

        metrics, folds = fit_by_run(model, data, optim, seed=seed, writer=writer, **train_cfg)
    else:
        metrics = fit(model, data, optim, seed=seed, writer=writer, **train_cfg)
    log.info("validation 60 s RMSE: %s deg/s", ", ".join(f"{a}={metrics[f'val/rmse_{a}_dps']:.4g}" for a in AXES))
    if "val/fits_tried" in metrics:  # gyronet.training.starts: how much the held-out figure moved over what was tried
        log.info("validation 60 s RMSE over the %d fits tried (starts and seeds): %s%s", int(metrics["val/fits_tried"]),
                 ", ".join(f"{a} {metrics[f'val/lowest_{a}_dps']:.4g}-{metrics[f'val/highest_{a}_dps']:.4g} deg/s "
                           f"({metrics[f'val/spread_{a}_pct']:.0f} %)" for a in AXES),
                 "" if folds else SEED_NOTE)
    metrics.update(coverage.thinnest(data))
    line = coverage.describe(metrics)
    if line:
        log.info(line)
    meta = _meta(model, data)
    if folds is None and "error_bar" in meta:
        log.warning(ONE_RECORDING_BAR_NOTE, f"the validation recording {data.val_path}" if getattr(data, "val_path", None)
                    else "held-out time blocks of this one recording")
    bundle_dir = save_bundle(model, meta, out_dir / "compensator", kalman_stage(kalman_cfg, model, data))
    evaluations = evaluate_paths(bundle_dir, held_out, eval_block_s)
    report = {"model": model_info(model), "train_path": data.path, "metrics": metrics,
              "eval": {p: {k: v for k, v in r.items() if k != "_arrays"} for p, r in evaluations.items()}}
    if folds is not None:
        report.update(train_paths=data.paths, folds=folds)
    for path, result in evaluations.items():
        metrics.update(_eval_metrics(result, prefix="eval" if len(evaluations) == 1 else f"eval_{run_name(path)}"))
    if writer is not None:
        _log_run(writer, metrics, evaluations, hparams or model_info(model))
    write_json(out_dir / "report.json", report, indent=1)  # strict JSON: a figure with no value is null
    return metrics


def _eval_metrics(result: Mapping[str, Any], prefix: str) -> dict[str, float]:
    metrics = {f"{prefix}/residual_rms_{axis}_dps": value for axis, value in result["residual_rms_dps"].items()}
    for stage in ("raw", "compensated", "noise_only"):
        for axis, values in ((a, result["allan"][stage][a]) for a in AXES if stage in result["allan"]):
            metrics[f"{prefix}/{stage}_arw_{axis}_deg_rthr"] = values["arw_deg_rthr"]
            metrics[f"{prefix}/{stage}_bias_instability_{axis}_deg_hr"] = values["bias_instability_deg_hr"]
            # 1: B is only a bound (the curve still falls at the last tau read)
            metrics[f"{prefix}/{stage}_bias_instability_bound_{axis}"] = float(values["bias_instability_upper_bound"])
    if "truth" in result:
        for axis in AXES:
            metrics[f"{prefix}/residual_{axis}_dps"] = result["truth"]["residual_dps"][axis]
            metrics[f"{prefix}/ratio_to_floor_{axis}"] = result["truth"]["ratio_to_floor"][axis]
    for key, values in result.get("error_bar", {}).items():  # eval/median_sigma_x_dps, eval/within_1_sigma_x
        if isinstance(values, dict):
            name = key.replace("_dps", "")
            metrics.update({f"{prefix}/{name}_{axis}{'_dps' if key.endswith('_dps') else ''}": v
                            for axis, v in values.items()})
    return metrics


def _log_run(writer: Any, metrics: Mapping[str, float], evaluations: Mapping[str, dict],
             hparams: Mapping[str, Any]) -> None:
    from gyronet.allan import plot_allan
    from gyronet.figures import plots, tb

    tb.log_scalars(writer, {k: v for k, v in metrics.items() if np.isfinite(v)})
    for path, result in evaluations.items():
        name = run_name(path)
        arrays = result["_arrays"]
        tb.log_figure(writer, f"eval/{name}/allan", plot_allan(
            {stage: result["allan"][stage] for stage in result["allan"]}, title=f"Allan deviation: {name}"))
        tb.log_figure(writer, f"eval/{name}/raw_vs_compensated", plots.raw_vs_compensated(arrays))
        tb.log_figure(writer, f"eval/{name}/residual_vs_temperature", plots.residual_vs_temperature(arrays))
        if "error_bar" in result:  # the sigma band: is the error bar honest on this record?
            tb.log_figure(writer, f"eval/{name}/drift_sigma", plots.drift_sigma_band(arrays))
    tb.log_hparams(writer, hparams, {k: v for k, v in metrics.items() if k.startswith(("val/", "eval")) and np.isfinite(v)})
    writer.flush()
