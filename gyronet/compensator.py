"""A loaded bundle, run causally: the one code path for offline files and live streams.

``Compensator.process`` takes the next samples (any number, from one to a whole recording),
computes the causal features, evaluates the TorchScript model, subtracts the drift and, when the
bundle has one, runs the Kalman stage. Calling it once on a recording or once per sample gives
the same numbers.
"""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Mapping, NamedTuple

import numpy as np
import torch

from gyronet.data import GYRO_COLUMNS
from gyronet.errors import BundleError
from gyronet.export import load_bundle
from gyronet.features import FeatureExtractor

log = logging.getLogger(__name__)

# Rows per model call on a long batch: intermediates of 64 k rows stay in cache, which makes a
# whole recording about six times faster than one call on all of it (scripts/bench.py).
CHUNK_ROWS = 65536


class Compensated(NamedTuple):
    """Output of ``Compensator.process`` for n samples."""

    rate_dps: np.ndarray  # (n, 3) compensated (and, with the Kalman stage, filtered) rate
    drift_dps: np.ndarray  # (n, 3) the model's drift estimate
    out_of_range: np.ndarray  # (n,) bool: temperature outside the range the model was trained on


class Compensator:
    """Stateful compensator built from a bundle's model, metadata and optional Kalman stage."""

    def __init__(self, model: torch.nn.Module, meta: Mapping[str, Any], kalman: Mapping[str, Any] | None = None):
        self.model, self.meta = model, dict(meta)
        self.extractor = FeatureExtractor(self.meta["features"], float(self.meta["fs_hz"]))
        self.temp_range_c = tuple(self.meta["temp_range_c"])
        self.kalman = None
        if kalman is not None:
            from gyronet.kalman import KalmanStage

            self.kalman = KalmanStage.from_dict(kalman)
        self.input_columns = list(dict.fromkeys([*self.extractor.columns, *GYRO_COLUMNS]))
        self.n_out_of_range = 0
        self.startup = None  # gyronet.startup.StartupOffset: the run's offset from its first still seconds

    @classmethod
    def load(cls, bundle_dir: str | Path) -> "Compensator":
        """Load a bundle folder (CONTRACT.md section 2)."""
        return cls(*load_bundle(bundle_dir))

    def reset(self) -> None:
        """Start a new stream: forget the filter states."""
        self.extractor.reset()
        if self.kalman is not None:
            self.kalman.reset()
        if self.startup is not None:
            self.startup.reset()
        self.n_out_of_range = 0

    def use_startup(self, still_s: float = 0.0, motion_dps: float = 0.5, static_rate_dps=(0.0, 0.0, 0.0)) -> None:
        """Estimate the run's offset over the first ``still_s`` s and apply it from then on (0: off)."""
        from gyronet.startup import StartupOffset

        self.startup = StartupOffset(still_s, motion_dps, static_rate_dps or (0.0, 0.0, 0.0)) if still_s else None

    def check_columns(self, columns: Mapping[str, Any], source: str = "input") -> None:
        """Raise a BundleError naming the columns this bundle needs and ``source`` lacks."""
        missing = [c for c in self.input_columns if c not in columns]
        if missing:
            raise BundleError(f"{source}: missing column(s) {', '.join(missing)} that the compensator needs")

    def drift(self, columns: Mapping[str, np.ndarray]) -> np.ndarray:
        """Drift estimate (n, 3), deg/s, advancing the feature state."""
        features = torch.from_numpy(self.extractor.process(columns))
        with torch.no_grad():
            if len(features) <= CHUNK_ROWS:
                return self.model(features).numpy()
            return torch.cat([self.model(chunk) for chunk in features.split(CHUNK_ROWS)]).numpy()

    def process(self, columns: Mapping[str, np.ndarray]) -> Compensated:
        """Compensate the next samples; ``columns`` maps each of ``input_columns`` to an array (n,)."""
        drift_dps = self.drift(columns)
        gyro_dps = np.column_stack([np.asarray(columns[c], dtype=np.float64) for c in GYRO_COLUMNS])
        rate_dps = gyro_dps - drift_dps
        if self.startup is not None:
            rate_dps = self.startup.process(columns["time_s"], rate_dps)
        if self.kalman is not None:
            rate_dps = self.kalman.process(rate_dps)
        temp_c = np.asarray(columns["temp_c"], dtype=np.float64)
        low, high = self.temp_range_c
        out_of_range = (temp_c < low) | (temp_c > high)
        self.n_out_of_range += int(out_of_range.sum())
        return Compensated(rate_dps, drift_dps, out_of_range)


def build_meta(feature_specs: list, feature_names: list, fs_hz: float, temp_range_c: tuple[float, float],
               input_columns: list, data_sha256: str, model_info: Mapping[str, Any]) -> dict[str, Any]:
    """The ``meta.json`` content (CONTRACT.md section 2), apart from the fields ``save_bundle`` adds."""
    if not np.isfinite(fs_hz) or fs_hz <= 0:
        raise BundleError(f"cannot build a bundle for a sampling rate of {fs_hz} Hz")
    return {
        "input_columns": list(input_columns),
        "features": feature_specs,
        "feature_names": feature_names,
        "fs_hz": fs_hz,
        "temp_range_c": list(temp_range_c),
        "axes": ["x", "y", "z"],
        "output": "drift per axis, deg/s; compensated = gyro - drift",
        "data_sha256": data_sha256,
        "model": dict(model_info),
    }
