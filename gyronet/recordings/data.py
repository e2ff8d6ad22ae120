"""Recordings (CONTRACT.md section 1): load with clear errors, write, split by time block.

A recording is a CSV with optional ``# key=value`` metadata lines, a header row and one sample a
row. Every numeric column is kept; the ones gyronet does not know are auxiliary channels.
"""
from __future__ import annotations

import hashlib
import io
import logging
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Mapping, Sequence

import numpy as np
import pandas as pd

from gyronet.atomic import atomic_output
from gyronet.recordings.csvtable import parse_table
from gyronet.errors import RecordingError

log = logging.getLogger(__name__)

AXES = ("x", "y", "z")
GYRO_COLUMNS = tuple(f"gyro_{a}_dps" for a in AXES)
REQUIRED_COLUMNS = ("time_s", "temp_c") + GYRO_COLUMNS
ALLAN_COLUMNS = ("time_s",) + GYRO_COLUMNS
TRUTH_SUFFIX = ".truth.csv"
# a declared ``# fs_hz`` may differ this much from the median sample interval (clock tolerance)
FS_TOLERANCE = 0.05
# an interval this many times the median one is a break in the record, not jitter
BREAK_FACTOR = 5.0
# an interval over this many sample periods is a gap, lost samples (CONTRACT.md 1): the features bridge or
# restart there, Allan analysis takes the longest stretch without one, importers count what was lost
GAP_FACTOR = 1.5


@dataclass
class Recording:
    """One static gyro recording: every numeric column by name, plus the metadata lines."""

    columns: dict[str, np.ndarray]
    meta: dict[str, str] = field(default_factory=dict)
    path: str | None = None
    lines: np.ndarray | None = None  # the file line of each row, when loaded from a CSV
    dropped: dict[str, str] = field(default_factory=dict)  # auxiliary columns not loaded, and why
    cut_rows: int = 0  # an unterminated last line cut short: dropped with a warning (gyronet.recordings.csvtable.tail)
    dropped_lines: dict[str, int] = field(default_factory=dict)  # left out by bad_lines="drop", by reason

    def __len__(self) -> int:
        return len(self.time_s)

    @property
    def time_s(self) -> np.ndarray:
        return self.columns["time_s"]

    @property
    def temp_c(self) -> np.ndarray:
        return self.columns["temp_c"]

    @property
    def gyro_dps(self) -> np.ndarray:
        """Angular rate, shape (n, 3), deg/s."""
        return np.column_stack([self.columns[c] for c in GYRO_COLUMNS])

    @property
    def aux_columns(self) -> list[str]:
        """Columns that are neither required nor gyro: candidates for the diagnosis."""
        return [c for c in self.columns if c not in REQUIRED_COLUMNS]

    @property
    def fs_hz(self) -> float:
        """Sampling rate from the ``fs_hz`` metadata, else from the median sample interval.

        A declared rate must be a positive number within ``FS_TOLERANCE`` of the median interval's:
        a wrong one would scale every rate feature silently.
        """
        measured = float(1.0 / np.median(np.diff(self.time_s))) if len(self) > 1 else float("nan")
        if "fs_hz" not in self.meta:
            return measured
        text = str(self.meta["fs_hz"])
        try:
            declared = float(text)
        except ValueError:
            declared = float("nan")
        if not (np.isfinite(declared) and declared > 0):
            raise RecordingError(f"{self.path}: # fs_hz={text[:40]} is not a positive number of Hz")
        if np.isfinite(measured) and abs(declared - measured) > FS_TOLERANCE * measured:
            raise RecordingError(f"{self.path}: # fs_hz={text[:40]} disagrees with the samples (median "
                                 f"interval {1.0 / measured:.6g} s, i.e. {measured:.6g} Hz); correct or "
                                 "remove the fs_hz line")
        return declared

    def checksum(self, names: Sequence[str] | None = None) -> str:
        """sha256 of the numeric content (of the columns ``names`` only, if given), so a bundle can name the
        data it was trained on."""
        digest = hashlib.sha256()
        for name in sorted(self.columns if names is None else names):
            digest.update(name.encode())
            digest.update(np.ascontiguousarray(self.columns[name], dtype=np.float64).tobytes())
        return digest.hexdigest()

    def slice(self, index: slice | np.ndarray) -> "Recording":
        """A sub-recording (a time block), sharing metadata."""
        lines = None if self.lines is None else self.lines[index]
        return Recording({k: v[index] for k, v in self.columns.items()}, dict(self.meta), self.path, lines,
                         dict(self.dropped))

    def line_of(self, row: int) -> str:
        """How an error names a row: its file line when known."""
        return f"line {self.lines[row]}" if self.lines is not None else f"row {row + 1}"


def load_recording(path: str | os.PathLike, required: Sequence[str] = REQUIRED_COLUMNS, *,
                   delimiter: str | None = ",", decimal: str | None = ".", bad_lines: str = "refuse") -> Recording:
    """Load and validate a recording.

    Parameters
    ----------
    path
        CSV file, plain or gzip-compressed (``.csv``, ``.csv.gz``); UTF-8, or UTF-16 with a BOM.
    required
        Columns that must be finite numbers in every row; by default those of CONTRACT.md
        section 1. Another column that is not (text, an empty cell, NaN) is dropped with a warning
        and named in ``Recording.dropped``.
    delimiter, decimal
        The contract's ``,`` and ``.``; None sniffs them (``;``, tab, decimal commas), for import.
    bad_lines
        ``refuse`` a file with a malformed line, or ``drop`` such lines (counted in ``Recording.dropped_lines``).

    Returns
    -------
    Recording
        All usable numeric columns as float64 arrays of equal length.

    Raises
    ------
    RecordingError
        With one line naming the file, the line or column, and what is wrong.
    """
    path = Path(path)
    if path.suffix.lower() in (".bag", ".db3", ".mcap", ".ulg") or (path / "metadata.yaml").is_file():
        raise RecordingError(f"{path}: a ROS bag or PX4 log, not a recording: convert it first "
                             f"(python scripts/convert.py input={path} output=F.csv)")
    if path.is_dir():
        raise RecordingError(f"{path}: a folder, not a recording (give a .csv or .csv.gz file in it)")
    if not path.is_file():
        raise RecordingError(f"{path}: no such file")
    table = parse_table(path, tuple(dict.fromkeys(("time_s", *required))), delimiter, decimal, bad_lines)
    recording = Recording(table.columns, table.meta, str(path), table.lines, table.dropped, table.cut_rows,
                          table.dropped_lines)
    if "fs_hz" in recording.meta:
        recording.fs_hz  # noqa: B018 - refuses a declared rate that is not the recording's
    return recording


def write_recording(path: str | os.PathLike, columns: Mapping[str, Iterable[float]],
                    meta: Mapping[str, object] | None = None, float_format: str = "%.9g") -> Path:
    """Write columns and ``# key=value`` lines as a CONTRACT.md CSV, whole or not at all; gzip for ``.gz``."""
    path = Path(path)
    frame = pd.DataFrame({k: np.asarray(v) for k, v in columns.items()})
    buffer = io.StringIO()
    for key, value in (meta or {}).items():
        buffer.write(f"# {key}={value}\n")
    frame.to_csv(buffer, index=False, float_format=float_format, lineterminator="\n")
    with atomic_output(path) as tmp:
        tmp.write_text(buffer.getvalue(), encoding="utf-8")
    return path


def truth_path(path: str | os.PathLike) -> Path:
    """Where the simulator writes the ground truth of ``path``: ``F.csv`` -> ``F.truth.csv`` (``.csv.gz`` alike)."""
    path, gz = Path(path), ".gz" if str(path).endswith(".csv.gz") else ""
    name = path.name[:-4 - len(gz)] if path.name.endswith(".csv" + gz) else path.name
    return path.with_name(name + TRUTH_SUFFIX + gz)


def load_truth(path: str | os.PathLike) -> Recording:
    """Load the ground truth written beside a simulated recording."""
    return load_recording(truth_path(path), required=("time_s",))


def time_blocks(time_s: np.ndarray, block_s: float) -> np.ndarray:
    """Index of the ``block_s``-long time block each sample falls in, counted from the first sample."""
    return np.floor((time_s - time_s[0]) / block_s).astype(np.int64)


def gap_blocks(time_s: np.ndarray, block_s: float) -> np.ndarray:
    """Index of the ``block_s`` time block of each sample; the grid restarts after every gap longer
    than a block, so that a block never straddles a break in the record and the samples after one
    fill whole blocks."""
    time_s = np.asarray(time_s, dtype=np.float64)
    if len(time_s) == 0:
        return np.empty(0, dtype=np.int64)
    segment = np.concatenate([[0], np.cumsum(np.diff(time_s) > block_s)])
    starts = np.flatnonzero(np.diff(np.concatenate([[-1], segment])))
    local = np.floor((time_s - time_s[starts][segment]) / block_s).astype(np.int64)
    # number the blocks of each segment after those of the segments before it
    offsets = np.concatenate([[0], np.cumsum(np.maximum.reduceat(local, starts) + 1)[:-1]])
    return offsets[segment] + local


def block_means(values: np.ndarray, time_s: np.ndarray, block_s: float = 60.0,
                min_fill: float = 0.5, full_count: float | None = None) -> np.ndarray:
    """Average ``values`` (n,) or (n, k) over ``block_s`` time blocks; drop blocks under ``min_fill`` full.

    Used for the contract's residual metric (60 s blocks) and to decimate training data, since the
    thermal drift has no content a 60 s average would hide. Blocks restart after a gap longer than
    a block (``gap_blocks``); a block that a shorter gap cuts is averaged over the samples it has.
    A full block holds ``full_count`` samples (None: the median block's count). Empty input gives
    an empty result of the same trailing shape.
    """
    values = np.asarray(values, dtype=np.float64)
    tail = values.shape[1:]
    if len(values) == 0:
        return np.empty((0,) + tail)
    flat = values.reshape(len(values), int(np.prod(tail, dtype=np.int64)))
    block = gap_blocks(time_s, block_s)
    counts = np.bincount(block)
    sums = np.stack([np.bincount(block, weights=flat[:, j], minlength=len(counts))
                     for j in range(flat.shape[1])], axis=1)
    expected = max(1.0, float(np.median(counts[counts > 0]) if full_count is None else full_count))
    keep = counts >= min_fill * expected
    means = sums[keep] / counts[keep, None]
    return means.reshape((-1,) + tail)


def recorded_time_s(time_s: np.ndarray) -> np.ndarray:
    """Time since the first sample with every break (an interval over ``BREAK_FACTOR`` median
    intervals) shortened to one median interval; equal to ``time_s - time_s[0]`` without breaks."""
    time_s = np.asarray(time_s, dtype=np.float64)
    if len(time_s) < 2:
        return np.zeros(len(time_s))
    step_s = np.diff(time_s)
    median_s = float(np.median(step_s))
    removed_s = np.where(step_s > BREAK_FACTOR * median_s, step_s - median_s, 0.0)
    return time_s - time_s[0] - np.concatenate([[0.0], np.cumsum(removed_s)])


_TIMING_WARNED: set = set()


def warn_timing(recording: Recording, block_s: float = 60.0) -> None:
    """Warn once per file when its stamps look wrong for training: a rate under 0.1 Hz (time_s in
    milliseconds?), or no stretch without a break as long as a block (bursts, as psim-tvc's 5 s)."""
    time_s = recording.time_s
    if recording.path in _TIMING_WARNED or len(time_s) < 3:
        return
    _TIMING_WARNED.add(recording.path)
    step_s = np.diff(time_s)
    breaks = np.flatnonzero(step_s > BREAK_FACTOR * np.median(step_s))
    edges = np.concatenate([[0], breaks + 1, [len(time_s)]])
    longest_s = max(float(time_s[b - 1] - time_s[a]) for a, b in zip(edges[:-1], edges[1:]))
    if recording.fs_hz < 0.1:
        log.warning("%s: %.3g Hz, a sample every %.3g s: if time_s is in milliseconds, the record is 1000x too "
                    "long and every rate and lag wrong; time_s must be seconds", recording.path, recording.fs_hz,
                    1.0 / recording.fs_hz)
    elif longest_s < block_s:
        log.warning("%s: no stretch without a break reaches %g s (the longest is %.3g s): its %g s blocks are "
                    "bursts, and the figures and lags chosen on them mean little; record continuously",
                    recording.path, block_s, longest_s, block_s)


def fold_count(val_fraction: float) -> int:
    """How many interleaved validation sets ``split_by_time`` has for ``val_fraction`` (1 in k held out)."""
    return max(2, int(round(1.0 / val_fraction)))


def held_out_span(val_fraction: float, fold: int | None = None) -> tuple[int, int]:
    """``split_by_time``'s rule: span s is held out when ``s % k == which``; (k, which)."""
    k = fold_count(val_fraction)
    return k, k // 2 if fold is None else fold % k


def split_by_time(time_s: np.ndarray, val_fraction: float = 0.2, n_blocks: int = 10,
                  fold: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Train and validation masks from contiguous time blocks, never random samples.

    The record is cut into ``n_blocks`` equal spans of recorded time (a break longer than
    ``BREAK_FACTOR`` sample intervals counts as one interval, so that no span falls in a break and
    comes out empty) and every k-th span (k = 1 / ``val_fraction``), starting with span ``fold``
    (default: the centre offset, k // 2; ``held_out_span``), is held out, so that validation covers
    the whole temperature history; folds 0 .. k-1 together hold out every span once.

    Returns
    -------
    train, val
        Boolean masks of shape (n,).
    """
    if not 0.0 < val_fraction < 1.0:
        raise ValueError(f"val_fraction must be in (0, 1), got {val_fraction}")
    recorded_s = recorded_time_s(time_s)
    if len(time_s) < 2 or recorded_s[-1] <= 0:
        return np.ones(len(time_s), dtype=bool), np.zeros(len(time_s), dtype=bool)
    span_s = recorded_s[-1] / n_blocks * (1 + 1e-12)
    block = np.floor(recorded_s / span_s).astype(np.int64)
    step, which = held_out_span(val_fraction, fold)
    val = (block % step) == which
    return ~val, val
