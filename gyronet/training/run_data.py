"""A campaign's runs one by one (loaded, featurised, blocked), below ``runs.RunsData`` so runs.py stays short."""
from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from gyronet.errors import GyronetError
from gyronet.recordings.data import REQUIRED_COLUMNS, Recording, warn_timing
from gyronet.training.dataset import (
    MIN_TEMP_SPAN_C,
    MIN_VAL_BLOCKS,
    Blocks,
    _features_by_key,
    _file_key,
    check_features_present,
    check_physical,
    load_cached,
    static_rate_dps,
    to_blocks,
    trained_range_c,
)

log = logging.getLogger(__name__)


@dataclass
class Run:
    """One recording of a campaign: its causal features and drift targets at the full rate."""

    recording: Recording
    name: str
    features: np.ndarray  # (n, k), from a fresh causal extractor
    targets: np.ndarray  # (n, 3) gyro minus the static rate, deg/s
    index: int  # position in the campaign's list of runs
    path: str
    # rows the guard accepted (gyronet.recordings.guard); features and targets hold those rows only. None: all
    accepted: np.ndarray | None = None

    @property
    def time_s(self) -> np.ndarray:
        return self.recording.time_s if self.accepted is None else self.recording.time_s[self.accepted]

    @property
    def temp_c(self) -> np.ndarray:
        """The accepted temperature readings: a rejected glitch is in no range and no score."""
        return self.recording.temp_c if self.accepted is None else self.recording.temp_c[self.accepted]

    @property
    def temp_range_c(self) -> tuple[float, float]:
        return trained_range_c(self.temp_c, np.ones(len(self.temp_c), dtype=bool))

    def blocks(self, block_s: float) -> Blocks:
        """Block means within this run only."""
        return to_blocks(self.time_s, self.features, self.targets, block_s)

    def describe(self) -> dict[str, Any]:
        """What ``meta.json`` says about the run."""
        return {"name": self.name, "path": self.path, "sha256": self.recording.checksum(),
                "n_samples": len(self.recording), "temp_range_c": list(self.temp_range_c)}


def run_name(path: str) -> str:
    """A run's name: its file name without ``.csv`` / ``.csv.gz``."""
    name = Path(path).name
    for suffix in (".gz", ".csv"):
        name = name[:-len(suffix)] if name.endswith(suffix) else name
    return name


def load_runs(paths: Sequence[str], specs: Sequence[dict], static_rate: Sequence[float] | None = None) -> list[Run]:
    """Load each recording and compute its features from a fresh extractor at the first run's rate."""
    if len(set(map(str, paths))) != len(paths):
        raise GyronetError(f"data.paths names a recording twice: {list(paths)}")
    recordings = [load_cached(str(p)) for p in paths]
    first_with: dict[str, str] = {}
    for path, rec in zip(paths, recordings):  # a copy under another name would be held out against itself
        # the samples every recording has: a re-export that adds or drops an auxiliary column is the same run
        first = first_with.setdefault(rec.checksum(REQUIRED_COLUMNS), str(path))
        if first != str(path):
            raise GyronetError(f"data.paths: {path} holds the same samples as {first}; each run must be a recording "
                               "of its own (a copy would score its fold in sample)")
    fs_hz = recordings[0].fs_hz
    for rec in recordings[1:]:
        if abs(rec.fs_hz - fs_hz) > 0.01 * fs_hz:
            raise GyronetError(f"{rec.path}: sampled at {rec.fs_hz:.4g} Hz, but {recordings[0].path} at "
                               f"{fs_hz:.4g} Hz: the runs of one training need one rate")
    span_c = max(float(r.temp_c.max()) for r in recordings) - min(float(r.temp_c.min()) for r in recordings)
    if span_c < MIN_TEMP_SPAN_C:
        raise GyronetError(f"data.paths: the runs' temperatures span {span_c:.3g} degC together; a drift model "
                           f"needs at least {MIN_TEMP_SPAN_C:g} degC of range")
    specs_json = json.dumps([dict(s) for s in specs], sort_keys=True)
    runs, names = [], set()
    for index, (path, rec) in enumerate(zip(paths, recordings)):
        check_physical(rec)  # before any feature work, as for one recording
        check_features_present(rec, specs)
        warn_timing(rec)
        name = run_name(str(path))
        name = name if name not in names else f"{name}_{index}"
        names.add(name)
        features, accepted = _features_by_key(_file_key(str(path)), specs_json, fs_hz)
        targets = rec.gyro_dps - static_rate_dps(rec, static_rate)
        if accepted.all():
            runs.append(Run(rec, name, features, targets, index, str(path)))
            continue
        log.warning("%s: %d of %d rows have an impossible temperature (a glitch, gyronet.recordings.guard): left out of "
                    "training and of the trained range", path, int(np.count_nonzero(~accepted)), len(accepted))
        runs.append(Run(rec, name, features[accepted], targets[accepted], index, str(path), accepted))
    span_c = max(float(r.temp_c.max()) for r in runs) - min(float(r.temp_c.min()) for r in runs)
    if span_c < MIN_TEMP_SPAN_C:  # a glitch row gave the check above its span
        raise GyronetError(f"data.paths: the runs' accepted temperatures span {span_c:.3g} degC together; a drift "
                           f"model needs at least {MIN_TEMP_SPAN_C:g} degC of range")
    return runs


def check_long_enough(runs: Sequence[Run], startup_s: float, block_s: float) -> None:
    """Every run, held out, must leave blocks to score after its start-up window (``data.val_startup_s``)."""
    for run in runs:
        duration_s = float(run.time_s[-1] - run.time_s[0]) if len(run.time_s) else 0.0
        if startup_s > 0 and duration_s < startup_s + MIN_VAL_BLOCKS * block_s:
            raise GyronetError(f"{run.path}: {duration_s:.0f} s long; held out, a run is scored after its first "
                               f"data.val_startup_s={startup_s:g} s (as deployed with startup.still_s), which leaves "
                               f"fewer than {MIN_VAL_BLOCKS} blocks of {block_s:g} s: give longer runs, or "
                               "data.val_startup_s=0")


@dataclass
class RunBlocks(Blocks):
    """Blocks of several runs side by side, with the position (among the training runs) of each block's run."""

    run: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))


def stack_runs(runs: Sequence[Run], block_s: float) -> RunBlocks:
    """Every run's blocks of ``block_s`` s, in run order, each labelled with its run's position."""
    parts = [r.blocks(block_s) for r in runs]
    return RunBlocks(np.concatenate([b.x for b in parts]), np.concatenate([b.y for b in parts]),
                     np.concatenate([b.time_s for b in parts]),
                     np.concatenate([np.full(len(b), i, dtype=np.int64) for i, b in enumerate(parts)]))


def scored_after_startup(time_s: np.ndarray, residual: np.ndarray, startup_s: float
                         ) -> tuple[np.ndarray, np.ndarray]:
    """What ``startup.still_s`` leaves of ``residual``: the rows after the first ``startup_s`` s (the window's own,
    zero-mean by construction, are not scored) and the residual less its mean over that window."""
    window = time_s < time_s[0] + startup_s
    return ~window, residual - residual[window].mean(0) if window.any() else residual
