"""The table of docs/results/rate-changes.md: damaged sample clocks scored against the simulator's truth.

Each case is the held-out recording (a thermal history the bundle was not trained on) with its
clock damaged (:mod:`gyronet.sim.timing`), compensated as ``compensate.py`` runs it
(:func:`gyronet.bundle.offline.compensate_as_deployed`), and scored as the 60 s block RMS of the
residual against the truth's own rate at the truth's own time, over the intact file's.
A refusal is a result too: its one line is the row.
"""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np

from gyronet.bundle.compensator import Compensator
from gyronet.recordings.data import Recording, block_means
from gyronet.errors import GyronetError
from gyronet.bundle.offline import compensate_as_deployed
from gyronet.sim import timing

log = logging.getLogger(__name__)

TRUE_RATE = tuple(f"true_rate_{axis}_dps" for axis in "xyz")
BLOCK_S = 60.0


def residual_rms_dps(time_s: np.ndarray, rate_dps: np.ndarray, truth: Mapping[str, np.ndarray]) -> np.ndarray:
    """60 s block RMS of the compensated rate minus the true rate, per axis, on the truth's clock."""
    true_dps = np.column_stack([truth[c] for c in TRUE_RATE])
    return np.sqrt(np.mean(block_means(rate_dps - true_dps, time_s, BLOCK_S) ** 2, axis=0))


def score(bundle: str | Path, recording: Mapping[str, np.ndarray], truth: Mapping[str, np.ndarray],
          resample: bool = False, name: str = "damaged.csv", fs_hz: float | None = None) -> np.ndarray | str:
    """Residual RMS per axis of ``recording`` compensated by ``bundle`` as compensate.py does, or the
    refusal's one line. ``fs_hz``: a declared ``# fs_hz`` (None: none, the median interval's)."""
    meta = {} if fs_hz is None else {"fs_hz": f"{fs_hz:g}"}
    compensator = Compensator.load(bundle)
    try:
        out = compensate_as_deployed(compensator, Recording(dict(recording), meta, name), resample)
    except GyronetError as error:
        return f"refused: {error}"
    return residual_rms_dps(truth["time_s"], out.rate_dps, truth)


def damaged_cases(recording: Mapping[str, np.ndarray], step: int, seed: int = 0) -> dict[str, tuple[dict, np.ndarray]]:
    """The table's inputs, each a recording and the simulation rows it holds, from a simulation ``step``
    times faster than the bundle's rate."""
    n = len(recording["time_s"])
    rng = np.random.default_rng(seed)
    every = np.arange(0, n, step)

    def stamped(change: Callable[[np.ndarray], np.ndarray]) -> tuple[dict, np.ndarray]:
        columns = {k: v[every] for k, v in recording.items()}
        columns["time_s"] = change(columns["time_s"])
        return columns, every

    def rows(picked: np.ndarray) -> tuple[dict, np.ndarray]:
        return {k: v[picked] for k, v in recording.items()}, picked

    half = max(1, step // 2)
    return {
        "intact": rows(every),
        "stamp jitter +-20 %": stamped(lambda t: timing.jitter_stamps(t, 0.2, rng)),
        "stamp jitter +-30 %": stamped(lambda t: timing.jitter_stamps(t, 0.3, rng)),
        "sampling jitter +-20 %": rows(timing.irregular_rows(n, step, 0.2, rng)),
        "sampling jitter +-30 %": rows(timing.irregular_rows(n, step, 0.3, rng)),
        "clock 200 ppm fast": stamped(lambda t: timing.drift_stamps(t, offset_ppm=200.0)),
        "clock drifting to 1 % fast over the file": stamped(lambda t: timing.drift_stamps(t, end_fraction=0.01)),
        "rate doubles for the last fifth (the median stays)": rows(timing.rate_change_rows(n, step, half, 0.8)),
        "rate doubles for the last third (the median doubles)": rows(timing.rate_change_rows(n, step, half, 2 / 3)),
        "rate halves half-way": rows(timing.rate_change_rows(n, step, 2 * step, 0.5)),
        "rate doubles for a tenth at 20 %": rows(np.unique(np.concatenate([
            timing.rate_change_rows(n, step, half, 0.2)[:int(0.3 * n / half)], every[every >= int(0.3 * n)]]))),
    }


def rate_table(bundle: str | Path, recording: Mapping[str, np.ndarray], truth: Mapping[str, np.ndarray],
               step: int, seed: int = 0) -> dict[str, dict[str, Any]]:
    """Every case with and without ``resample``: its residual per axis over the residual of the same
    samples with the features computed at the simulation's full rate (the clock's cost alone), or
    the refusal."""
    compensator = Compensator.load(bundle)
    full_rate = compensate_as_deployed(compensator, Recording(dict(recording), {}, "full-rate"), True).rate_dps
    rows: dict[str, dict[str, Any]] = {}
    for name, (columns, picked) in damaged_cases(recording, step, seed).items():
        case_truth = {k: v[picked] for k, v in truth.items()}
        reference = residual_rms_dps(case_truth["time_s"], full_rate[picked], case_truth)
        rows[name] = {"n_samples": len(picked)}
        for resample in (False, True):
            got = score(bundle, columns, case_truth, resample)
            rows[name]["resample" if resample else "default"] = got if isinstance(got, str) else (got / reference).tolist()
    return rows


def to_markdown(rows: Mapping[str, Mapping[str, Any]]) -> str:
    """Rows as a markdown table: the ratio per axis x / y / z, or the refusal."""
    def cell(value: Any) -> str:
        return value if isinstance(value, str) else " / ".join(f"{v:.2f}x" for v in value)

    lines = ["| input (held-out recording) | compensate.py | with resample=true |", "|---|---|---|"]
    lines += [f"| {name} | {cell(row['default'])} | {cell(row['resample'])} |" for name, row in rows.items()]
    return "\n".join(lines)


def training_rows(train_recording: Mapping[str, np.ndarray], recording: Mapping[str, np.ndarray],
                  truth: Mapping[str, np.ndarray], step: int, held_out_step: int, out_dir: str | Path,
                  train_model: Callable[[str, Path], Path]) -> dict[str, list[float]]:
    """Train on ``train_recording`` (a simulation ``step`` times the bundle's rate) intact and with its rate
    doubled for the last fifth; each bundle's held-out residual (``recording`` at the bundle's rate)
    over the intact bundle's (``held_out_step``: its step to the bundle's rate).

    ``train_model(csv_path, run_dir)`` trains one bundle and returns its folder (the caller's recipe).
    """
    from gyronet.recordings.data import write_recording

    n = len(train_recording["time_s"])
    half = max(1, step // 2)
    cases = {"intact": np.arange(0, n, step),
             "rate doubles for the last fifth (the median stays)": timing.rate_change_rows(n, step, half, 0.8)}
    every = np.arange(0, len(recording["time_s"]), held_out_step)
    held_out = {k: v[every] for k, v in recording.items()}
    held_truth = {k: v[every] for k, v in truth.items()}
    out_dir = Path(out_dir)
    results: dict[str, np.ndarray | str] = {}
    for i, (name, rows) in enumerate(cases.items()):
        path = out_dir / f"train{i}.csv"
        out_dir.mkdir(parents=True, exist_ok=True)
        write_recording(path, {k: v[rows] for k, v in train_recording.items()}, {})
        results[name] = score(train_model(str(path), out_dir / f"run{i}"), held_out, held_truth)
    intact = np.asarray(results["intact"])
    return {name: (got if isinstance(got, str) else (np.asarray(got) / intact).tolist()) for name, got in results.items()}


__all__ = ["damaged_cases", "rate_table", "residual_rms_dps", "score", "to_markdown", "training_rows"]
