"""Rows against allantools and pandas: Allan deviation in-process and as a command, loading a recording."""
from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

from .harness import ROOT, Context, bench, row, run_command, timed


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
    from gyronet.recordings.data import write_recording

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

    from gyronet.recordings.data import load_recording

    n = ctx.size(460_000, 46_000)
    csv = _recording(ctx, "load", n, 10.0, extra=True)
    ours_s, recording = timed(load_recording, csv, repeat=3)
    reference_s, _ = timed(pd.read_csv, csv, comment="#", repeat=3)
    assert len(recording) == n
    goal = "met" if ours_s < 0.5 * n / 460_000 else "NOT met"
    return row("load_460k", ours_s, reference_s, f"{n} rows x {len(recording.columns)} columns; goal < 0.5 s"
               f" (scaled to size): {goal}")
