"""Training rows: the default model on the paper profile against the PX4 cubic, and the GA sweep."""
from __future__ import annotations

import json
import shutil
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from .harness import (ROOT, Context, bench, bundle_run_dir, log_matches, log_times, paper_recording, row,
                      run_command, train_command, train_overrides)

TRAIN_GOAL_S = 60.0
SWEEP_GOAL_S = 600.0
# what train.log says at the end of each stage of gyronet.training.pipeline.train_run
_STAGE_LINES = {"data": r"^training data ", "fit": r"^validation 60 s RMSE", "export": r"^bundle written"}


def _compose(overrides: list[str]):
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(str(ROOT / "conf"), version_base="1.3"):
        return compose("train", overrides=overrides)


def _fit_in_process(csv: Path, overrides: list[str]) -> dict[str, Any]:
    """DriftData (cold), the model from conf/ via compose + instantiate, then gyronet.training.train.fit, timed apart."""
    from hydra.utils import instantiate
    from omegaconf import OmegaConf

    from gyronet.training import dataset
    from gyronet.training.axis_lag import with_axis_lags
    from gyronet.training.train import fit

    dataset.clear_caches()  # a cold load, whatever ran before in this process
    cfg = _compose([f"data.path={csv}", *overrides])
    start = time.perf_counter()
    data = instantiate(cfg.data)
    model = instantiate(cfg.model, n_inputs=data.n_features)
    data, model = with_axis_lags(data, lambda n, columns: instantiate(cfg.model, n_inputs=n, axis_columns=columns),
                                 model)
    data_s = time.perf_counter() - start  # the lag screen's features included
    train_cfg = {**OmegaConf.to_container(cfg.train), "progress": False}
    start = time.perf_counter()
    metrics = fit(model, data, instantiate(cfg.optim), seed=cfg.seed, **train_cfg)
    return {"data_s": data_s, "fit_s": time.perf_counter() - start, "steps": metrics.get("train/steps"),
            "val_rmse_dps": metrics["val/rmse_dps"]}


def _command_stages(run_dir: Path, start_epoch: float, end_epoch: float) -> dict[str, float]:
    """Seconds from the command's start to data loaded, fit done, bundle written, and the end, from train.log."""
    marks = log_times(run_dir / "train.log", _STAGE_LINES)
    edges = [("start_to_data", start_epoch, marks.get("data")),
             ("data_to_fit", marks.get("data"), marks.get("fit")),
             ("fit_to_export", marks.get("fit"), marks.get("export")),
             ("export_to_end", marks.get("export"), end_epoch)]
    return {name: b - a for name, a, b in edges if a is not None and b is not None}


@bench("train_default_paper")
def train_default_paper(ctx: Context) -> dict[str, Any]:
    """scripts/train.py (default config) on the paper's 12.7 h 10 Hz profile against model=poly3; goal < 60 s."""
    import torch

    csv = paper_recording(ctx)
    commands, stages = {}, {}
    for model in ("default", "poly3"):
        run_dir = bundle_run_dir(ctx, model)
        shutil.rmtree(run_dir, ignore_errors=True)
        start_epoch = time.time()
        commands[model] = run_command(train_command(ctx, csv, run_dir, None if model == "default" else model), ctx)
        stages[model] = _command_stages(run_dir, start_epoch, time.time())
    threads = torch.get_num_threads()
    ours = _fit_in_process(csv, train_overrides(ctx))
    reference = _fit_in_process(csv, ["model=poly3", *train_overrides(ctx)])
    torch.set_num_threads(threads)  # fit() sets 1 for the rest of this process
    goal = "met" if commands["default"] < TRAIN_GOAL_S else "NOT met"
    startup = stages["default"].get("start_to_data", float("nan")) - ours["data_s"]
    notes = (f"{'quick: 1 Hz profile, max_epochs=100; ' if ctx.quick else ''}whole command {commands['default']:.1f} s "
             f"(goal < {TRAIN_GOAL_S:.0f} s: {goal}) vs poly3 command {commands['poly3']:.1f} s; in-process fit "
             f"{ours['fit_s']:.2f} s ({ours['steps']} steps) vs poly3 fit {reference['fit_s'] * 1e3:.1f} ms; "
             f"DriftData {ours['data_s']:.2f} s; command stages from train.log: start-up ~{startup:.1f} s, "
             + ", ".join(f"{k} {v:.1f} s" for k, v in stages["default"].items()))
    return row("train_default_paper", commands["default"], commands["poly3"], notes,
               fit_s=ours["fit_s"], fit_reference_s=reference["fit_s"], fit_ratio=ours["fit_s"] / reference["fit_s"],
               fit_steps=ours["steps"], data_s=ours["data_s"], command_stages_s=stages["default"],
               command_stages_reference_s=stages["poly3"], startup_s=startup,
               val_rmse_dps=ours["val_rmse_dps"], val_rmse_reference_dps=reference["val_rmse_dps"])


# ---------------------------------------------------------------- GA sweep


def _job_times(job_dir: Path) -> dict[str, float] | None:
    """One sweep job: config written (start), data, fit, export (train.log), last file (end), worker pid."""
    log = job_dir / "train.log"
    if not log.is_file():
        return None
    marks = log_times(log, _STAGE_LINES)
    start = min(p.stat().st_mtime for p in (job_dir / ".hydra").iterdir())
    end = max(p.stat().st_mtime for p in job_dir.rglob("*") if p.is_file())
    # TensorBoard names its event files events.out.tfevents.<time>.<host>.<pid>.<n>: the worker
    pids = {int(p.name.split(".")[-2]) for p in (job_dir / "tb").glob("events.out.tfevents.*")}
    return {"start": start, **marks, "end": end, "pid": pids.pop() if len(pids) == 1 else -1}


def _sweep_breakdown(sweep_dir: Path, log_path: Path, start_epoch: float, end_epoch: float,
                     n_workers: int) -> dict[str, Any]:
    """Jobs run, per-job stages (start-up, data, fit, export and logging) and the sweep's own overheads."""
    history = json.loads((sweep_dir / "ga_history.json").read_text())
    individuals = [(g["generation"], e) for g in history["generations"] for e in g["individuals"]]
    launched = [(gen, e) for gen, e in individuals if not e["cached"]]
    jobs = [(gen, _job_times(sweep_dir / e["job_dir"])) for gen, e in launched if e["job_dir"]]
    jobs = sorted(((g, t) for g, t in jobs if t and {"data", "fit", "export"} <= set(t)), key=lambda j: j[1]["start"])
    # start-up: from the batch's launch, or the same worker's previous job of the batch, to the job's config
    launches = log_matches(log_path, r"^Launching jobs")
    generations_run = sorted({g for g, _ in jobs})
    launch_of = dict(zip(generations_run, launches)) if len(launches) == len(generations_run) else {}
    free_at: dict[tuple[int, int], float] = {}
    stage: dict[str, list[float]] = {"startup": [], "data": [], "fit": [], "export_and_logging": [], "job": []}
    for gen, t in jobs:
        ready = max(launch_of.get(gen, float("nan")), free_at.get((gen, t["pid"]), -np.inf))
        free_at[(gen, t["pid"])] = t["end"]
        if np.isfinite(ready):
            stage["startup"].append(t["start"] - ready)
        stage["data"].append(t["data"] - t["start"])
        stage["fit"].append(t["fit"] - t["data"])
        stage["export_and_logging"].append(t["end"] - t["fit"])
        stage["job"].append(t["end"] - t["start"])
    busy_s = float(sum(stage["job"]))
    spans = [max(t["end"] for g, t in jobs if g == gen) - min(t["start"] for g, t in jobs if g == gen)
             for gen in generations_run]
    sweep_start = log_times(log_path, {"start": r"^GA sweep: "}).get("start", float("nan"))
    return {
        "jobs_run": len(launched), "individuals": len(individuals), "jobs_timed": len(jobs),
        "generations": len(history["generations"]), "workers_seen": len({t["pid"] for _, t in jobs}),
        "per_job_s": {k: {"mean": float(np.mean(v)), "median": float(np.median(v)), "max": float(np.max(v)),
                          "sum": float(np.sum(v))}
                      for k, v in stage.items() if v},
        "busy_s": busy_s,
        "ideal_s": busy_s / n_workers,
        "startup_s": sweep_start - start_epoch,
        "after_last_job_s": end_epoch - max((t["end"] for _, t in jobs), default=float("nan")),
        "generation_span_s": spans,
        "worker_utilisation": busy_s / (n_workers * sum(spans)) if spans else None,
    }


@bench("ga_sweep", long=True)
def ga_sweep(ctx: Context) -> dict[str, Any]:
    """GA sweep (joblib, 2 workers, population 16 x 8 generations; quick 4 x 2) on the paper profile; goal < 10 min."""
    population, generations, n_workers = ctx.size(16, 4), ctx.size(8, 2), 2
    csv = paper_recording(ctx)
    sweep_dir = ctx.path("ga_sweep")
    shutil.rmtree(sweep_dir, ignore_errors=True)  # resume=true would reuse an old history
    log_path = sweep_dir.with_name(sweep_dir.name + ".log")
    start_epoch = time.time()
    wall_s = run_command([sys.executable, str(ROOT / "scripts" / "train.py"), "-m", "hydra/sweeper=ga",
                          "hydra/launcher=joblib", f"hydra.launcher.n_jobs={n_workers}", f"data.path={csv}",
                          f"hydra.sweep.dir={sweep_dir}", f"hydra.sweeper.population_size={population}",
                          f"hydra.sweeper.generations={generations}", "train.progress=false",
                          *train_overrides(ctx)], ctx, log_path=log_path)
    parts = _sweep_breakdown(sweep_dir, log_path, start_epoch, time.time(), n_workers)
    per_job = parts["per_job_s"]
    goal = "met" if wall_s < SWEEP_GOAL_S else "NOT met"
    quick = " (quick, max_epochs=100)" if ctx.quick else ""
    notes = (f"population {population} x {generations} generations{quick}; "
             f"{parts['jobs_run']} jobs run of {parts['individuals']} individuals (rest cached); wall {wall_s:.0f} s "
             f"(goal < {SWEEP_GOAL_S:.0f} s: {goal}); reference = sum of job times / {n_workers} workers; "
             "per job mean: "
             + ", ".join(f"{k} {v['mean']:.1f} s" for k, v in per_job.items())
             + f"; sweep process start-up {parts['startup_s']:.1f} s; worker utilisation "
             f"{(parts['worker_utilisation'] or float('nan')):.0%} within generations")
    return row("ga_sweep", wall_s, parts["ideal_s"], notes, **parts)
