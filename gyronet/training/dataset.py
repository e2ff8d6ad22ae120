"""Training data: a recording turned into causal features and drift targets, split by time block.

The thermal drift changes over minutes, so fitting it at 10 Hz would spend the effort on noise:
features and targets are averaged over ``block_s`` (10 s by default) after the causal features are
computed at the full rate. Validation is a set of whole time blocks (or a separate recording),
never random samples of the training run.
"""
from __future__ import annotations

import functools
import json
import logging
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from gyronet.errors import GyronetError, RecordingError
from gyronet.model.features import PAPER_FEATURES, FeatureExtractor, required_columns
from gyronet.recordings.data import (AXES, GYRO_COLUMNS, Recording, block_means, gap_blocks, load_recording,
                                     split_by_time, time_blocks, warn_timing)
from gyronet.recordings.guard import check_temperatures

log = logging.getLogger(__name__)

# beyond these a sample is no reading of a real sensor: a corrupt line, not data to fit
RATE_LIMIT_DPS = 1.0e4  # the widest MEMS gyro ranges are +-4000 deg/s
# a record must vary this much in temperature to fit a drift on it, degC
MIN_TEMP_SPAN_C = 1.0
# and give at least this many averaging blocks to fit on and to validate on
MIN_TRAIN_BLOCKS = 10
MIN_VAL_BLOCKS = 2


def static_rate_dps(recording: Recording, override: Sequence[float] | None = None) -> np.ndarray:
    """The true rate during the static test (e.g. the Earth's rate on the sensor's axes), shape (3,).

    From ``override`` if given, else from the recording's ``# static_rate_dps=x,y,z`` metadata line,
    else zero: the compensator then learns the Earth's rate as part of the bias, as PX4 does.
    """
    given = override if override is not None else recording.meta.get("static_rate_dps", "0,0,0").split(",")
    values = [float(v) for v in given]
    if len(values) != 3:
        raise GyronetError(f"static_rate_dps needs 3 values (x, y, z), got {values}")
    return np.asarray(values)


@dataclass
class Blocks:
    """Block-averaged features ``x`` (m, k) and drift targets ``y`` (m, 3), with block mid-times."""

    x: np.ndarray
    y: np.ndarray
    time_s: np.ndarray

    def __len__(self) -> int:
        return len(self.y)


def _file_key(path: str) -> tuple[str, int, int]:
    stat = os.stat(path)
    return str(Path(path).resolve()), stat.st_mtime_ns, stat.st_size


@functools.lru_cache(maxsize=4)
def _load_by_key(key: tuple[str, int, int]) -> Recording:
    return load_recording(key[0])


def load_cached(path: str) -> Recording:
    """Load a recording once per process: sweep jobs in a reused joblib worker share it."""
    if not os.path.isfile(path):
        return load_recording(path)  # raises the one-line error
    return _load_by_key(_file_key(path))


@functools.lru_cache(maxsize=8)
def _features_by_key(key: tuple[str, int, int], specs_json: str, fs_hz: float) -> tuple[np.ndarray, np.ndarray]:
    """Features of a file and the mask of its accepted rows (both read-only: shared between runs)."""
    features, accepted = featurize(_load_by_key(key), json.loads(specs_json), fs_hz, with_accepted=True)
    features.setflags(write=False)  # shared between the runs of one process
    accepted.setflags(write=False)
    return features, accepted


def clear_caches() -> None:
    """Forget every recording and feature set this process has loaded (a cold load next time)."""
    _load_by_key.cache_clear()
    _features_by_key.cache_clear()


def check_physical(recording: Recording) -> None:
    """Refuse a recording with a rate no real sensor gives (a corrupt line), or too many temperatures no sensor
    reads (Kelvin, a wrong column: ``guard.check_temperatures``), naming the line."""
    for name in GYRO_COLUMNS:
        values = recording.columns[name]
        bad = np.flatnonzero(np.abs(values) > RATE_LIMIT_DPS)
        if bad.size:
            raise RecordingError(f"{recording.path}: {recording.line_of(int(bad[0]))}: {name} = "
                                 f"{float(values[bad[0]]):.6g} deg/s is outside any sensor's range "
                                 f"({-RATE_LIMIT_DPS:g} .. {RATE_LIMIT_DPS:g}); {bad.size} such sample(s): fix or "
                                 "remove those lines")
    check_temperatures(recording)


def check_features_present(recording: Recording, specs: Sequence[Mapping[str, Any]]) -> None:
    """The columns the features read must be in the recording: say why when the loader dropped one."""
    for name in required_columns(specs):
        if name not in recording.columns:
            why = recording.dropped.get(name)
            raise GyronetError(f"{recording.path}: the features need column {name!r}, "
                               + (f"which is not usable ({why})" if why else "which the recording lacks"))


def featurize(recording: Recording, specs: Sequence[Mapping[str, Any]], fs_hz: float | None = None,
              with_accepted: bool = False) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """Causal features of a whole recording at its full rate, shape (n, len(specs)).

    With ``with_accepted``, also the mask (n,) of the rows the guard accepted: a rejected row
    (``gyronet.recordings.guard``) has the filters' prediction for features and must not be trained on.
    """
    check_features_present(recording, specs)
    extractor = FeatureExtractor(specs, fs_hz or recording.fs_hz)
    features = extractor.process(recording.columns)
    return (features, ~extractor.rejected) if with_accepted else features


def trained_range_c(temp_c: np.ndarray, accepted: np.ndarray) -> tuple[float, float]:
    """The temperature box a bundle records: the accepted readings' extremes, never a rejected glitch's."""
    kept = temp_c[accepted]
    if not kept.size:
        raise GyronetError("no temperature reading was accepted: every row is an impossible value")
    return float(kept.min()), float(kept.max())


def to_blocks(time_s: np.ndarray, features: np.ndarray, target: np.ndarray, block_s: float) -> Blocks:
    """Average features and targets over ``block_s`` blocks (partial blocks under half full dropped)."""
    return Blocks(block_means(features, time_s, block_s), block_means(target, time_s, block_s),
                  block_means(time_s, time_s, block_s))


class TrainingData:
    """What every kind of training data says about its features (one recording, or several runs)."""

    features: list
    fs_hz: float

    @property
    def n_features(self) -> int:
        return len(self.features)

    @property
    def feature_names(self) -> list[str]:
        return FeatureExtractor(self.features, self.fs_hz).names

    @property
    def axes(self) -> tuple[str, ...]:
        return AXES


@dataclass
class DriftData(TrainingData):
    """A recording ready for training: features, targets, train/validation blocks.

    Parameters
    ----------
    path
        The training recording (CONTRACT.md section 1).
    features
        Feature specs (``gyronet.model.features``); the paper's T, dT/dt and T*dT/dt by default.
    block_s
        Averaging block for training, s.
    val_fraction, n_blocks, val_fold
        Hold out ``val_fraction`` of the record as whole time blocks out of ``n_blocks``; ``val_fold``
        picks which of the 1 / ``val_fraction`` interleaved sets (default: the middle one).
    val_path
        A separate validation recording instead (a different thermal history): preferred.
    static_rate_dps
        True rate during the test, deg/s per axis; see ``static_rate_dps()``.
    rate_tau_s
        If given, the time constant of every ``rate`` feature (a single knob for sweeps).
    val_startup_s
        Mix the starts as deployed with a start-up offset over this many s (``gyronet.training.starts``; 0: as is).
    """

    path: str
    features: list = field(default_factory=lambda: [dict(s) for s in PAPER_FEATURES])
    block_s: float = 10.0
    val_fraction: float = 0.2
    n_blocks: int = 10
    val_fold: int | None = None
    val_path: str | None = None
    static_rate_dps: Sequence[float] | None = None
    rate_tau_s: float | None = None
    val_startup_s: float = 0.0

    def __post_init__(self) -> None:
        self.features = [dict(s) for s in self.features]
        if self.rate_tau_s is not None:
            for spec in self.features:
                if spec["kind"] == "rate":
                    spec["tau_s"] = float(self.rate_tau_s)
        self.recording = load_cached(self.path)
        val_rec = load_cached(self.val_path) if self.val_path else None
        self._check(self.recording, val_rec)  # before any work
        self.fs_hz = self.recording.fs_hz
        self.static_rate = static_rate_dps(self.recording, self.static_rate_dps)
        # rejected rows (gyronet.recordings.guard) are lost samples here as everywhere: not fitted, not in the box
        full_x, full_y, accepted = self._full_rate(self.path)
        time_s = self.recording.time_s[accepted]
        self.n_rejected = len(accepted) - int(np.count_nonzero(accepted))
        if self.n_rejected:
            log.warning("%s: %d of %d rows have an impossible temperature (a glitch, gyronet.recordings.guard): left out of "
                        "training and of the trained range", self.path, self.n_rejected, len(accepted))
        if val_rec is not None:
            val_x, val_y, val_accepted = self._full_rate(self.val_path)
            self.train = to_blocks(time_s, full_x, full_y, self.block_s)
            self.val = to_blocks(val_rec.time_s[val_accepted], val_x, val_y, self.block_s)
            self.val_full = (val_rec.time_s[val_accepted], val_x, val_y)
        else:
            train_mask, val_mask = split_by_time(time_s, self.val_fraction, self.n_blocks, self.val_fold)
            # block means never straddle a split edge: average within each side separately
            self.train = to_blocks(time_s[train_mask], full_x[train_mask], full_y[train_mask], self.block_s)
            self.val = to_blocks(time_s[val_mask], full_x[val_mask], full_y[val_mask], self.block_s)
            self.val_full = (time_s[val_mask], full_x[val_mask], full_y[val_mask])
        self.temp_range_c = trained_range_c(self.recording.temp_c, accepted)
        if self.temp_range_c[1] - self.temp_range_c[0] < MIN_TEMP_SPAN_C:  # a glitch gave _check its span
            raise GyronetError(f"{self.path}: the accepted temperatures span {self.temp_range_c[1] - self.temp_range_c[0]:.3g}"
                               f" degC ({self.temp_range_c[0]:.6g} .. {self.temp_range_c[1]:.6g}; {self.n_rejected} "
                               f"glitch row(s) left out); a drift model needs at least {MIN_TEMP_SPAN_C:g} degC of range")
        log.info("training data %s: %d samples at %.3g Hz, %d train / %d validation blocks of %g s",
                 self.path, len(self.recording), self.fs_hz, len(self.train), len(self.val), self.block_s)

    def _check(self, recording: Recording, val_rec: Recording | None) -> None:
        """Refuse, in one line, a record that cannot be trained on: impossible values, too little
        temperature range, too few blocks; from the time stamps alone, before any feature work."""
        for rec in (r for r in (recording, val_rec) if r is not None):
            check_physical(rec)
            check_features_present(rec, self.features)
            warn_timing(rec, self.block_s)
        time_s = recording.time_s
        if val_rec is not None:
            n_train, n_val = (len(block_means(t, t, self.block_s)) for t in (time_s, val_rec.time_s))
        else:
            train, val = split_by_time(time_s, self.val_fraction, self.n_blocks, self.val_fold)
            n_train = len(block_means(time_s[train], time_s[train], self.block_s))
            n_val = len(block_means(time_s[val], time_s[val], self.block_s))
        if val_rec is not None and n_val < MIN_VAL_BLOCKS and n_train >= MIN_TRAIN_BLOCKS:
            raise GyronetError(f"{self.val_path}: too short to validate on ({n_val} blocks of {self.block_s:g} s; "
                               f"at least {MIN_VAL_BLOCKS} are needed)")
        if n_train < MIN_TRAIN_BLOCKS or n_val < MIN_VAL_BLOCKS:
            raise GyronetError(f"{self.path}: too short to train on ({len(recording)} samples over "
                               f"{float(time_s[-1] - time_s[0]):.6g} s: {n_train} training and {n_val} "
                               f"validation blocks of {self.block_s:g} s; at least {MIN_TRAIN_BLOCKS} and "
                               f"{MIN_VAL_BLOCKS} are needed)")
        span_c = float(np.ptp(recording.temp_c))
        if span_c < MIN_TEMP_SPAN_C:
            raise GyronetError(f"{self.path}: the temperature spans {span_c:.3g} degC "
                               f"({float(recording.temp_c.min()):.6g} .. {float(recording.temp_c.max()):.6g}); "
                               f"a drift model needs at least {MIN_TEMP_SPAN_C:g} degC of range")

    def _full_rate(self, path: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Features and targets of the accepted rows at the full rate (computed once per process for a
        given file), and the accepted mask over the file's rows."""
        recording = load_cached(path)
        x, accepted = _features_by_key(_file_key(path), json.dumps(self.features, sort_keys=True), self.fs_hz)
        y = recording.gyro_dps - static_rate_dps(recording, self.static_rate_dps)
        if accepted.all():
            return x, y, accepted
        return x[accepted], y[accepted], accepted


def block_rmse(time_s: np.ndarray, residual: np.ndarray, block_s: float = 60.0) -> np.ndarray:
    """RMS over ``block_s`` blocks of the block-averaged residual, per axis (the contract's metric)."""
    return np.sqrt(np.mean(residual_block_means(time_s, residual, block_s) ** 2, axis=0))


def residual_block_means(time_s: np.ndarray, residual: np.ndarray, block_s: float = 60.0) -> np.ndarray:
    """The ``block_s`` block means that ``block_rmse`` squares, (m, axes).

    Blocks are formed on contiguous runs: a time-block split leaves gaps, and a block never
    straddles one. A block needs half the samples of a full one, the one the median sample lies in:
    where a mask (the trained temperatures, say) flickers, its pieces of a few samples are no 60 s means.
    """
    gaps = np.flatnonzero(np.diff(time_s) > 1.5 * np.median(np.diff(time_s))) + 1
    spans = [(a, b) for a, b in zip([0, *gaps], [*gaps, len(time_s)]) if b - a > 1]
    if not spans:
        return np.empty((0, residual.shape[1]))
    counts = [np.bincount(gap_blocks(time_s[a:b], block_s)) for a, b in spans]
    full = float(np.median(np.concatenate([np.repeat(c, c) for c in counts])))
    pieces = [block_means(residual[a:b], time_s[a:b], block_s, full_count=full) for a, b in spans]
    kept = [p for p in pieces if len(p)]
    return np.concatenate(kept) if kept else np.empty((0, residual.shape[1]))


__all__ = ["Blocks", "DriftData", "TrainingData", "block_rmse", "check_features_present", "check_physical", "clear_caches",
           "featurize", "residual_block_means", "static_rate_dps", "to_blocks", "time_blocks", "trained_range_c"]
