"""Close the loop: train on the declared inputs, find what the residual still follows, add it, repeat.

1. Train the baseline network on the declared inputs (``data.features``) and save it.
2. Build every candidate effect the recording allows (:mod:`.candidates`) and its 60 s block means.
3. Screen them against the current network's held-out residual (:mod:`.screen`): held-out gain,
   family-wise permutation test over circular time shifts, a minimum gain.
4. For the best families that passed (:mod:`.choose`), best first: refine the parameter, add the
   feature, retrain the network, refine again with the retrained network, and **confirm**: the
   retrained network's own held-out residual must drop by at least ``confirm_gain``. The first
   that confirms is kept and the loop goes back to 3; if none does, it stops.
   The network's held-out residual is cross-validated over the same interleaving of ``span_s``
   spans as the screen's folds (cut from the samples' times, so within a block of the screen's
   own): one network per set of spans, each scored on the set it did not see, pooled. One
   held-out set alone would miss effects that live in one part of the record, like a warm-up
   in the first half hour. Each network early-stops on the spans it is scored on, as
   ``train.py`` does, which flatters before and after alike.
5. Save the final network as a bundle whose ``meta.json`` lists the extra feature specs, so the
   deployed compensator computes them through the same causal code, offline and live.

Two gates, because they catch different mistakes. The screen's permutation test rejects chance.
It cannot reject a real but unimportant association: on a long record the baseline's own small
imperfections (its dT/dt path at ramp corners, its first minutes) correlate with some candidate
well beyond chance. Those do not survive the retraining: a network given the candidate does no
better on held-out data, while one given a missing effect does much better.

The numbers in ``diagnosis.json`` are the networks' 60 s residual on held-out data: pooled over
the cross-validation folds, or on the separate ``val_path`` recording. ``baseline``, then each
effect's before and after, then ``final``. The screen's own cross-validated numbers are in each
effect's ``evidence``. The bundles are the networks trained on the default fold (one set of
spans held out for early stopping). ``diagnose()`` also writes ``diagnosis_details.json`` (every
round's candidates, every stage's metrics) and the report's PNG figures.
"""
from __future__ import annotations

import logging
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np
import torch

from gyronet.atomic import write_json
from gyronet.recordings.data import AXES
from gyronet.training.dataset import load_cached
from gyronet.errors import GyronetError
from gyronet.analysis.diagnose.candidates import (candidate_specs, effect_kind, effect_params,
                                         effect_source, source_columns)
from gyronet.analysis.diagnose.options import DiagnoseOptions, check_feature_specs
from gyronet.analysis.diagnose.choose import Choice, approximations, ranked, refine, score_specs
from gyronet.analysis.diagnose.report import approximation_sentence, evidence, write_report
from gyronet.analysis.diagnose.rows import ScreenRows
from gyronet.analysis.diagnose.screen import screen
from gyronet.analysis.diagnose.stages import Stage, Trainer
from gyronet.bundle.io import save_bundle
from gyronet.model.features import feature_name
from gyronet.training.pipeline import _meta

log = logging.getLogger(__name__)


def _attempt(choice: Choice, stage: Stage, train: Trainer, rows: ScreenRows, basis: tuple, ridge: float,
             options: DiagnoseOptions, longest_s: float) -> tuple[Choice, Stage]:
    """Retrain with the effect; refine its parameter again with the retrained network."""
    inputs = stage.data.features
    trained = train([*inputs, choice.spec])
    for _ in range(options.refine_passes):
        # the frozen basis had absorbed part of the effect, which biases its parameter: look
        # again with the retrained network, leaving out the new feature's own regressor
        rebasis = rows.basis(trained.model, trained.data.features, without=len(inputs))
        better = None if rebasis is None else refine(choice.spec, rows, rebasis, options.ridge, longest_s)
        if better is None or feature_name(better.spec) == feature_name(choice.spec):
            break
        log.info("refined %s to %s", feature_name(choice.spec), feature_name(better.spec))
        gain, score, rmse_after = score_specs(rows, basis, [better.spec], ridge)
        choice = Choice(better.spec, choice.index, gain[0], float(score[0]), rmse_after[0], choice.alternatives)
        trained = train([*inputs, choice.spec])
    return choice, trained


def diagnose(data_options: Mapping[str, Any], make_model: Callable[[int], torch.nn.Module], out_dir: str | Path,
             optim: Callable | None = None, train_cfg: Mapping[str, Any] | None = None,
             options: DiagnoseOptions | Mapping[str, Any] | None = None, seed: int = 0,
             plots: bool = True) -> dict[str, Any]:
    """Run the whole diagnosis; write ``out_dir/diagnosis.json``, both bundles and ``report.md``.

    Parameters
    ----------
    data_options
        ``DriftData`` arguments (``path``, ``features`` = the declared inputs, ``val_path``, ...).
    make_model
        ``make_model(n_inputs)`` returns an untrained model (e.g. the default ``RBFNet``).
    out_dir
        Where to write.
    optim, train_cfg, seed
        Passed to ``gyronet.training.train.fit``.
    options
        ``DiagnoseOptions`` or a mapping of its fields.
    plots
        Write the PNG figures of the report.

    Returns
    -------
    dict
        The content of ``diagnosis.json`` (CONTRACT.md section 4).
    """
    started = time.monotonic()
    out_dir = Path(out_dir)
    # data.paths: several runs (gyronet.analysis.diagnose.runs); one in a list is the one-record case
    paths = list(data_options.get("paths") or [])
    runs_options = {k: data_options[k] for k in ("run_offsets", "val_startup_s") if k in data_options}
    data_options = {k: v for k, v in data_options.items() if k not in ("paths", "run_offsets", "val_startup_s")}
    if not isinstance(options, DiagnoseOptions):
        options = DiagnoseOptions(**dict(options or {}))
    if len(paths) > 1 or (paths and data_options.get("path")):
        from gyronet.analysis.diagnose.runs import diagnose_runs

        return diagnose_runs(paths, {**data_options, **runs_options}, make_model, out_dir, optim, train_cfg, seed,
                             options, plots)
    if paths:
        data_options["path"] = paths[0]
    if not data_options.get("path"):
        raise GyronetError("no training data: give data.path=F.csv or data.paths=[A.csv,B.csv]")
    if "features" in data_options:
        check_feature_specs(data_options["features"], "data.features")
        if not data_options["features"]:
            raise GyronetError("data.features is empty: declare at least one input, e.g. [{kind: temp}]")
    for name in ("block_s", "rate_tau_s"):
        value = data_options.get(name)
        if value is not None and not value > 0:
            raise GyronetError(f"data.{name} must be positive, got {value}")
    if 1 / (options.n_shifts + 1) > options.alpha:
        log.warning("n_shifts=%d cannot give a p-value below alpha=%g: nothing can pass",
                    options.n_shifts, options.alpha)
    # loaded once per process: the networks' DriftData reuse it
    recordings, columns, untried = [load_cached(data_options["path"])], None, []
    span_s = float(recordings[0].time_s[-1] - recordings[0].time_s[0])
    n_spans = max(2 * options.n_folds, int(round(span_s / options.span_s)))
    # the networks are validated on the screen's folds (not data.n_blocks): interleaved spans of
    # span_s, one in n_folds held out, so every fold's training sees every dwell of the history
    data_options = {**data_options, "n_blocks": n_spans, "val_fraction": 1.0 / options.n_folds}
    train = Trainer(data_options, make_model, optim, dict(train_cfg or {}), seed, options.block_s)
    stage = train.cross_validate(train())
    stages = [stage]
    save_bundle(stage.model, _meta(stage.model, stage.data), out_dir / "baseline" / "compensator")

    if data_options.get("val_path"):
        recordings.append(load_cached(data_options["val_path"]))
        in_both = set(source_columns(recordings[1]))
        columns = [c for c in source_columns(recordings[0]) if c in in_both]
        untried = [c for c in source_columns(recordings[0]) if c not in in_both]
        if untried:
            log.warning("%s lacks (or holds constant) column(s) %s of the training record: no candidate reads them",
                        data_options["val_path"], ", ".join(untried))
    longest_s = options.candidates.max_tau_fraction * span_s
    rows = ScreenRows.build(recordings, stage.data.fs_hz, options.block_s, n_spans, options.n_folds,
                            data_options.get("static_rate_dps"))
    n_all = len(rows)
    if "temp_c" in stage.data.feature_names:
        trained_c = stage.data.train.x[:, stage.data.feature_names.index("temp_c")]
        rows = rows.within((float(trained_c.min()), float(trained_c.max())))
        if len(rows) < n_all:
            log.info("%d of %d blocks lie outside the training temperature range: not screened",
                     n_all - len(rows), n_all)
    pool = candidate_specs(recordings[0], options.candidates, exclude=stage.data.features, columns=columns)
    values = rows.features(pool)
    log.info("%d candidate effects, %d blocks of %g s", len(pool), len(rows), options.block_s)

    effects, rounds = [], []
    while len(effects) < options.max_effects and pool:
        basis = rows.basis(stage.model, stage.data.features)
        result = screen(basis[0], rows.target, values, rows.fold, rows.recording, [feature_name(s) for s in pool],
                        pool, options.n_shifts, options.seed + len(rounds), options.ridge, basis[1],
                        max(1, int(round(options.span_s / options.block_s))))
        passing = result.passing(options.alpha, options.min_gain)
        round_ = {"n_candidates": len(pool), "n_shifts": len(result.null_max), "ridge": result.ridge,
                  "null_max_quantile": float(np.quantile(result.null_max, 1 - options.alpha)) if len(result.null_max)
                  else None,
                  "rmse_before_dps": dict(zip(AXES, result.rmse_before.tolist())),
                  "candidates": result.table()[:15], "tried": []}
        rounds.append(round_)
        log.info("round %d: best %s score %.3g p %.3g; %d pass", len(rounds), round_["candidates"][0]["name"],
                 round_["candidates"][0]["score"], round_["candidates"][0]["p_value"], len(passing))
        kept = None
        for choice in (ranked(result, passing, rows, basis, options.refine_top, longest_s, options.tie_z)
                       if len(passing) else []):
            choice, trained = _attempt(choice, stage, train, rows, basis, result.ridge, options, longest_s)
            confirmed = train.cross_validate(trained).gain_over(stage)
            round_["tried"].append({"spec": choice.spec, "score": choice.score, "confirm": confirmed})
            log.info("%s: screen score %.3g, retrained held-out score %.3g (%s)", feature_name(choice.spec),
                     choice.score, confirmed, "kept" if confirmed >= options.confirm_gain else "not confirmed")
            if confirmed >= options.confirm_gain:
                kept = (choice, trained, confirmed)
                break
        if kept is None:
            break
        choice, trained, confirmed = kept
        axes = result.axes(choice.index, options.alpha)
        effects.append({
            "kind": effect_kind(choice.spec), "source": effect_source(choice.spec),
            "params": effect_params(choice.spec), "axes": axes,
            "val_rmse_before_dps": stage.val_rmse(), "val_rmse_after_dps": trained.val_rmse(),
            "evidence": evidence(choice.spec, choice.score, choice.rmse_after, choice.index, result, axes,
                                 options.alpha, options.min_gain, confirmed, options.confirm_gain)
            + approximation_sentence(choice.spec, choice.score,
                                     approximations(choice, result, passing, rows, basis)),
            "alternatives": choice.alternatives,
        })
        log.info("effect %d: %s", len(effects), effects[-1]["evidence"])
        stage = trained
        stages.append(stage)
        drop = {feature_name(choice.spec), result.names[choice.index]}
        keep = [i for i, s in enumerate(pool) if feature_name(s) not in drop]
        pool, values = [pool[i] for i in keep], values[:, keep]

    save_bundle(stage.model, _meta(stage.model, stage.data), out_dir / "compensator")
    diagnosis = {
        "baseline": {"inputs": stages[0].data.feature_names, "val_rmse_dps": stages[0].val_rmse()},
        "effects": effects,
        "final": {"inputs": stage.data.feature_names, "val_rmse_dps": stage.val_rmse()},
    }
    out_dir.mkdir(parents=True, exist_ok=True)
    write_json(out_dir / "diagnosis.json", diagnosis)
    details = {"options": asdict(options), "n_blocks": len(rows), "n_blocks_outside": n_all - len(rows),
               "untried_columns": untried,  # in the training record, not (or constant) in data.val_path
               "rounds": rounds, "stages": [{"inputs": s.data.feature_names, "features": s.data.features,
                                             "metrics": s.metrics, "held_out_dps": s.held_out}
                                            for s in stages]}
    write_report(out_dir, diagnosis, details, rows, stages, plots=plots)
    details["runtime_s"] = time.monotonic() - started
    write_json(out_dir / "diagnosis_details.json", details)
    log.info("diagnosis done in %.1f s: %d effect(s)", details["runtime_s"], len(effects))
    return diagnosis
