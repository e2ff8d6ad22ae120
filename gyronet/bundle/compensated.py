"""What a ``Compensator`` returns (``Compensated``, ``CompensatedRow``), refuses (``RateChangeError``) and writes
(``build_meta``: a bundle's ``meta.json`` before ``save_bundle`` adds its own fields)."""
from __future__ import annotations

from typing import Any, Mapping, NamedTuple

import numpy as np

from gyronet.errors import BundleError
from gyronet.recordings.rate_watch import RateChange


class RateChangeError(BundleError):
    """A rate change inside the data that this bundle cannot follow; ``change`` says where."""

    def __init__(self, message: str, change: RateChange):
        super().__init__(message)
        self.change = change

    def __reduce__(self):
        """Both arguments, so that a worker process's error reaches its parent (joblib, submitit) intact."""
        return type(self), (str(self), self.change)


class Compensated(NamedTuple):
    """Output of ``Compensator.process`` for n samples."""

    rate_dps: np.ndarray  # (n, 3) compensated (and, with the Kalman stage, filtered) rate
    drift_dps: np.ndarray  # (n, 3) the model's drift estimate
    out_of_range: np.ndarray  # (n,) bool: temperature outside the range the model was trained on
    # (n,) bool: an impossible input (temperature or gyro, gyronet.recordings.guard) kept out of every filter's
    # state; None (older callers) means none
    bad_input: np.ndarray | None = None
    # (n, 3) the 1-sigma error bar of drift_dps (gyronet.model.error_bar); NaN for a bundle without one,
    # None (older callers) means not computed
    drift_sigma_dps: np.ndarray | None = None


class CompensatedRow(NamedTuple):
    """Output of ``Compensator.process_row`` for one sample, in plain floats."""

    rate_dps: list  # 3 compensated (and filtered) rates
    drift_dps: list  # 3 drift estimates
    out_of_range: bool
    bad_input: bool
    drift_sigma_dps: list | None = None  # 3 error bars of drift_dps (NaN: the bundle has none)


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
