"""Score a survey bundle on its held-out history against the simulator's truth, three ways.

Each from the end of the start-up window on, on the same blocks:

- ``deployed``: as ``compensate.py ... startup.still_s=S`` runs it, the run's own offset estimated
  over its first S s (the recording's static rate subtracted). This is the survey's headline: a
  turn-on bias is new at each power-up, so no model trained on another run can know it. Its floor
  is what a perfect drift model leaves when deployed so: the noise minus the window's mean noise,
  a constant the offset carries into every later sample (each sensor draws its own).
- ``turn_on_removed``: no start-up offset, the difference between the two runs' true turn-on
  biases taken from the truth (a campaign's: the held-out run's less its runs' mean): the
  temperature model alone.
- ``as_is``: no start-up offset at all (the turn-on bias difference stays in the residual).
"""
from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping

import numpy as np

from gyronet.bundle.compensator import Compensator
from gyronet.bundle.offline import compensate_as_deployed
from gyronet.bundle.startup import StartupOffset
from gyronet.errors import GyronetError
from gyronet.recordings.data import AXES, Recording
from gyronet.training.dataset import static_rate_dps
from gyronet.training.sigma_table import score_against_truth
from gyronet.training.train import residual_report

VARIANTS = ("deployed", "turn_on_removed", "as_is")


def turn_on_bias(truth: Mapping[str, np.ndarray]) -> np.ndarray:
    """A run's true turn-on bias per axis (zero when it has none), shape (3,), deg/s."""
    columns = [f"turn_on_bias_{a}_dps" for a in AXES]
    if not all(c in truth for c in columns):
        return np.zeros(len(AXES))
    return np.array([float(truth[c][0]) for c in columns])


def deployed_floor_truth(truth: Mapping[str, np.ndarray], keep: np.ndarray) -> dict[str, np.ndarray]:
    """The truth's rows after the start-up window, their noise less the window's mean noise.

    As deployed, a perfect drift model leaves that: the offset carries the window's noise into every
    later sample. Scored on it, residual / floor is 1 where the drift is gone, as without a window.
    """
    out = {k: v[keep] for k, v in truth.items()}
    for a in AXES:
        out[f"noise_{a}_dps"] = out[f"noise_{a}_dps"] - truth[f"noise_{a}_dps"][~keep].mean()
    return out


def score_bundle(bundle: Path, recording: Recording, truth: Mapping[str, np.ndarray], startup_s: float,
                 turn_on_difference_dps: np.ndarray) -> dict[str, Any]:
    """Residual / floor per axis of one bundle on the held-out record and its truth's columns, each of :data:`VARIANTS`."""
    keep = kept_rows(recording, startup_s)
    kept_truth = {k: v[keep] for k, v in truth.items()}
    compensator = Compensator.load(bundle)
    compensator.use_startup(still_s=startup_s, static_rate_dps=static_rate_dps(recording).tolist())
    deployed = compensate_as_deployed(compensator, recording)
    compensator.use_startup(0.0)
    plain = compensate_as_deployed(compensator, recording)
    scores = score_rates(recording, truth, keep, deployed.rate_dps, plain.rate_dps, turn_on_difference_dps)
    scores["n_out_of_range"] = int(plain.out_of_range[keep].sum())
    sigma = deployed.drift_sigma_dps[keep]
    if np.isfinite(sigma).all():  # the bar as deployed: blocks within 1 sigma, and allan.py's recalibration check
        score = score_against_truth(recording.time_s[keep], deployed.rate_dps[keep], sigma,
                                    deployed.out_of_range[keep], kept_truth)
        scores["error_bar"] = {"within_1_sigma": [score["within_1_sigma"][a] for a in AXES],
                               "calibrated_range": [score["calibrated_range"][a] for a in AXES],
                               "worst_hour_rms_ratio": [score["recalibration"][a]["worst_hour_rms_ratio"] for a in AXES]}
    return scores


def kept_rows(recording: Recording, startup_s: float) -> np.ndarray:
    """The rows scored: from the end of the start-up window on (a one-line error if none are left)."""
    keep = recording.time_s >= recording.time_s[0] + startup_s
    if keep.sum() < 2:
        raise GyronetError(f"{recording.path}: nothing left to score after startup_s={startup_s:g} s")
    return keep


def with_startup_offset(recording: Recording, plain_dps: np.ndarray, startup_s: float) -> np.ndarray:
    """``plain_dps`` (n, 3) less the run's offset from ``startup_s`` s on, measured as ``compensate.py`` measures it."""
    window = StartupOffset(startup_s, static_rate_dps=static_rate_dps(recording))
    return window.process(recording.time_s, plain_dps)


def score_rates(recording: Recording, truth: Mapping[str, np.ndarray], keep: np.ndarray, deployed_dps: np.ndarray,
                plain_dps: np.ndarray, turn_on_difference_dps: np.ndarray) -> dict[str, list[float]]:
    """Residual / floor per axis of each of :data:`VARIANTS`, from the rates compensated with and without the
    start-up offset (shape (n, 3)), on the ``keep`` rows."""
    rates = {"deployed": deployed_dps, "as_is": plain_dps, "turn_on_removed": plain_dps - turn_on_difference_dps}
    kept_truth = {k: v[keep] for k, v in truth.items()}
    scores = {}
    for variant in VARIANTS:
        floor_truth = deployed_floor_truth(truth, keep) if variant == "deployed" else kept_truth
        report = residual_report(recording.time_s[keep], rates[variant][keep], floor_truth)
        scores[variant] = [report["ratio_to_floor"][a] for a in AXES]
    return scores
