"""Apply a bundle to a whole recording and write the compensated CSV (the offline path)."""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from gyronet.bundle.compensator import Compensated, Compensator
from gyronet.bundle.startup import StartupMotionError
from gyronet.recordings.data import AXES, GYRO_COLUMNS, Recording, load_recording, write_recording
from gyronet.recordings.guard import check_temperatures
from gyronet.atomic import atomic_output, refuse_overwriting
from gyronet.recordings.fastcsv import write_csv

log = logging.getLogger(__name__)

# 13 digits: half a unit of the 13th is at most 5e-13 of the value, inside the 1e-12 round trip
SIGNIFICANT_DIGITS = 13
SIGMA_COLUMNS = [f"drift_sigma_{a}_dps" for a in AXES]  # CONTRACT.md section 3
STILL_S_KEY = "startup_still_s"  # the output's # line naming the start-up window it was compensated with


def output_columns(time_s: np.ndarray, temp_c: np.ndarray, out: Compensated) -> dict[str, np.ndarray]:
    """The columns of a compensated file, shared by the offline and live writers.

    ``bad_input`` (int8) marks rows whose temperature or gyro reading was impossible (a glitch kept
    out of the filters); ``out_of_range`` those outside the trained temperature range;
    ``drift_sigma_*_dps`` is the 1-sigma error bar of the removed drift (``gyronet.model.error_bar``; NaN
    for a bundle without one).
    """
    columns = {"time_s": time_s}
    for i, name in enumerate(GYRO_COLUMNS):
        columns[name] = out.rate_dps[:, i]
    columns["temp_c"] = temp_c
    columns["out_of_range"] = out.out_of_range.astype(np.int8)
    bad_input = np.zeros(len(time_s), dtype=bool) if out.bad_input is None else out.bad_input
    columns["bad_input"] = bad_input.astype(np.int8)
    sigma = np.full((len(time_s), 3), np.nan) if out.drift_sigma_dps is None else out.drift_sigma_dps
    for i, name in enumerate(SIGMA_COLUMNS):
        columns[name] = sigma[:, i]
    return columns


def compensated_meta(bundle_dir: str | Path, still_s: float = 0.0, static_rate_dps=None) -> dict[str, object]:
    """A compensated file's ``#`` lines: the bundle, the start-up window (for ``allan.py``'s ``still_s``) and
    the true rate of a still test that stays in the output (the Earth's: ``allan.py`` holds the rate against it)."""
    meta: dict[str, object] = {"compensated_by": Path(bundle_dir).resolve()}
    if still_s:
        still_s = float(still_s)  # every digit: allan.py starts exactly where the offset did
        meta[STILL_S_KEY] = str(int(still_s)) if still_s.is_integer() else repr(still_s)
    if isinstance(static_rate_dps, str):  # a recording's own # line, passed on as it is
        meta["static_rate_dps"] = static_rate_dps.strip()
    elif static_rate_dps is not None and np.any(np.asarray(static_rate_dps, dtype=np.float64)):
        meta["static_rate_dps"] = ",".join(repr(float(v)) for v in static_rate_dps)
    return meta


def write_compensated(path: str | Path, columns: dict[str, np.ndarray], bundle_dir: str | Path,
                      still_s: float = 0.0, static_rate_dps=None) -> Path:
    """Write a compensated file whole or not at all (:func:`gyronet.atomic.atomic_output`): 13
    significant digits of every value, so any value reads back within 1e-12 relative (the
    vectorised writer), or pandas' ``%.13g`` per value if a column is not finite."""
    meta = compensated_meta(bundle_dir, still_s, static_rate_dps)
    if all(np.isfinite(v).all() for v in columns.values()):
        return write_csv(path, columns, meta, significant=SIGNIFICANT_DIGITS)
    with atomic_output(path) as tmp:
        write_recording(tmp, columns, meta, float_format=f"%.{SIGNIFICANT_DIGITS}g")
    return Path(path)


def compensate_recording(compensator: Compensator, recording: Recording) -> Compensated:
    """Compensate a whole recording from a fresh state (as a stream that starts with its first sample)."""
    compensator.check_columns(recording.columns, source=str(recording.path))
    compensator.reset()
    return compensator.process(recording.columns)


def compensate_as_deployed(compensator: Compensator, recording: Recording, resample: bool = False) -> Compensated:
    """A whole recording as ``compensate.py`` runs it: a rate not the bundle's refused (or, with
    ``resample``, adopted: ``use_input_rate``), from a fresh state, a start-up window required to end."""
    compensator.use_input_rate(recording.fs_hz, resample, str(recording.path))  # a bad # fs_hz= is one line there
    compensator.row_name = recording.line_of
    out = compensate_recording(compensator, recording)
    if compensator.startup is not None:
        compensator.startup.require_done(str(recording.path))
    return out


def log_what_it_rests_on(compensator: Compensator) -> None:
    """A deployment's first lines (offline and live alike): how far to trust its error bar, and its Kalman stage."""
    if compensator.error_bar is not None:
        bar = compensator.error_bar
        (log.warning if bar.narrow_axes() else log.info)(bar.trust_line())
    if compensator.kalman is not None:
        log.info(kalman_line(compensator))


def kalman_line(compensator: Compensator) -> str | None:
    """One line for a deployment's log when the bundle has a Kalman stage: it low-passes, and by how much."""
    if compensator.kalman is None:
        return None
    from gyronet.model.kalman.costs import step_response

    response = step_response(compensator.kalman, compensator.bundle_fs_hz, 1.0, 30.0)
    delays = "/".join(f"{response[a]['delay_s']:.2f}" for a in AXES)
    return (f"Kalman stage on: the output follows a rate step 50 % after {delays} s (x/y/z), a low-pass; quote "
            "that beside the Allan figures (docs/guides/kalman.md)")


def compensate_file(bundle_dir: str | Path, input_path: str | Path, output_path: str | Path,
                    resample: bool = False, startup: Mapping[str, Any] | None = None) -> dict[str, int]:
    """``compensate.py``: read, compensate, write; return counts for the log.

    A recording whose rate differs from the bundle's ``fs_hz`` by more than 5 % is refused unless
    ``resample`` (:meth:`Compensator.use_input_rate`); ``startup``: ``use_startup`` options.
    """
    refuse_overwriting(input_path, output_path)
    compensator = Compensator.load(bundle_dir)
    compensator.use_startup(**dict(startup or {}))
    log_what_it_rests_on(compensator)
    recording = load_recording(input_path)
    check_temperatures(recording)  # Kelvin or a wrong column: refused, not every row flagged and compensated
    try:
        out = compensate_as_deployed(compensator, recording, resample)
    except StartupMotionError as err:  # the line names the file, as every refusal of one does
        raise StartupMotionError(f"{input_path}: {err}") from None
    still_s = 0.0 if compensator.startup is None else compensator.startup.still_s
    # the true rate left in the output: the input's, unless a start-up offset took the window's rate for its own
    # (it removes everything but its static_rate_dps, 0 unless given)
    static = recording.meta.get("static_rate_dps") if compensator.startup is None else compensator.startup.static_rate_dps
    write_compensated(output_path, output_columns(recording.time_s, recording.temp_c, out), bundle_dir, still_s, static)
    n_oor = int(out.out_of_range.sum())
    if n_oor:
        low, high = compensator.temp_range_c
        log.warning("%d of %d samples outside the trained temperature range [%.2f, %.2f] degC: flagged "
                    "in column out_of_range; the model holds its edge value there", n_oor, len(recording), low, high)
    n_bad = int(np.count_nonzero(out.bad_input))
    if n_bad:
        log.warning("%d of %d samples flagged in column bad_input (a temperature no sensor can read or jump to, or "
                    "a gyro value that is not finite or beyond the sensor's range): compensated from the last "
                    "good state", n_bad, len(recording))
    log.info("compensated %d samples (%s) -> %s", len(recording), ", ".join(AXES), output_path)
    return {"n_samples": len(recording), "n_out_of_range": n_oor, "n_bad_input": n_bad}
