"""Recordings (CONTRACT.md section 1): load with clear errors, write, split by time block.

A recording is a CSV with optional ``# key=value`` metadata lines, a header row and one sample a
row. Every numeric column is kept; the ones gyronet does not know are auxiliary channels.
"""
from __future__ import annotations

import csv
import hashlib
import io
import logging
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Mapping, Sequence

import numpy as np
import pandas as pd

from gyronet.errors import RecordingError

log = logging.getLogger(__name__)

AXES = ("x", "y", "z")
GYRO_COLUMNS = tuple(f"gyro_{a}_dps" for a in AXES)
REQUIRED_COLUMNS = ("time_s", "temp_c") + GYRO_COLUMNS
ALLAN_COLUMNS = ("time_s",) + GYRO_COLUMNS
TRUTH_SUFFIX = ".truth.csv"


@dataclass
class Recording:
    """One static gyro recording: every numeric column by name, plus the metadata lines."""

    columns: dict[str, np.ndarray]
    meta: dict[str, str] = field(default_factory=dict)
    path: str | None = None

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
        """Sampling rate from the ``fs_hz`` metadata, else from the median sample interval."""
        if "fs_hz" in self.meta:
            return float(self.meta["fs_hz"])
        return float(1.0 / np.median(np.diff(self.time_s))) if len(self) > 1 else float("nan")

    def checksum(self) -> str:
        """sha256 of the numeric content, so a bundle can name the data it was trained on."""
        digest = hashlib.sha256()
        for name in sorted(self.columns):
            digest.update(name.encode())
            digest.update(np.ascontiguousarray(self.columns[name], dtype=np.float64).tobytes())
        return digest.hexdigest()

    def slice(self, index: slice | np.ndarray) -> "Recording":
        """A sub-recording (a time block), sharing metadata."""
        return Recording({k: v[index] for k, v in self.columns.items()}, dict(self.meta), self.path)


def _read_preamble(path: Path) -> tuple[dict[str, str], int, list[str]]:
    """Read the ``#`` metadata lines and the header; return meta, header line number, names."""
    meta: dict[str, str] = {}
    opener = _open_text(path)
    with opener as handle:
        for line_no, line in enumerate(handle, start=1):
            if "\x00" in line:
                raise RecordingError(f"{path}: not a CSV file (binary content on line {line_no})")
            stripped = line.strip().lstrip("\ufeff")
            if not stripped:
                continue
            if stripped.startswith("#"):
                key, sep, value = stripped[1:].partition("=")
                if sep:
                    meta[key.strip()] = value.strip()
                continue
            names = [n.strip() for n in next(csv.reader([stripped]))]
            return meta, line_no, names
    raise RecordingError(f"{path}: empty file (no header row)")


def _open_text(path: Path):
    if path.suffix == ".gz":
        import gzip

        return gzip.open(path, "rt", encoding="utf-8", errors="strict")
    return open(path, "r", encoding="utf-8", errors="strict", newline="")


def load_recording(path: str | os.PathLike, required: Sequence[str] = REQUIRED_COLUMNS) -> Recording:
    """Load and validate a recording.

    Parameters
    ----------
    path
        CSV file (``.csv`` or ``.csv.gz``).
    required
        Columns that must be present; by default those of CONTRACT.md section 1.

    Returns
    -------
    Recording
        All numeric columns as float64 arrays of equal length.

    Raises
    ------
    RecordingError
        With one line naming the file, the line or column, and what is wrong.
    """
    path = Path(path)
    if not path.is_file():
        raise RecordingError(f"{path}: no such file")
    try:
        meta, header_line, names = _read_preamble(path)
    except UnicodeDecodeError:
        raise RecordingError(f"{path}: not a CSV file (not UTF-8 text)") from None
    _check_header(path, names, required)
    try:
        frame = pd.read_csv(path, skiprows=header_line - 1, comment=None, dtype=np.float64,
                            skip_blank_lines=True, encoding="utf-8-sig")
    except ValueError as err:  # a non-numeric cell, or a malformed row
        frame = _read_as_text(path, header_line, err)
        _raise_first_bad_cell(path, frame, header_line)
        raise  # pragma: no cover - _raise_first_bad_cell always raises for a text frame
    frame.columns = names
    if frame.empty:
        raise RecordingError(f"{path}: no samples after the header")
    columns = {name: frame[name].to_numpy(dtype=np.float64, copy=False) for name in names}
    _check_finite(path, columns, header_line)
    _check_time(path, columns["time_s"], header_line)
    return Recording(columns, meta, str(path))


def _check_header(path: Path, names: list[str], required: Sequence[str]) -> None:
    if len(names) < 2:
        raise RecordingError(f"{path}: not a CSV recording (first line {','.join(names)[:60]!r} has no commas)")
    duplicates = sorted({n for n in names if names.count(n) > 1})
    if duplicates:
        raise RecordingError(f"{path}: duplicate column {duplicates[0]!r} in the header")
    if "" in names:
        raise RecordingError(f"{path}: column {names.index('') + 1} of the header has no name")
    missing = [c for c in required if c not in names]
    if missing:
        raise RecordingError(f"{path}: missing required column(s) {', '.join(missing)}"
                             f" (header has {', '.join(names)})")


def _read_as_text(path: Path, header_line: int, err: Exception) -> pd.DataFrame:
    """Re-read as strings to find where a fast numeric parse failed."""
    try:
        return pd.read_csv(path, skiprows=header_line - 1, dtype=str, keep_default_na=False,
                           encoding="utf-8-sig")
    except pd.errors.ParserError as parse_err:
        # pandas says "Expected 8 fields in line 12, saw 9"; its line counts from the header.
        text = str(parse_err).strip().splitlines()[-1]
        raise RecordingError(f"{path}: malformed row ({text}, counting from the header)") from None
    except ValueError:
        raise RecordingError(f"{path}: not a CSV recording ({err})") from None


def _raise_first_bad_cell(path: Path, frame: pd.DataFrame, header_line: int) -> None:
    first: tuple[int, str, str] | None = None
    for name in frame.columns:
        text = frame[name].astype(str).str.strip()
        numeric = pd.to_numeric(text, errors="coerce")
        bad = np.flatnonzero(numeric.isna().to_numpy() & (text != "").to_numpy()
                             & ~text.str.lower().isin(["nan", "inf", "-inf", "+inf"]).to_numpy())
        if bad.size and (first is None or bad[0] < first[0]):
            first = (int(bad[0]), str(name), text.iloc[bad[0]])
    if first is None:
        raise RecordingError(f"{path}: could not parse the file as numeric CSV")
    row, name, value = first
    raise RecordingError(f"{path}: line {header_line + 1 + row}: column {name!r}: "
                         f"non-numeric value {value[:40]!r}")


def _check_finite(path: Path, columns: Mapping[str, np.ndarray], header_line: int) -> None:
    for name, values in columns.items():
        bad = np.flatnonzero(~np.isfinite(values))
        if bad.size:
            what = "empty cell or NaN" if np.isnan(values[bad[0]]) else "infinite value"
            raise RecordingError(f"{path}: line {header_line + 1 + int(bad[0])}: column {name!r}: {what}"
                                 f" ({bad.size} such cell(s) in this column)")


def _check_time(path: Path, time_s: np.ndarray, header_line: int) -> None:
    bad = np.flatnonzero(np.diff(time_s) <= 0)
    if bad.size:
        row = int(bad[0]) + 1
        raise RecordingError(f"{path}: line {header_line + 1 + row}: time_s {float(time_s[row])!r} does not "
                             f"increase (previous {float(time_s[row - 1])!r})")


def write_recording(path: str | os.PathLike, columns: Mapping[str, Iterable[float]],
                    meta: Mapping[str, object] | None = None, float_format: str = "%.9g") -> Path:
    """Write columns (and ``# key=value`` metadata lines) as a CONTRACT.md CSV."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    frame = pd.DataFrame({k: np.asarray(v) for k, v in columns.items()})
    buffer = io.StringIO()
    for key, value in (meta or {}).items():
        buffer.write(f"# {key}={value}\n")
    frame.to_csv(buffer, index=False, float_format=float_format, lineterminator="\n")
    path.write_text(buffer.getvalue(), encoding="utf-8")
    return path


def truth_path(path: str | os.PathLike) -> Path:
    """Where the simulator writes the ground truth of ``path``: ``F.csv`` -> ``F.truth.csv``."""
    path = Path(path)
    name = path.name[:-4] if path.name.endswith(".csv") else path.name
    return path.with_name(name + TRUTH_SUFFIX)


def load_truth(path: str | os.PathLike) -> Recording:
    """Load the ground truth written beside a simulated recording."""
    return load_recording(truth_path(path), required=("time_s",))


def time_blocks(time_s: np.ndarray, block_s: float) -> np.ndarray:
    """Index of the ``block_s``-long time block each sample falls in, counted from the first sample."""
    return np.floor((time_s - time_s[0]) / block_s).astype(np.int64)


def block_means(values: np.ndarray, time_s: np.ndarray, block_s: float = 60.0,
                min_fill: float = 0.5) -> np.ndarray:
    """Average ``values`` (n,) or (n, k) over ``block_s`` time blocks; drop blocks under ``min_fill`` full.

    Used for the contract's residual metric (60 s blocks) and to decimate training data, since the
    thermal drift has no content a 60 s average would hide.
    """
    values = np.asarray(values, dtype=np.float64)
    flat = values.reshape(len(values), -1)
    block = time_blocks(time_s, block_s)
    counts = np.bincount(block)
    sums = np.stack([np.bincount(block, weights=flat[:, j], minlength=len(counts))
                     for j in range(flat.shape[1])], axis=1)
    expected = max(1.0, np.median(counts[counts > 0]))
    keep = counts >= min_fill * expected
    means = sums[keep] / counts[keep, None]
    return means.reshape((-1,) + values.shape[1:])


def fold_count(val_fraction: float) -> int:
    """How many interleaved validation sets ``split_by_time`` has for ``val_fraction`` (1 in k held out)."""
    return max(2, int(round(1.0 / val_fraction)))


def split_by_time(time_s: np.ndarray, val_fraction: float = 0.2, n_blocks: int = 10,
                  fold: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Train and validation masks from contiguous time blocks, never random samples.

    The record is cut into ``n_blocks`` equal spans of time and every k-th span (k = 1 /
    ``val_fraction``), starting with span ``fold`` (default: the centre offset, k // 2), is held
    out, so that validation covers the whole temperature history; folds 0 .. k-1 together hold
    out every span once (cross-validation).

    Returns
    -------
    train, val
        Boolean masks of shape (n,).
    """
    if not 0.0 < val_fraction < 1.0:
        raise ValueError(f"val_fraction must be in (0, 1), got {val_fraction}")
    span_s = (time_s[-1] - time_s[0]) / n_blocks * (1 + 1e-12)
    block = time_blocks(time_s, span_s)
    step = fold_count(val_fraction)
    val = (block % step) == (step // 2 if fold is None else fold % step)
    return ~val, val
