"""The paper's Table 1: Allan N and B per axis for raw data and each compensator, plus the residual
against ground truth, on one held-out recording."""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from gyronet.allan import allan_report
from gyronet.compensator import Compensator
from gyronet.data import AXES, load_recording, load_truth, truth_path
from gyronet.dataset import block_rmse
from gyronet.offline import compensate_recording
from gyronet.train import residual_report

log = logging.getLogger(__name__)

# The paper's reported figures (LPMS-USBAL2, 60 to -40 degC): N deg/sqrt(h), B deg/h.
PAPER_TABLE_1 = {
    "Raw": {"arw_deg_rthr": [3.03, 4.55, 5.89], "bias_instability_deg_hr": [139, 154, 178]},
    "RBF+GA+KF": {"arw_deg_rthr": [1.58, 2.58, 0.71], "bias_instability_deg_hr": [2.9, 3.9, 1.6]},
}


def table_rows(input_path: str | Path, bundles: Mapping[str, str | Path]) -> dict[str, dict[str, Any]]:
    """Raw and each bundle's compensated output on ``input_path``: N, B, and truth residuals if known."""
    recording = load_recording(input_path)
    truth = load_truth(input_path).columns if truth_path(input_path).is_file() else None
    rows = {"Raw": _row(recording.time_s, recording.gyro_dps, truth, np.zeros_like(recording.gyro_dps))}
    if truth is not None:
        noise = np.column_stack([truth[f"noise_{a}_dps"] for a in AXES])
        rows["Noise only (truth)"] = _row(recording.time_s, noise, None)
    for name, bundle in bundles.items():
        log.info("table: %s <- %s", name, bundle)
        out = compensate_recording(Compensator.load(bundle), recording)
        rows[name] = _row(recording.time_s, out.rate_dps, truth, out.drift_dps)
    return rows


def _row(time_s: np.ndarray, rate_dps: np.ndarray, truth: Mapping[str, np.ndarray] | None,
         drift_dps: np.ndarray | None = None) -> dict[str, Any]:
    report = allan_report(time_s, rate_dps)
    row: dict[str, Any] = {
        "arw_deg_rthr": [report[a]["arw_deg_rthr"] for a in AXES],
        "bias_instability_deg_hr": [report[a]["bias_instability_deg_hr"] for a in AXES],
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
    """A Markdown table in the paper's layout, with the residual-to-noise-floor ratio when known."""
    has_truth = any("ratio_to_floor" in r for r in rows.values())
    head = "| method | N x | N y | N z | B x | B y | B z |" + (" residual / floor x, y, z |" if has_truth else "")
    unit = "| | deg/sqrt(h) | | | deg/h | | |" + (" |" if has_truth else "")
    lines = [head, "|" + "---|" * (head.count("|") - 1), unit]
    for name, row in rows.items():
        cells = [f"{v:.2f}" for v in row["arw_deg_rthr"]] + [f"{v:.2f}" for v in row["bias_instability_deg_hr"]]
        if has_truth:
            cells.append(", ".join(f"{v:.2f}" for v in row["ratio_to_floor"]) if "ratio_to_floor" in row else "")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"
