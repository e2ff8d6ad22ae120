"""A loaded bundle, run causally: the one code path for offline files and live streams.

``Compensator.process`` takes the next samples (any number, from one to a whole recording),
computes the causal features, evaluates the TorchScript model, subtracts the drift, removes the
run's start-up offset (``use_startup``) and, when the bundle has one, runs the Kalman stage.
Impossible inputs are flagged (``bad_input``) and kept out of every state. Calling it once on a
recording or once per sample gives the same numbers.
"""
from __future__ import annotations

import logging
import math
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np
import torch

from gyronet.bundle.schema import KALMAN_FILE, META_FILE, check_model, validate_meta
from gyronet.recordings.data import GYRO_COLUMNS
from gyronet.model.error_bar import CHUNK_ROWS, from_meta
from gyronet.errors import BundleError, GyronetError
from gyronet.bundle.compensated import Compensated, CompensatedRow, RateChangeError, build_meta
from gyronet.bundle.io import read_bundle
from gyronet.model.features import FeatureExtractor
from gyronet.recordings.guard import GYRO_RANGE_DPS, bad_gyro
from gyronet.recordings.rate_watch import RateChange
from gyronet.recordings.skipping import stage_skipping
from gyronet.model.small_model import SMALL_ROWS, row_model

log = logging.getLogger(__name__)

# a data rate this far from the bundle's fs_hz (relative) is the bundle's rate with a clock error
RATE_TOLERANCE = 0.05


class Compensator:
    """Stateful compensator built from a bundle's model, metadata and optional Kalman stage."""

    def __init__(self, model: torch.nn.Module, meta: Mapping[str, Any], kalman: Mapping[str, Any] | None = None,
                 source: str | Path | None = None):
        # source: the bundle folder, for messages; meta is checked against the schema either way
        self.source = str(source) if source is not None else "bundle"
        validate_meta(meta, f"{source}/{META_FILE}" if source is not None else META_FILE)
        self.model, self.meta = model, dict(meta)
        self.bundle_fs_hz = float(self.meta["fs_hz"])
        self.fs_hz = self.bundle_fs_hz  # the rate the features run at (use_input_rate may change it)
        self.resample, self.rate_source = False, "input"  # use_input_rate's: how a rate change is met
        self.row_name: Callable[[int], str] = lambda row: f"sample {row + 1}"  # offline: the file's line
        self.extractor = FeatureExtractor(self.meta["features"], self.fs_hz, self._rate_changed)
        self.temp_range_c = tuple(self.meta["temp_range_c"])
        self.kalman = None
        if kalman is not None:
            self.kalman = _kalman_stage(kalman, self.bundle_fs_hz,
                                        f"{source}/{KALMAN_FILE}" if source is not None else KALMAN_FILE)
        self.input_columns = list(dict.fromkeys([*self.extractor.columns, *GYRO_COLUMNS]))
        self.error_bar = from_meta(self.meta, f"{source}/{META_FILE}" if source is not None else META_FILE)
        self.n_out_of_range = 0
        self.n_bad_input = 0  # rows flagged ``bad_input`` since reset()
        self._last_rate_dps: np.ndarray | list | None = None  # the last output row: what a bad gyro value becomes
        self.startup = None  # gyronet.bundle.startup.StartupOffset: the run's offset from its first still seconds
        self._widen_for_offset = False  # add the offset's noise to drift_sigma (use_startup)
        self._row_model = None  # the model on one row of floats, for chunks of a few rows (use_small_chunks)

    @classmethod
    def load(cls, bundle_dir: str | Path) -> "Compensator":
        """Load a bundle folder (CONTRACT.md section 2); a damaged or mismatched bundle is a one-line BundleError."""
        bundle = read_bundle(bundle_dir)
        # the model against meta.json first: a mismatched model.pt is named as such, not by what follows from it
        validate_meta(bundle.meta, f"{bundle_dir}/{META_FILE}")
        check_model(bundle.model, bundle.facts, bundle.meta, str(bundle_dir))
        return cls(bundle.model, bundle.meta, bundle.kalman, source=bundle_dir)

    def use_small_chunks(self, model: torch.nn.Module | None = None) -> bool:
        """Evaluate chunks of up to ``SMALL_ROWS`` rows in plain floats (``gyronet.model.small_model``), not TorchScript.

        The live path's choice: one frame costs a few microseconds instead of ~30 TorchScript ops;
        the result equals TorchScript to rounding, not to the bit, so ``compensate.py`` keeps
        TorchScript. ``model`` is the unfrozen model (default: read from the bundle this was
        loaded from). Returns False, and changes nothing, for a model class it does not know.
        """
        if model is None:
            from gyronet.bundle.io import load_unfrozen

            if not Path(self.source).is_dir():
                raise BundleError(f"{self.source}: not loaded from a bundle folder; pass the unfrozen model")
            model = load_unfrozen(self.source)
        self._row_model = row_model(model)
        return self._row_model is not None

    def use_input_rate(self, fs_hz: float, resample: bool, source: str) -> None:
        """Run at the data's sampling rate ``fs_hz``, or refuse a rate the bundle was not trained at.

        Within ``RATE_TOLERANCE`` of the bundle's ``fs_hz`` nothing changes. Further off, a
        BundleError names both rates, unless ``resample``: then the feature filters are rebuilt
        for ``fs_hz`` (they are defined by time constants in seconds, so they keep the
        continuous-time behaviour the model was trained on) and the state is reset. A bundle
        with a Kalman stage is refused: its drift and noise model was identified per sample at
        the bundle's rate, and moving an AR(p) model to another rate is not exact.
        """
        fs_hz = float(fs_hz)
        self.resample, self.rate_source = bool(resample), source
        if not np.isfinite(fs_hz) or fs_hz <= 0:
            raise BundleError(f"{source}: sampling rate {fs_hz!r} Hz is not a rate > 0")
        if abs(fs_hz / self.bundle_fs_hz - 1.0) <= RATE_TOLERANCE:
            if self.fs_hz != self.bundle_fs_hz:
                self._run_at(self.bundle_fs_hz)
            return
        ratio = self.bundle_fs_hz / fs_hz
        unit = "milliseconds" if 500 < ratio < 2000 else "microseconds" if 5e5 < ratio < 2e6 else None
        if unit is not None:  # resampling would make it worse
            raise BundleError(f"{source}: sampled at {fs_hz:g} Hz, {ratio:.0f}x slower than the bundle {self.source} "
                              f"was trained at ({self.bundle_fs_hz:g} Hz): is time_s in {unit}? It must be seconds")
        if not resample:
            raise BundleError(f"{source}: sampled at {fs_hz:g} Hz, but the bundle {self.source} was trained at "
                              f"{self.bundle_fs_hz:g} Hz (more than {RATE_TOLERANCE:.0%} apart); pass resample=true "
                              f"to run it at {fs_hz:g} Hz, or use a bundle trained at that rate")
        if self.kalman is not None:
            raise BundleError(f"{source}: sampled at {fs_hz:g} Hz, but the bundle {self.source} has a Kalman stage "
                              f"identified at {self.bundle_fs_hz:g} Hz, which cannot be resampled; use a bundle "
                              "trained at the data's rate, or one trained with kalman=disabled")
        log.warning("%s: %g Hz data on a bundle trained at %g Hz: the feature filters run at %g Hz (resample=true)",
                    source, fs_hz, self.bundle_fs_hz, fs_hz)
        self._run_at(fs_hz)

    def _run_at(self, fs_hz: float) -> None:
        self.fs_hz = fs_hz
        self.extractor = FeatureExtractor(self.meta["features"], fs_hz, self._rate_changed, self.bundle_fs_hz)
        self.reset()

    def _rate_changed(self, change: RateChange) -> None:
        """A rate change inside the data (``gyronet.recordings.rate_watch``): the filters follow one to the bundle's
        rate, or with ``resample`` (no Kalman stage) to any; any other is refused in one line."""
        if abs(change.new_hz / self.bundle_fs_hz - 1.0) <= RATE_TOLERANCE or (self.resample and self.kalman is None):
            return
        where = (f"{self.rate_source}: near {self.row_name(change.since_row)} (time_s={change.since_time_s:.6g}): the "
                 f"sampling rate changes from {change.old_hz:.4g} Hz to {change.new_hz:.4g} Hz")
        if self.kalman is not None and self.resample:
            raise RateChangeError(f"{where}, but the bundle {self.source} has a Kalman stage identified at "
                                  f"{self.bundle_fs_hz:g} Hz, which cannot follow it; split the file there", change)
        raise RateChangeError(f"{where}, but the bundle {self.source} was trained at {self.bundle_fs_hz:g} Hz (more than "
                              f"{RATE_TOLERANCE:.0%} apart); pass resample=true to follow it, or split the file there",
                              change)

    def reset(self) -> None:
        """Start a new stream: forget the filter states."""
        self.extractor.reset()
        if self.kalman is not None:
            self.kalman.reset()
        if self.startup is not None:
            self.startup.reset()
        self.n_out_of_range = 0
        self.n_bad_input, self._last_rate_dps = 0, None

    def use_startup(self, still_s: float = 0.0, motion_dps: float = 0.5, static_rate_dps=(0.0, 0.0, 0.0)) -> None:
        """Estimate the run's offset over the first ``still_s`` s and apply it from then on (0: off)."""
        from gyronet.bundle.startup import StartupOffset

        if static_rate_dps is None or (hasattr(static_rate_dps, "__len__") and not len(static_rate_dps)):
            static_rate_dps = (0.0, 0.0, 0.0)  # (a list or an array: no truth test)
        self.startup = StartupOffset(still_s, motion_dps, static_rate_dps) if still_s else None
        calibrated_s = 0.0 if self.error_bar is None else self.error_bar.startup_s
        # a bar calibrated on held-out runs with their start-up offsets has the offset's noise in its floor
        self._widen_for_offset = self.startup is not None and self.error_bar is not None and not calibrated_s
        if calibrated_s > 0 and not still_s:
            log.warning("the error bar was calibrated with a start-up offset over the first %g s; without one "
                        "(startup.still_s=0) the run's turn-on bias is in the error and not in drift_sigma: use "
                        "startup.still_s=%g", calibrated_s, calibrated_s)

    def check_columns(self, columns: Mapping[str, Any], source: str = "input") -> None:
        """Raise a BundleError naming the columns this bundle needs and ``source`` lacks."""
        missing = [c for c in self.input_columns if c not in columns]
        if missing:
            raise BundleError(f"{source}: missing column(s) {', '.join(missing)} that the compensator needs")

    def drift(self, columns: Mapping[str, np.ndarray]) -> np.ndarray:
        """Drift estimate (n, 3), deg/s, advancing the feature state."""
        return self._drift_of(self.extractor.process(columns))

    def drift_sigma(self, features: np.ndarray) -> np.ndarray:
        """The 1-sigma error bar (n, 3), deg/s, of the drift at these features (NaN without an error bar)."""
        if self.error_bar is None:
            return np.full((len(features), 3), np.nan)
        if self._row_model is not None and len(features) <= SMALL_ROWS:
            return np.array([self.error_bar.sigma_row(row) for row in features.tolist()],
                            dtype=np.float64).reshape(-1, 3)
        return self.error_bar.sigma(features)

    def _drift_of(self, features: np.ndarray) -> np.ndarray:
        if self._row_model is not None and len(features) <= SMALL_ROWS:
            return np.array([self._row_model(row) for row in features.tolist()], dtype=np.float64).reshape(-1, 3)
        features = torch.from_numpy(features)
        with torch.no_grad():
            if len(features) <= CHUNK_ROWS:
                return self.model(features).numpy()
            return torch.cat([self.model(chunk) for chunk in features.split(CHUNK_ROWS)]).numpy()

    def process(self, columns: Mapping[str, np.ndarray]) -> Compensated:
        """Compensate the next samples; ``columns`` maps each of ``input_columns`` to an array (n,).

        A row whose temperature the feature extractor rejects gets the features' prediction; a gyro
        value that is not finite or beyond ``gyronet.recordings.guard.GYRO_RANGE_DPS`` is replaced by that
        axis's last output. Both are flagged in ``bad_input``, counted in ``n_bad_input`` and kept
        out of the start-up window and the Kalman state (``gyronet.recordings.skipping``): every other row is
        what the recording without the flagged rows gives.
        """
        self.check_columns(columns, str(self.rate_source))  # one line naming them, not a bare KeyError
        features = self.extractor.process(columns)
        drift_dps = self._drift_of(features)
        sigma_dps = self.drift_sigma(features)
        gyro_dps = np.column_stack([np.asarray(columns[c], dtype=np.float64) for c in GYRO_COLUMNS])
        rejected = self.extractor.rejected
        residual_dps = gyro_dps - drift_dps
        # one comparison in the usual case (NaN compares False)
        bad_dps = None if len(gyro_dps) and np.abs(gyro_dps).max() <= GYRO_RANGE_DPS else bad_gyro(gyro_dps)
        bad_input = rejected if bad_dps is None else rejected | bad_dps.any(1)
        if self.startup is not None:
            # flagged rows stay out of the start-up window's mean; stage_skipping replaces bad values afterwards
            held_dps = residual_dps if bad_dps is None else np.where(bad_dps, 0.0, residual_dps)
            residual_dps = self.startup.process(columns["time_s"], held_dps, ~bad_input if bad_input.any() else None)
            if self._widen_for_offset:
                sigma_dps = self.startup.widen(sigma_dps)
        if bad_input.any():
            rate_dps, self._last_rate_dps = stage_skipping(self.kalman, residual_dps, bad_input, bad_dps,
                                                           self._last_rate_dps)
        else:
            rate_dps = self._stage(residual_dps)
        # from the reading itself, as the C compensator does: a rejected row outside the range carries both flags
        out_of_range = self._outside(np.asarray(columns["temp_c"], dtype=np.float64))
        self.n_out_of_range += int(out_of_range.sum())
        self.n_bad_input += int(np.count_nonzero(bad_input))
        return Compensated(rate_dps, drift_dps, out_of_range, bad_input, sigma_dps)

    def process_row(self, time_s: float, values: Mapping[str, float]) -> CompensatedRow | None:
        """``process`` on one sample in plain floats (``values``: every input column but ``time_s``), the live
        path's one-frame chunk without arrays; the same numbers to rounding. None, with nothing changed,
        where it does not apply (no ``use_small_chunks`` model, a start-up window still open, a gyro value
        out of range): ``process`` it then."""
        if self._row_model is None or (self.startup is not None and not self.startup.done):
            return None
        try:
            gyro_dps = [values[c] for c in GYRO_COLUMNS]
            if not all(abs(v) <= GYRO_RANGE_DPS for v in gyro_dps):  # NaN compares False
                return None
            features, rejected = self.extractor.process_row(time_s, values)
        except KeyError:  # one line naming every missing input, not a bare KeyError
            self.check_columns({"time_s": time_s, **values}, str(self.rate_source))
            raise
        drift_dps = self._row_model(features)
        sigma_dps = [math.nan] * 3 if self.error_bar is None else self.error_bar.sigma_row(features)
        rate_dps = [g - d for g, d in zip(gyro_dps, drift_dps)]
        if self.startup is not None:
            rate_dps = [r - o for r, o in zip(rate_dps, self.startup.offset_dps.tolist())]
            if self._widen_for_offset:
                sigma_dps = [math.sqrt(s * s + v) for s, v in zip(sigma_dps, self.startup.noise_var_dps2.tolist())]
        if self.kalman is not None:
            # a rejected row gets the filter's estimate but stays out of its state (gyronet.recordings.skipping)
            run = self.kalman.peek if rejected else self.kalman.process
            rate_dps = run(np.array([rate_dps]))[0].tolist()
        if not rejected:
            self._last_rate_dps = rate_dps
        out_of_range = self._outside(values["temp_c"])
        self.n_out_of_range += out_of_range
        self.n_bad_input += rejected
        return CompensatedRow(rate_dps, drift_dps, out_of_range, rejected, sigma_dps)

    def _outside(self, temp_c):
        """Outside the trained temperatures (an array or a float; NaN is not outside: it is bad input)."""
        low, high = self.temp_range_c
        return (temp_c < low) | (temp_c > high)

    def _stage(self, rate_dps: np.ndarray) -> np.ndarray:
        if len(rate_dps) == 0:
            return rate_dps
        if self.kalman is not None:
            rate_dps = self.kalman.process(rate_dps)
        self._last_rate_dps = rate_dps[-1]  # a view: rate_dps is never written to afterwards
        return rate_dps


def _kalman_stage(data: Mapping[str, Any], bundle_fs_hz: float, source: str):
    """The bundle's Kalman stage, or a one-line BundleError for a kalman.json that cannot be one."""
    from gyronet.model.kalman import KalmanStage

    try:
        stage = KalmanStage.from_dict(data)
    except (GyronetError, KeyError, TypeError, ValueError, AttributeError, IndexError, np.linalg.LinAlgError) as err:
        what = f"missing field {err}" if isinstance(err, KeyError) else str(err).strip().splitlines()[0]
        raise BundleError(f"{source}: not a valid Kalman stage ({what[:160]})") from None
    if abs(stage.model.fs_hz / bundle_fs_hz - 1.0) > 1e-9:
        raise BundleError(f"{source}: identified at {stage.model.fs_hz:g} Hz, but meta.json says the bundle runs "
                          f"at {bundle_fs_hz:g} Hz; the files come from different bundles")
    return stage


__all__ = ["CHUNK_ROWS", "Compensated", "CompensatedRow", "Compensator", "RATE_TOLERANCE", "RateChangeError",
           "build_meta"]
