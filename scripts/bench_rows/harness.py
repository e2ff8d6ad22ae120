"""The benchmark harness: the row registry, the context a row gets, timers and shared inputs.

A row is a function ``fn(ctx: Context) -> dict`` registered with ``@bench("name")``; it returns
:func:`row`. Rows marked ``long=True`` run only when named with ``--only`` or under ``--full``.
"""
from __future__ import annotations

import math
import os
import re
import shutil
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
BENCHES: dict[str, Callable[["Context"], dict[str, Any]]] = {}
LONG: set[str] = set()


def bench(name: str, long: bool = False) -> Callable:
    """Register a benchmark row under ``name``; ``long`` rows run only when asked for."""
    def register(fn: Callable[["Context"], dict[str, Any]]) -> Callable[["Context"], dict[str, Any]]:
        if name in BENCHES:
            raise ValueError(f"benchmark {name!r} registered twice")
        BENCHES[name] = fn
        if long:
            LONG.add(name)
        return fn
    return register


@dataclass(frozen=True)
class Context:
    """What a benchmark row may depend on."""

    quick: bool
    work_dir: Path

    def size(self, full: int, quick: int) -> int:
        return quick if self.quick else full

    def env(self) -> dict[str, str]:
        """Environment for subprocesses: this checkout first on the import path."""
        return {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}

    def path(self, stem: str) -> Path:
        """A file or folder under the work folder, suffixed ``_quick`` in quick mode (never mixed up)."""
        return self.work_dir / (f"{stem}_quick" if self.quick else stem)


def timed(fn: Callable, *args: Any, repeat: int = 1, **kwargs: Any) -> tuple[float, Any]:
    """Best wall time of ``repeat`` calls, s, and the last result."""
    best, result = math.inf, None
    for _ in range(repeat):
        start = time.perf_counter()
        result = fn(*args, **kwargs)
        best = min(best, time.perf_counter() - start)
    return best, result


def run_command(args: list[str], ctx: Context, log_path: Path | None = None, timeout_s: float | None = None) -> float:
    """Wall time of a subprocess, s; raises with its stderr if it fails. ``log_path`` keeps its output."""
    start = time.perf_counter()
    proc = subprocess.run(args, cwd=ROOT, env=ctx.env(), capture_output=True, text=True, timeout=timeout_s)
    elapsed = time.perf_counter() - start
    if log_path is not None:
        log_path.parent.mkdir(parents=True, exist_ok=True)
        log_path.write_text(proc.stdout + proc.stderr)
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(args[:3])} ... exited {proc.returncode}: {proc.stderr.strip()[-500:]}")
    return elapsed


def row(name: str, ours_s: float, reference_s: float | None, notes: str = "", **figures: Any) -> dict[str, Any]:
    """A result row; ``figures`` are extra named numbers (``samples_per_s``, ``p99_ms``, a breakdown...)."""
    ratio = ours_s / reference_s if reference_s else None
    return {"name": name, "ours_s": round(ours_s, 4), "reference_s": None if reference_s is None else
            round(reference_s, 4), "ratio": None if ratio is None else round(ratio, 3), "notes": notes,
            **{k: _rounded(v) for k, v in figures.items()}}


def _rounded(value: Any) -> Any:
    if isinstance(value, (float, np.floating)):
        return float(f"{float(value):.4g}") if math.isfinite(value) else None
    if isinstance(value, Mapping):
        return {k: _rounded(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_rounded(v) for v in value]
    return value


class LoadSampler:
    """Samples the 1-minute load average in a thread while a row runs: start, mean, max, end."""

    def __init__(self, every_s: float = 5.0):
        self.every_s, self.samples = every_s, [os.getloadavg()[0]]
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self._stop.wait(self.every_s):
            self.samples.append(os.getloadavg()[0])

    def __enter__(self) -> "LoadSampler":
        self._thread.start()
        return self

    def __exit__(self, *exc: Any) -> None:
        self._stop.set()
        self._thread.join()
        self.samples.append(os.getloadavg()[0])

    def summary(self) -> dict[str, float]:
        return {"start": self.samples[0], "mean": float(np.mean(self.samples)), "max": max(self.samples),
                "end": self.samples[-1]}


def rss_mb(pid: int | str = "self") -> float:
    """Resident set size of a process, MB (Linux /proc)."""
    with open(f"/proc/{pid}/statm") as handle:
        return int(handle.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 1e6


# "[date time,ms][logger][LEVEL] - message" in job logs, "[date time,ms][HYDRA] message" from Hydra itself
_LOG_LINE = re.compile(r"^\[(\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d{3})\]\[([^\]]+)\](?:\[\w+\] -)? (.*)$")


def log_matches(path: Path, pattern: str) -> list[float]:
    """Epoch times of every line of a Hydra log whose message matches the regex ``pattern``."""
    times = []
    for line in path.read_text().splitlines():
        match = _LOG_LINE.match(line)
        if match and re.search(pattern, match.group(3)):
            times.append(datetime.strptime(match.group(1), "%Y-%m-%d %H:%M:%S,%f").timestamp())
    return times


def log_times(path: Path, patterns: Mapping[str, str]) -> dict[str, float]:
    """Epoch time of the first line of a Hydra log matching each regex (keys absent when none does)."""
    found = {key: log_matches(path, pattern) for key, pattern in patterns.items()}
    return {key: times[0] for key, times in found.items() if times}


# ---------------------------------------------------------------- shared inputs


def paper_recording(ctx: Context) -> Path:
    """The paper's 12.7 h chamber profile (gyronet.sim defaults, 10 Hz; 1 Hz in quick mode), written once."""
    from gyronet.sim import simulate, write_simulation

    fs_hz = 1.0 if ctx.quick else 10.0
    path = ctx.work_dir / f"paper_{fs_hz:g}hz.csv"
    if not path.exists():
        partial = path.with_name(path.stem + "_partial.csv")
        recording, truth = write_simulation(simulate("paper", fs_hz=fs_hz), partial)
        truth.replace(path.with_name(path.stem + ".truth.csv"))
        recording.replace(path)
    return path


def train_overrides(ctx: Context) -> list[str]:
    """Overrides that shrink training in quick mode (none in full mode: the default config)."""
    return ["train.max_epochs=100", "train.patience=50"] if ctx.quick else []


def train_command(ctx: Context, csv: Path, run_dir: Path, model: str | None = None) -> list[str]:
    """``python scripts/train.py data.path=F.csv [model=M]`` into ``run_dir``."""
    return [sys.executable, str(ROOT / "scripts" / "train.py"), f"data.path={csv}",
            *([f"model={model}"] if model else []), f"hydra.run.dir={run_dir}", *train_overrides(ctx)]


def bundle_run_dir(ctx: Context, model: str) -> Path:
    """Where ``train_default_paper`` trains ``model`` (default or poly3); other rows reuse the bundle."""
    return ctx.path(f"train_{model}")


def trained_bundle(ctx: Context, model: str) -> Path:
    """The bundle of ``model`` trained on :func:`paper_recording`: reused when it loads, else trained."""
    from gyronet.bundle.compensator import Compensator

    csv = paper_recording(ctx)
    bundle = bundle_run_dir(ctx, model) / "compensator"
    try:
        if (bundle / "model.pt").stat().st_mtime > csv.stat().st_mtime:
            Compensator.load(bundle)
            return bundle
    except Exception:  # missing, stale or unreadable: train it again
        pass
    shutil.rmtree(bundle.parent, ignore_errors=True)
    run_command(train_command(ctx, csv, bundle.parent, None if model == "default" else model), ctx)
    return bundle


def percentiles_ms(seconds: Sequence[float] | np.ndarray) -> dict[str, float]:
    """p50, p99, p99.9 and max of durations given in seconds, in ms."""
    values = np.asarray(seconds, dtype=float) * 1e3
    if values.size == 0:
        return {}
    p50, p99, p999 = np.percentile(values, [50, 99, 99.9])
    return {"p50": p50, "p99": p99, "p99_9": p999, "max": float(values.max())}
