"""``diagnose.py`` on several runs: run-level effects first, then what the runs share within them.

1. The baseline is trained by leave-one-run-out on the declared inputs, **without** per-run
   offsets: a per-run offset (``run_offset``) must earn its place like any other effect.
2. Run-level candidates (:mod:`.runlevel`: ``run_offset`` and every column constant within a run
   that changes between runs, such as an orientation's ``acc_z_g``) are scored on held-out spans
   within every run and tested against random deals of the runs' contiguous pieces to the runs
   (never a shift across a joint). Those whose per-run values span the same constants, given the runs'
   design (two runs: every run-level candidate is the same single contrast), are equivalent;
   the simplest is kept (a per-run offset before an orientation column), the others are its
   ``alternatives``. A run-level effect is confirmed by its held-out score within the runs
   (leave-one-run-out cannot: a held-out run's constant is unknowable from the others).
3. Within-run candidates (the single record's: lags, columns, warm-up, ...) are screened against
   circular shifts within each run, on top of the model and one constant per run, and
   confirmed by retraining by run: the held-out runs' residual, each with its own constant
   removed, must drop by ``confirm_gain``, and as it is must not grow.
Both screens are one family-wise test at ``alpha``: each deal of the runs' pieces is paired with a
within-run shift and the best score of either is the null. A run-level effect that passes is taken
first (the next round tests what is left). ``report.md`` ends with what the campaign's design
cannot show and the cheapest run that would show it (:mod:`.advice`).
"""
from __future__ import annotations

import logging
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np
import torch

from gyronet.atomic import write_json
from gyronet.recordings.data import AXES
from gyronet.analysis.diagnose.options import DiagnoseOptions
from gyronet.analysis.diagnose.advice import orientation_label, rate_tau_of, record_advice, runs_advice
from gyronet.analysis.diagnose.candidates import candidate_specs, describe, effect_kind, effect_params, effect_source
from gyronet.analysis.diagnose.candidates import source_columns
from gyronet.analysis.diagnose.choose import approximations, complexity, ranked
from gyronet.analysis.diagnose.report import approximation_sentence
from gyronet.analysis.diagnose.report_figures import write_runs_figures
from gyronet.analysis.diagnose.rows import ScreenRows
from gyronet.analysis.diagnose.runlevel import RunCandidate, run_candidates, screen_runs
from gyronet.analysis.diagnose.screen import screen
from gyronet.analysis.diagnose.runs_report import write_runs_report
from gyronet.bundle.io import save_bundle
from gyronet.model.features import feature_name
from gyronet.training.pipeline import _meta

log = logging.getLogger(__name__)


NOTE = ("several runs: trained and scored by leave-one-run-out (`runs`: the final network's folds); run-level "
        "effects (run_offset, orientation) screened against deals of the runs' pieces, within-run effects against "
        "shifts within each run")


@dataclass
class RunStage:
    """A network trained by leave-one-run-out, its data and its held-out figures."""

    model: torch.nn.Module
    data: Any  # gyronet.training.runs.RunsData
    metrics: dict
    folds: list

    def val_rmse(self) -> dict[str, float]:
        return {a: float(self.metrics[f"val/rmse_{a}_dps"]) for a in AXES}

    def demeaned(self) -> np.ndarray:
        """(3,) held-out residual of the folds, each held-out run's own constant removed (mean over folds)."""
        return np.mean([f["val/rmse_demeaned_dps"] for f in self.folds], axis=0)

    def harmless_over(self, before: "RunStage") -> bool:
        """True when the held-out runs' residual as it is (no constant removed) is no worse than
        ``before``'s: an input whose level differs between runs can help the demeaned residual
        while adding an offset that a deployment without a start-up window would keep."""
        old, new = (np.array(list(s.val_rmse().values())) for s in (before, self))
        return bool((new**2).sum() <= (old**2).sum())

    def gain_over(self, before: "RunStage") -> float:
        old, new = before.demeaned(), self.demeaned()
        return float(np.clip(1.0 - new**2 / np.maximum(old**2, 1e-300), 0.0, None).sum())


def _same_design(a: RunCandidate, b: RunCandidate) -> bool:
    """True when two run-level candidates span the same per-run constants (with the mean level)."""
    ones = np.ones((len(a.per_run), 1))
    rank = [np.linalg.matrix_rank(np.column_stack(m), tol=1e-9) for m in
            ((ones, a.per_run), (ones, b.per_run), (ones, a.per_run, b.per_run))]
    return rank[0] == rank[1] == rank[2]


def _run_columns(rows: ScreenRows, columns: Sequence[str], n_runs: int) -> tuple[dict, dict]:
    values = rows.features([{"kind": "column", "source": c, "tau_s": 0.0} for c in columns])
    means = {c: np.array([values[rows.recording == r, j].mean() for r in range(n_runs)]) for j, c in enumerate(columns)}
    spread = {c: np.array([values[rows.recording == r, j].std() for r in range(n_runs)]) for j, c in enumerate(columns)}
    return means, spread


def _orientations(recordings: Sequence[Any]) -> list[str | None]:
    names = ("acc_x_g", "acc_y_g", "acc_z_g")
    return [orientation_label(np.array([rec.columns[n].mean() for n in names]))
            if all(n in rec.columns for n in names) else None for rec in recordings]


def _joint_null(runs: Any, within: Any, rng: np.random.Generator) -> None:
    """One family-wise test over both screens: pair the deals of the runs' pieces with the within-run
    shifts, take the best score of either at each pair, and recompute every p-value against it."""
    n = min(len(runs.null_max), len(within.null_max))
    joint = np.maximum(rng.permutation(runs.null_max)[:n], rng.permutation(within.null_max)[:n])
    runs.null_max = within.null_max = joint
    runs.p_value = (1 + (joint[None, :] >= runs.score[:, None]).sum(1)) / (1 + n)
    within.p_value = (1 + (joint[None, :] >= within.score[:, None]).sum(1)) / (1 + n)


def diagnose_runs(paths: Sequence[str], data_options: Mapping[str, Any], make_model: Callable[[int], torch.nn.Module],
                  out_dir: str | Path, optim: Callable | None = None, train_cfg: Mapping[str, Any] | None = None,
                  seed: int = 0, options: Any = None, plots: bool = True) -> dict[str, Any]:
    """Diagnose a campaign; write ``diagnosis.json``, ``report.md`` (with PNG figures when ``plots``) and the
    baseline and final bundles."""
    from gyronet.training.runs import fit_by_run, training_data

    options = options if isinstance(options, DiagnoseOptions) else DiagnoseOptions(**dict(options or {}))
    out_dir = Path(out_dir)
    base = {k: v for k, v in data_options.items()
            if k not in ("n_blocks", "val_fraction", "val_fold", "val_path") and not (k == "path" and v is None)}

    def train(features: Sequence[Mapping[str, Any]] | None, offsets: bool) -> RunStage:
        data = training_data(paths=list(paths), **{**base, "run_offsets": offsets,
                                                   **({"features": [dict(f) for f in features]} if features else {})})
        model = make_model(data.n_features)
        metrics, folds = fit_by_run(model, data, optim, seed=seed, **dict(train_cfg or {}))
        return RunStage(model, data, metrics, folds)

    stage = train(base.get("features"), False)
    stages = [stage]
    save_bundle(stage.model, _meta(stage.model, stage.data), out_dir / "baseline" / "compensator")
    recordings = [run.recording for run in stage.data.runs]
    n_runs = len(recordings)
    rows = ScreenRows.build_runs(recordings, stage.data.fs_hz, options.block_s, options.span_s, options.n_folds,
                                 base.get("static_rate_dps"))
    common = [c for c in source_columns(recordings[0]) if all(c in r.columns for r in recordings[1:])]
    means, spread = _run_columns(rows, common, n_runs)
    run_pool = run_candidates(means, spread, n_runs)
    shortest = min(recordings, key=lambda r: np.ptp(r.time_s))
    longest_s = options.candidates.max_tau_fraction * float(np.ptp(shortest.time_s))
    pool = candidate_specs(shortest, options.candidates, exclude=stage.data.features, columns=common)
    values = rows.features(pool)
    dummies = np.eye(n_runs)[rows.recording][:, 1:]
    effects, rounds, offsets, alpha = [], [], False, options.alpha
    while len(effects) < options.max_effects:
        basis, free = rows.basis(stage.model, stage.data.features)
        round_: dict[str, Any] = {"tried": []}
        rounds.append(round_)
        kept = None
        within = np.column_stack([basis, dummies])
        free_w = np.concatenate([free, np.ones(dummies.shape[1], bool)])
        result = screen(within, rows.target, values, rows.fold, rows.recording, [feature_name(s) for s in pool],
                        pool, options.n_shifts, options.seed + len(rounds), options.ridge, free_w,
                        max(1, int(round(options.span_s / options.block_s))))
        if run_pool:
            rs = screen_runs(basis, free, rows.target, rows.fold, rows.recording, rows.position, run_pool,
                             options.n_shifts, options.seed + len(rounds), options.ridge)
            _joint_null(rs, result, np.random.default_rng(options.seed + len(rounds)))
            round_.update(run_level=rs.table(), run_null_quantile=float(np.quantile(rs.null_max, 1 - alpha)),
                          run_n_shifts=len(rs.null_max))
            passing = list(rs.passing(alpha, options.min_gain))
            if passing:
                group = [j for j in passing if _same_design(run_pool[passing[0]], run_pool[j])
                         or rs.score[passing[0]] - rs.score[j] <= 1e-9]
                best = min(group, key=lambda j: complexity(run_pool[j].spec))
                cand = run_pool[best]
                confirmed = float(rs.score[best])
                round_["tried"].append({"spec": cand.spec, "score": confirmed, "confirm": confirmed})
                if confirmed >= options.confirm_gain:
                    offsets = offsets or cand.spec["kind"] == "run_offset"
                    extra = [] if cand.spec["kind"] == "run_offset" else [cand.spec]
                    trained = train([*stage.data.features, *extra], offsets)
                    axes = [a for i, a in enumerate(AXES) if rs.gain[best, i] >= 0.05] or [AXES[int(np.argmax(rs.gain[best]))]]
                    sentence = (f"Adding {'one constant per run' if not extra else describe(cand.spec) + ' (constant within each run)'} "
                                f"cut the held-out 60 s residual ({options.n_folds}-fold cross-validation over spans "
                                f"within each of the {n_runs} runs, {len(rows)} blocks) from "
                                + ", ".join(f"{a} {rs.rmse_before[AXES.index(a)]:.3g}" for a in axes) + " to "
                                + ", ".join(f"{a} {rs.rmse_after[best, AXES.index(a)]:.3g}" for a in axes)
                                + f" deg/s, score {confirmed:.3g} >= {options.confirm_gain:g}; the best run-level "
                                f"candidate did as well in {int((rs.null_max >= rs.score[best]).sum())} of "
                                f"{len(rs.null_max)} random deals of the runs' pieces, each with a shift within the runs (p = "
                                f"{rs.p_value[best]:.3g}"
                                f" <= {alpha:g}).")
                    kept = ({"kind": "run_offset" if not extra else "column", "source": cand.spec["source"],
                             "params": {k: v for k, v in cand.spec.items() if k not in ("kind", "source")},
                             "axes": axes, "evidence": sentence,
                             "alternatives": [{"kind": "run_offset" if run_pool[j].spec["kind"] == "run_offset"
                                               else "column", "source": run_pool[j].spec["source"],
                                               "params": {k: v for k, v in run_pool[j].spec.items()
                                                          if k not in ("kind", "source")},
                                               "score": float(rs.score[j])} for j in group if j != best]}, trained)
                    run_pool = []  # the runs' constants are taken: nothing run-level is left to test
        if kept is None:
            round_.update(candidates=result.table()[:15], n_shifts=len(result.null_max),
                          null_max_quantile=float(np.quantile(result.null_max, 1 - alpha)))
            passing = result.passing(alpha, options.min_gain)
            for choice in (ranked(result, passing, rows, (within, free_w), options.refine_top, longest_s, options.tie_z)
                           if len(passing) else []):
                trained = train([*stage.data.features, choice.spec], offsets)
                confirmed = trained.gain_over(stage)
                harmless = trained.harmless_over(stage)
                round_["tried"].append({"spec": choice.spec, "score": choice.score, "confirm": confirmed,
                                        "harmless": harmless})
                if confirmed >= options.confirm_gain and harmless:
                    axes = result.axes(choice.index, alpha)
                    kept = ({"kind": effect_kind(choice.spec), "source": effect_source(choice.spec),
                             "params": effect_params(choice.spec), "axes": axes,
                             "evidence": (f"Adding {describe(choice.spec)} scored {choice.score:.3g} on held-out spans "
                                          f"within the runs (family-wise p = {result.p_value[choice.index]:.3g} <= "
                                          f"{alpha:g}, circular shifts within each run); retrained by run, the "
                                          f"held-out runs' residual (own constant removed) confirms it (score "
                                          f"{confirmed:.3g} >= {options.confirm_gain:g}).")
                             + approximation_sentence(choice.spec, choice.score,
                                                      approximations(choice, result, passing, rows, (within, free_w))),
                             "alternatives": choice.alternatives}, trained)
                    drop = feature_name(choice.spec)
                    keep = [i for i, s in enumerate(pool) if feature_name(s) != drop]
                    pool, values = [pool[i] for i in keep], values[:, keep]
                    break
        if kept is None:
            break
        effect, trained = kept
        effects.append({"kind": effect["kind"], "source": effect["source"], "params": effect["params"],
                        "axes": effect["axes"], "val_rmse_before_dps": stage.val_rmse(),
                        "val_rmse_after_dps": trained.val_rmse(), "evidence": effect["evidence"],
                        "alternatives": effect["alternatives"]})
        log.info("effect %d: %s", len(effects), effect["evidence"])
        stage = trained
        stages.append(stage)

    save_bundle(stage.model, _meta(stage.model, stage.data), out_dir / "compensator")
    diagnosis = {"baseline": {"inputs": stages[0].data.feature_names, "val_rmse_dps": stages[0].val_rmse()},
                 "effects": effects,
                 "final": {"inputs": stage.data.feature_names, "val_rmse_dps": stage.val_rmse()},
                 "runs": stage.folds, "note": NOTE}
    out_dir.mkdir(parents=True, exist_ok=True)
    write_json(out_dir / "diagnosis.json", diagnosis)
    orientations = _orientations(recordings)
    advice = runs_advice(orientations)
    union_c = (min(float(r.temp_c.min()) for r in recordings), max(float(r.temp_c.max()) for r in recordings))
    rate_tau_s = rate_tau_of(stage.data.features)  # the tracker the model uses (2.5 s by default), not 5 s
    per_run = [{(a.cost, a.record): a for a in record_advice(r.time_s, r.temp_c, r.fs_hz, common, rate_tau_s,
                                                             range_c=union_c)} for r in recordings]
    advice += [a for key, a in per_run[0].items() if all(key in other for other in per_run[1:])]
    details = {"options": asdict(options), "runs": [{"name": r.name, "orientation": o} for r, o in
                                                    zip(stage.data.runs, orientations)],
               "rounds": rounds, "stages": [{"inputs": s.data.feature_names, "run_offsets": s.data.run_offsets,
                                             "metrics": s.metrics, "folds": s.folds} for s in stages],
               "next": [a.to_dict() for a in advice]}
    write_json(out_dir / "diagnosis_details.json", details)
    figures = write_runs_figures(out_dir, rows, stages, [r.name for r in stage.data.runs]) if plots else []
    write_runs_report(out_dir, diagnosis, details, orientations, advice, figures)
    return diagnosis


__all__ = ["diagnose_runs"]
