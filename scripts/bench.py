"""Benchmarks against reference tools: python scripts/bench.py [--only NAME ...] [--json PATH] [--quick].

Each row is one function registered with ``@bench("name")``. It gets a :class:`Context` (sizes,
a work folder for generated files) and returns :func:`row`: ``name``, ``ours_s``,
``reference_s``, ``ratio`` (ours / reference: below 1 is faster than the reference) and
``notes``. To add a row, write one more decorated function. Generated data and results go under
``outputs/bench/`` (not versioned). ``--quick`` shrinks every size for a smoke test.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import platform
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
BENCHES: dict[str, Callable[["Context"], dict[str, Any]]] = {}


def bench(name: str) -> Callable:
    """Register a benchmark row under ``name``."""
    def register(fn: Callable[["Context"], dict[str, Any]]) -> Callable[["Context"], dict[str, Any]]:
        if name in BENCHES:
            raise ValueError(f"benchmark {name!r} registered twice")
        BENCHES[name] = fn
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


def timed(fn: Callable, *args: Any, repeat: int = 1, **kwargs: Any) -> tuple[float, Any]:
    """Best wall time of ``repeat`` calls, s, and the last result."""
    best, result = math.inf, None
    for _ in range(repeat):
        start = time.perf_counter()
        result = fn(*args, **kwargs)
        best = min(best, time.perf_counter() - start)
    return best, result


def run_command(args: list[str], ctx: Context) -> float:
    """Wall time of a subprocess, s; raises with its stderr if it fails."""
    start = time.perf_counter()
    proc = subprocess.run(args, cwd=ROOT, env=ctx.env(), capture_output=True, text=True)
    elapsed = time.perf_counter() - start
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(args[:3])} ... exited {proc.returncode}: {proc.stderr.strip()[-500:]}")
    return elapsed


def row(name: str, ours_s: float, reference_s: float | None, notes: str = "") -> dict[str, Any]:
    ratio = ours_s / reference_s if reference_s else None
    return {"name": name, "ours_s": round(ours_s, 4), "reference_s": None if reference_s is None else
            round(reference_s, 4), "ratio": None if ratio is None else round(ratio, 3), "notes": notes}


def _gyro_columns(n: int, fs_hz: float, seed: int, extra: bool = False) -> dict[str, np.ndarray]:
    """A static record: bias, white noise and a slow random walk per axis (and temperature, accel)."""
    rng = np.random.default_rng(seed)
    columns = {"time_s": np.arange(n) / fs_hz}
    if extra:
        columns["temp_c"] = 25.0 + 10.0 * np.sin(columns["time_s"] / 3600.0)
    for i, axis in enumerate("xyz"):
        columns[f"gyro_{axis}_dps"] = (0.1 * (i - 1) + 0.05 * rng.standard_normal(n)
                                       + 2e-6 * np.cumsum(rng.standard_normal(n)))
    if extra:
        for axis, g in zip("xyz", (0.0, 0.0, -1.0)):
            columns[f"acc_{axis}_g"] = g + 1e-3 * rng.standard_normal(n)
    return columns


def _recording(ctx: Context, stem: str, n: int, fs_hz: float, extra: bool) -> Path:
    """Write (once) a seeded recording under the work folder; later runs reuse it."""
    from gyronet.data import write_recording

    path = ctx.work_dir / f"{stem}_{n}.csv"
    if not path.exists():
        partial = path.with_suffix(".partial")
        write_recording(partial, _gyro_columns(n, fs_hz, seed=n % 9973, extra=extra), {"fs_hz": fs_hz})
        partial.replace(path)
    return path


@bench("allan_1e7")
def allan_1e7(ctx: Context) -> dict[str, Any]:
    """gyronet.allan.oadev against allantools.oadev on one long axis, same taus, same run."""
    import allantools

    from gyronet.allan import log_taus, oadev

    n, fs_hz = ctx.size(10_000_000, 200_000), 100.0
    rate = _gyro_columns(n, fs_hz, seed=1)["gyro_x_dps"]
    m, taus_s = log_taus(n, fs_hz)
    ours_s, (_, ours, _) = timed(oadev, rate, fs_hz, m=m)
    reference_s, (_, reference, _, _) = timed(allantools.oadev, rate, rate=fs_hz, data_type="freq", taus=taus_s)
    worst = float(np.max(np.abs(ours / reference - 1.0)))
    return row("allan_1e7", ours_s, reference_s, f"{n} samples, {len(m)} taus, max rel diff {worst:.1e}")


_ALLANTOOLS_SCRIPT = """
import json, sys
import allantools, numpy as np, pandas as pd
frame = pd.read_csv(sys.argv[1], comment="#")
fs_hz = 1.0 / np.median(np.diff(frame["time_s"].to_numpy()))
taus_s = np.loadtxt(sys.argv[2])
out = {}
for axis in "xyz":
    taus, adev, _, _ = allantools.oadev(frame[f"gyro_{axis}_dps"].to_numpy(), rate=fs_hz, data_type="freq",
                                        taus=taus_s)
    out[axis] = {"taus_s": taus.tolist(), "adev_dps": adev.tolist()}
with open(sys.argv[3], "w") as handle:
    json.dump(out, handle)
"""


@bench("allan_cli_3axis_3e6")
def allan_cli_3axis_3e6(ctx: Context) -> dict[str, Any]:
    """The whole ``scripts/allan.py`` command against a plain pandas + allantools script."""
    from gyronet.allan import log_taus

    n, fs_hz = ctx.size(3_000_000, 100_000), 100.0
    csv = _recording(ctx, "allan_3axis", n, fs_hz, extra=False)
    taus_path = ctx.work_dir / f"allan_3axis_{n}.taus.txt"
    np.savetxt(taus_path, log_taus(n, fs_hz)[1])
    ours_json, reference_json = ctx.work_dir / "allan_cli.json", ctx.work_dir / "allan_cli_allantools.json"
    ours_s = run_command([sys.executable, str(ROOT / "scripts" / "allan.py"), f"input={csv}",
                          f"output={ours_json}", f"hydra.run.dir={ctx.work_dir / 'hydra_allan'}"], ctx)
    reference_s = run_command([sys.executable, "-c", _ALLANTOOLS_SCRIPT, str(csv), str(taus_path),
                               str(reference_json)], ctx)
    ours, reference = (json.loads(p.read_text()) for p in (ours_json, reference_json))
    worst = max(float(np.max(np.abs(np.asarray(ours[a]["adev_dps"]) / np.asarray(reference[a]["adev_dps"]) - 1)))
                for a in "xyz")
    return row("allan_cli_3axis_3e6", ours_s, reference_s,
               f"{n} x 3 samples; ours also validates, fits N/B/K and draws the PNG; max rel diff {worst:.1e}")


@bench("load_460k")
def load_460k(ctx: Context) -> dict[str, Any]:
    """load_recording (with validation) against a bare pandas.read_csv of the same file; goal < 0.5 s."""
    import pandas as pd

    from gyronet.data import load_recording

    n = ctx.size(460_000, 46_000)
    csv = _recording(ctx, "load", n, 10.0, extra=True)
    ours_s, recording = timed(load_recording, csv, repeat=3)
    reference_s, _ = timed(pd.read_csv, csv, comment="#", repeat=3)
    assert len(recording) == n
    goal = "met" if ours_s < 0.5 * n / 460_000 else "NOT met"
    return row("load_460k", ours_s, reference_s, f"{n} rows x {len(recording.columns)} columns; goal < 0.5 s"
               f" (scaled to size): {goal}")


def _table(rows: list[dict[str, Any]]) -> str:
    def fmt(value: Any) -> str:
        return "-" if value is None else f"{value:.3f}" if isinstance(value, float) else str(value)

    header = f"{'name':24} {'ours_s':>9} {'reference_s':>12} {'ratio':>7}  notes"
    lines = [header, "-" * len(header)]
    lines += [f"{r['name']:24} {fmt(r['ours_s']):>9} {fmt(r['reference_s']):>12} {fmt(r['ratio']):>7}  {r['notes']}"
              for r in rows]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", nargs="+", metavar="NAME", choices=sorted(BENCHES),
                        help="run only these rows (default: all)")
    parser.add_argument("--json", type=Path, default=ROOT / "outputs" / "bench" / "bench.json",
                        help="where to write the rows as JSON")
    parser.add_argument("--quick", action="store_true", help="small sizes, for a smoke test")
    parser.add_argument("--work-dir", type=Path, default=ROOT / "outputs" / "bench",
                        help="folder for generated data (reused between runs)")
    parser.add_argument("--list", action="store_true", help="list the rows and exit")
    args = parser.parse_args(argv)
    if args.list:
        print("\n".join(f"{name}: {(fn.__doc__ or '').strip()}" for name, fn in BENCHES.items()))
        return 0
    ctx = Context(quick=args.quick, work_dir=args.work_dir.resolve())
    ctx.work_dir.mkdir(parents=True, exist_ok=True)
    rows, failed = [], 0
    for name in args.only or list(BENCHES):
        try:
            rows.append(BENCHES[name](ctx))
        except Exception as err:  # one broken row must not hide the others
            failed += 1
            rows.append({"name": name, "ours_s": None, "reference_s": None, "ratio": None,
                         "notes": f"FAILED: {type(err).__name__}: {err}"})
        print(_table(rows[-1:]).splitlines()[-1], file=sys.stderr, flush=True)
    print(_table(rows))
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps({"quick": args.quick, "machine": platform.platform(),
                                     "cpu_count": os.cpu_count(), "python": platform.python_version(),
                                     "numpy": np.__version__, "rows": rows}, indent=2) + "\n")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
