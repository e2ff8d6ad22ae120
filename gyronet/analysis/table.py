"""The paper's Table 1: Allan N and B per axis for raw data and each compensator, plus the residual
over the noise floor, on held-out recordings (one, or each run of a campaign from a fresh state)."""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from gyronet.allan import allan_report
from gyronet.analysis.campaign import BLOCK_S, cold_dwell, floor_dps, score, touched_blocks
from gyronet.bundle.compensator import Compensator
from gyronet.recordings.data import AXES, Recording, load_recording, load_truth, truth_path
from gyronet.training.dataset import block_rmse
from gyronet.deploy.as_flown import is_px4_cubic, px4_firmware_output
from gyronet.errors import GyronetError
from gyronet.bundle.offline import compensate_as_deployed
from gyronet.training.runs import run_name
from gyronet.training.train import residual_report

log = logging.getLogger(__name__)

# The paper's reported figures (LPMS-USBAL2, 60 to -40 degC): N deg/sqrt(h), B deg/h.
PAPER_TABLE_1 = {
    "Raw": {"arw_deg_rthr": [3.03, 4.55, 5.89], "bias_instability_deg_hr": [139, 154, 178]},
    "RBF+GA+KF": {"arw_deg_rthr": [1.58, 2.58, 0.71], "bias_instability_deg_hr": [2.9, 3.9, 1.6]},
}
# a real recording's own floor needs this much of a still cold stretch (ten 60 s blocks)
MIN_COLD_S = 10 * BLOCK_S


def held_out_paths(input_path: str | None = None, path: str | None = None,
                   paths: Sequence[str] | None = None) -> list[str]:
    """The recordings to score: ``input=F.csv``, ``data.path=F.csv`` or ``data.paths=[A.csv,B.csv]``, one of them."""
    given = [[input_path]] if input_path else []
    given += [[path]] if path else []
    given += [list(paths)] if paths else []
    if len(given) != 1:
        raise GyronetError("give the held-out recording(s) once: input=F.csv, data.path=F.csv or "
                           f"data.paths=[A.csv,B.csv] ({'none' if not given else 'more than one'} given)")
    return [str(p) for p in given[0]]


def table_rows(input_path: str | Path, bundles: Mapping[str, str | Path], startup: Mapping[str, Any] | None = None,
               score_from_s: float = 0.0, px4_firmware_schedule: bool = True) -> dict[str, dict[str, Any]]:
    """Raw and each bundle's compensated output on ``input_path``, from a fresh state: N, B and residual / floor.

    ``px4_firmware_schedule``: a PX4 cubic bundle (poly3, px4, px4_onboard) is run as PX4's
    firmware runs it, its offset recomputed once a second and published only when the
    temperature moved more than 1 degC (``gyronet.deploy.as_flown``); False: per sample.

    The floor is the simulator's noise where it wrote the truth, else the recording's own (the
    Allan deviation at 60 s in its cold dwell, ``gyronet.analysis.campaign``: a real run). ``startup``:
    ``Compensator.use_startup`` options (every bundle gets the run's offset, and a row "Raw, start-up
    offset" what the offset alone does, the bar any model must clear); rows are scored from
    ``max(score_from_s, startup.still_s)`` on, so the window that measures the offset is left out.
    """
    recording = load_recording(input_path)
    truth = load_truth(input_path).columns if truth_path(input_path).is_file() else None
    startup = dict(startup or {})
    from_s = max(float(score_from_s), float(startup.get("still_s") or 0.0))
    keep = recording.time_s >= recording.time_s[0] + from_s
    if not keep.any():
        raise GyronetError(f"{input_path}: nothing left to score after {from_s:g} s (score_from_s, startup.still_s)")
    floor = None if truth is not None else _own_floor(recording)
    touched = None if floor is None else touched_blocks(recording)
    kept_truth = None if truth is None else {k: v[keep] for k, v in truth.items()}

    def row(rate_dps: np.ndarray, drift_dps: np.ndarray | None) -> dict[str, Any]:
        figures = _row(recording.time_s[keep], rate_dps[keep], kept_truth, None if drift_dps is None else drift_dps[keep])
        if floor is not None:
            figures["ratio_to_floor"] = score(recording, rate_dps, from_s, floor, touched).tolist()
        return figures

    rows = {"Raw": row(recording.gyro_dps, np.zeros_like(recording.gyro_dps))}
    if startup.get("still_s"):
        window = recording.time_s < recording.time_s[0] + float(startup["still_s"])
        static_dps = np.asarray(startup.get("static_rate_dps") or (0.0, 0.0, 0.0), dtype=np.float64)
        offset_dps = recording.gyro_dps[window].mean(0) - static_dps
        rows["Raw, start-up offset"] = row(recording.gyro_dps - offset_dps,
                                           np.broadcast_to(offset_dps, recording.gyro_dps.shape))
    if truth is not None:
        noise = np.column_stack([truth[f"noise_{a}_dps"] for a in AXES])
        rows["Noise only (truth)"] = _row(recording.time_s[keep], noise[keep], None)
    checksum = recording.checksum()
    for name, bundle in bundles.items():
        log.info("table: %s <- %s on %s", name, bundle, input_path)
        compensator = Compensator.load(bundle)
        compensator.use_startup(**startup)
        out = compensate_as_deployed(compensator, recording)
        if px4_firmware_schedule and is_px4_cubic(compensator.meta):
            out = px4_firmware_output(recording.time_s, recording.temp_c, out)
        meta = compensator.meta
        if checksum in {meta.get("data_sha256"), *(r.get("sha256") for r in meta.get("runs", []))}:
            log.warning("table: %s was trained on %s: its row is in sample, named so and left out of any mean",
                        name, input_path)
            name = f"{name} (in sample)"
        if out.out_of_range[keep].any():
            log.warning("table: %s on %s: %.0f %% of the scored samples are outside its trained temperatures", name,
                        input_path, 100.0 * out.out_of_range[keep].mean())
        rows[name] = row(out.rate_dps, out.drift_dps)
    return rows


def table_runs(paths: Sequence[str], bundles: Mapping[str, str | Path], startup: Mapping[str, Any] | None = None,
               score_from_s: float = 0.0, px4_firmware_schedule: bool = True) -> dict[str, dict[str, dict[str, Any]]]:
    """``table_rows`` for each run of a campaign (each from a fresh state, as at its own power-up), by run name."""
    names = [run_name(p) for p in paths]
    if len(set(names)) != len(names):
        raise GyronetError(f"data.paths: two runs share a name ({', '.join(names)}); rename one")
    return {name: table_rows(path, bundles, startup, score_from_s, px4_firmware_schedule)
            for name, path in zip(names, paths)}


def mean_ratios(per_run: Mapping[str, Mapping[str, Mapping[str, Any]]]) -> dict[str, list[float]]:
    """Residual / floor per axis, averaged over the runs, for every row every run has it for."""
    runs = list(per_run.values())
    names = [n for n in runs[0] if all("ratio_to_floor" in r.get(n, {}) for r in runs)]
    return {n: np.mean([r[n]["ratio_to_floor"] for r in runs], axis=0).tolist() for n in names}


def _own_floor(recording: Recording) -> np.ndarray | None:
    """A real recording's floor (``gyronet.analysis.campaign.floor_dps``), or None, said once, without a still cold stretch."""
    cold = cold_dwell(recording)
    cold_s = float(np.ptp(recording.time_s[cold])) if cold.any() else 0.0
    if cold_s < MIN_COLD_S:
        log.info("%s: no ground truth and no still cold stretch of %g s (%g s): residual / floor left out",
                 recording.path, MIN_COLD_S, cold_s)
        return None
    return floor_dps(recording)


def _row(time_s: np.ndarray, rate_dps: np.ndarray, truth: Mapping[str, np.ndarray] | None,
         drift_dps: np.ndarray | None = None) -> dict[str, Any]:
    report = allan_report(time_s, rate_dps)
    row: dict[str, Any] = {
        "arw_deg_rthr": [report[a]["arw_deg_rthr"] for a in AXES],
        "bias_instability_deg_hr": [report[a]["bias_instability_deg_hr"] for a in AXES],
        # True: B is only an upper bound (the curve still falls at the last tau read), printed "<="
        "bias_instability_upper_bound": [bool(report[a]["bias_instability_upper_bound"]) for a in AXES],
    }
    if truth is not None:
        residual = residual_report(time_s, rate_dps, truth)
        row["ratio_to_floor"] = [residual["ratio_to_floor"][a] for a in AXES]
        row["residual_dps"] = [residual["residual_dps"][a] for a in AXES]
        if drift_dps is not None:  # the drift estimate against the true drift, 60 s blocks
            true_drift = np.column_stack([truth[f"drift_{a}_dps"] for a in AXES])
            row["drift_error_dps"] = block_rmse(time_s, drift_dps - true_drift, 60.0).tolist()
    return row


def to_markdown(rows: Mapping[str, Mapping[str, Any]]) -> str:
    """A Markdown table in the paper's layout, with the residual-to-noise-floor ratio when known; a B that is only
    an upper bound reads ``<=``."""
    has_truth = any("ratio_to_floor" in r for r in rows.values())
    head = "| method | N x | N y | N z | B x | B y | B z |" + (" residual / floor x, y, z |" if has_truth else "")
    unit = "| | deg/sqrt(h) | | | deg/h | | |" + (" |" if has_truth else "")
    lines = [head, "|" + "---|" * (head.count("|") - 1), unit]
    for name, row in rows.items():
        bounds = row.get("bias_instability_upper_bound", [False] * 3)
        cells = [f"{v:.2f}" for v in row["arw_deg_rthr"]] + [
            f"{'<=' if bound else ''}{v:.2f}" for v, bound in zip(row["bias_instability_deg_hr"], bounds)]
        if has_truth:
            cells.append(", ".join(f"{v:.2f}" for v in row["ratio_to_floor"]) if "ratio_to_floor" in row else "")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def runs_to_markdown(per_run: Mapping[str, Mapping[str, Mapping[str, Any]]]) -> str:
    """One table per run, then residual / floor averaged over the runs (when every run has it)."""
    parts = [f"### {name}\n\n{to_markdown(rows)}" for name, rows in per_run.items()]
    means = mean_ratios(per_run)
    if means:
        lines = ["| method | residual / floor x | y | z | mean |", "|---|---|---|---|---|"]
        lines += [f"| {n} | " + " | ".join(f"{v:.2f}" for v in [*m, float(np.mean(m))]) + " |" for n, m in means.items()]
        parts.append(f"### Mean over the {len(per_run)} runs\n\n" + "\n".join(lines) + "\n")
    return "\n".join(parts)
