"""Apply a bundle to a whole recording and write the compensated CSV (the offline path)."""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from gyronet.compensator import Compensated, Compensator
from gyronet.data import AXES, GYRO_COLUMNS, Recording, load_recording, write_recording
from gyronet.fastcsv import write_csv

log = logging.getLogger(__name__)


def output_columns(time_s: np.ndarray, temp_c: np.ndarray, out: Compensated) -> dict[str, np.ndarray]:
    """The columns of a compensated file, shared by the offline and live writers."""
    columns = {"time_s": time_s}
    for i, name in enumerate(GYRO_COLUMNS):
        columns[name] = out.rate_dps[:, i]
    columns["temp_c"] = temp_c
    columns["out_of_range"] = out.out_of_range.astype(np.int8)
    return columns


def write_compensated(path: str | Path, columns: dict[str, np.ndarray], bundle_dir: str | Path) -> Path:
    """Write a compensated file: 12 significant digits of each column's largest value (the
    vectorised writer), or pandas' ``%.12g`` per value if a column is not finite."""
    meta = {"compensated_by": Path(bundle_dir).resolve()}
    if all(np.isfinite(v).all() for v in columns.values()):
        return write_csv(path, columns, meta, significant=12)
    return write_recording(path, columns, meta, float_format="%.12g")


def compensate_recording(compensator: Compensator, recording: Recording) -> Compensated:
    """Compensate a whole recording from a fresh state (as a stream that starts with its first sample)."""
    compensator.check_columns(recording.columns, source=str(recording.path))
    compensator.reset()
    return compensator.process(recording.columns)


def compensate_file(bundle_dir: str | Path, input_path: str | Path, output_path: str | Path,
                    startup: Mapping[str, Any] | None = None) -> dict[str, int]:
    """``compensate.py``: read, compensate, write; return counts for the log. ``startup``: ``use_startup`` options."""
    compensator = Compensator.load(bundle_dir)
    compensator.use_startup(**dict(startup or {}))
    recording = load_recording(input_path)
    out = compensate_recording(compensator, recording)
    if compensator.startup is not None:
        compensator.startup.require_done(str(input_path))
    write_compensated(output_path, output_columns(recording.time_s, recording.temp_c, out), bundle_dir)
    n_oor = int(out.out_of_range.sum())
    if n_oor:
        low, high = compensator.temp_range_c
        log.warning("%d of %d samples outside the trained temperature range [%.2f, %.2f] degC: flagged "
                    "in column out_of_range; the model holds its edge value there", n_oor, len(recording), low, high)
    log.info("compensated %d samples (%s) -> %s", len(recording), ", ".join(AXES), output_path)
    return {"n_samples": len(recording), "n_out_of_range": n_oor}
