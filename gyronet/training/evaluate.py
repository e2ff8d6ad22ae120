"""``evaluate()``: run a compensator over a whole recording and score it (Allan, truth, error bar)."""
from __future__ import annotations

from typing import Any, Mapping

import numpy as np

from gyronet.recordings.data import AXES
from gyronet.training.dataset import block_rmse


def residual_report(time_s: np.ndarray, compensated_dps: np.ndarray, truth: Mapping[str, np.ndarray],
                    block_s: float = 60.0) -> dict[str, Any]:
    """Score a compensated record against the simulator's ground truth, per axis.

    The residual is compensated minus true rate; the noise floor is the same block statistic of
    the noise the simulator actually added, so a ratio of 1 means "drift fully removed".
    """
    true_rate = np.column_stack([truth[f"true_rate_{a}_dps"] for a in AXES])
    noise = np.column_stack([truth[f"noise_{a}_dps"] for a in AXES])
    residual = block_rmse(time_s, compensated_dps - true_rate, block_s)
    floor = block_rmse(time_s, noise, block_s)
    return {
        "residual_dps": dict(zip(AXES, residual.tolist())),
        "noise_floor_dps": dict(zip(AXES, floor.tolist())),
        "ratio_to_floor": dict(zip(AXES, (residual / floor).tolist())),
    }


def evaluate(compensator: Any, recording: Any, truth: Mapping[str, np.ndarray] | None = None,
             block_s: float = 60.0) -> dict[str, Any]:
    """Run a compensator over a whole recording and score it: Allan N and B raw and compensated,
    and, with ground truth, the residual against the true rate and the noise floor.

    Returns the report dict and keeps the arrays for plots under the private key ``_arrays``.
    """
    from gyronet.allan import allan_report

    compensator.reset()
    out = compensator.process(recording.columns)
    raw = recording.gyro_dps
    report: dict[str, Any] = {
        "path": recording.path,
        "n_samples": len(recording),
        "n_out_of_range": int(out.out_of_range.sum()),
        "allan": {"raw": _allan_summary(allan_report(recording.time_s, raw)),
                  "compensated": _allan_summary(allan_report(recording.time_s, out.rate_dps))},
    }
    arrays = {"time_s": recording.time_s, "temp_c": recording.temp_c, "raw_dps": raw,
              "compensated_dps": out.rate_dps, "drift_hat_dps": out.drift_dps, "drift_sigma_dps": out.drift_sigma_dps}
    if truth is not None:
        report["truth"] = residual_report(recording.time_s, out.rate_dps, truth, block_s)
        noise = np.column_stack([truth[f"noise_{a}_dps"] for a in AXES])
        report["allan"]["noise_only"] = _allan_summary(allan_report(recording.time_s, noise))
        arrays["drift_true_dps"] = np.column_stack([truth[f"drift_{a}_dps"] for a in AXES])
    if out.drift_sigma_dps is not None and np.isfinite(out.drift_sigma_dps).all():
        from gyronet.training.sigma_table import error_bar_summary

        report["error_bar"] = error_bar_summary(recording.time_s, out, arrays.get("drift_true_dps"), block_s)
    report["_arrays"] = arrays
    return report


def _allan_summary(report: Mapping[str, Any]) -> dict[str, Any]:
    """Each axis's curve and terms as ``allan.py`` reports them (a B that is only a bound says so, with the taus
    read at), and the segments (the plot's faint tail past the last tau read)."""
    return {**{axis: dict(report[axis]) for axis in AXES}, "segments": report.get("segments", {})}
