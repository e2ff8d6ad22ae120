"""The PAN cubesat thermal-vacuum test (``psim`` repository, TVCtest3_7_20.csv) as a recording.

The file and its meaning are described in ``shared/data/real/psim-tvc/PROVENANCE.md``:

- ``time (ms)``: flight-computer time since boot, ms.
- ``gyrox rad/s`` ... ``gyroz rad/s``: the LSM6DSM rate as logged. The authors' analysis script
  (``temp_dep_gyro_mag.m``) multiplies them by 0.5 "to correct for an error in driver script";
  so does this importer (``gyro_scale``).
- ``temp``: the LSM6DSM OUT_TEMP word stored as unsigned 16 bit. With the datasheet scale
  (256 LSB/degC, 0 LSB = 25 degC), ``T = 25 + int16(temp) / 256``. The authors call it
  uncalibrated: the absolute value may be a few degC off, the slope is what matters.
- ``mag1x [T]`` ...: magnetometer, tesla, kept as ``mag1_x_t`` ...
- 25 bursts of 5 s at 50 Hz, ~305 s apart: the gaps are breaks in the record (CONTRACT.md allows them).
- The authors removed 3 spike samples with ``gyrox rad/s <= -0.08``; ``drop_spikes`` does the same,
  on the logged value, and counts them.

The hand-written chamber log (ETUColdTest3_7_20.csv: thermocouples F2, F3, F4 in degF and C1 in
degC every 5 min) can be attached with ``chamber_log``. Its alignment with ``time (ms)`` was never
recorded (the authors aligned the two "roughly" by index), so the importer assumes the first log
row is at the first sample, shifted by ``chamber_offset_s``, and says so in the metadata.
"""
from __future__ import annotations

import logging
import os
import re
from pathlib import Path

import numpy as np

from gyronet.recordings.data import Recording
from gyronet.errors import RecordingError
from gyronet.recordings.importers._common import (degrees, fahrenheit_to_c, finish, read_header_line,
                                       read_numeric_table, snake)

log = logging.getLogger(__name__)

GYRO_SCALE = 0.5  # the authors' driver-error correction (temp_dep_gyro_mag.m)
SPIKE_THRESHOLD_RAD_S = -0.08  # on the logged gyrox column, before the 0.5 correction
TEMP_LSB_PER_C = 256.0  # LSM6DSM OUT_TEMP sensitivity
TEMP_OFFSET_C = 25.0  # LSM6DSM OUT_TEMP = 0 at 25 degC
SENSOR = "ST LSM6DSM on the PAN cubesat ETU (psim TVC test 2020-03-07)"

_TIME = re.compile(r"time\s*[\(\[]\s*(ms|s|us)\s*[\)\]]\Z", re.I)
_GYRO = re.compile(r"gyro\s*([xyz])\s*[\(\[]?\s*([^\)\]]*?)\s*[\)\]]?\Z", re.I)
_MAG = re.compile(r"mag(\d*)\s*([xyz])\s*[\(\[]\s*([^\)\]]+?)\s*[\)\]]\Z", re.I)
_UNIT = re.compile(r"(.*?)\s*[\(\[]\s*([^\)\]]+?)\s*[\)\]]\Z")
_TIME_SCALE_S = {"ms": 1e-3, "s": 1.0, "us": 1e-6}


def import_psim(path: str | os.PathLike, drop_spikes: bool = True, gyro_scale: float = GYRO_SCALE,
                chamber_log: str | os.PathLike | None = None, chamber_offset_s: float = 0.0,
                sensor: str | None = None) -> Recording:
    """Convert TVCtest3_7_20.csv (or a file of the same layout) to a recording.

    Parameters
    ----------
    path
        The psim TVC CSV.
    drop_spikes
        Drop the samples with logged ``gyrox rad/s <= -0.08`` as the authors did (counted).
    gyro_scale
        Factor on the logged rates before rad/s -> deg/s; 0.5 is the authors' driver correction.
    chamber_log
        Optional ETUColdTest3_7_20.csv to attach as ``chamber_*_c`` columns (alignment assumed).
    chamber_offset_s
        Time of the first chamber-log row relative to the first sample, s.
    sensor
        Overrides the ``sensor`` metadata.

    Returns
    -------
    Recording
        ``time_s``, ``temp_c``, ``gyro_*_dps`` (deg/s), ``mag1_*_t`` (tesla) and any other column.
    """
    path = Path(path)
    header_line, header = read_header_line(path)
    names = [n.strip() for n in header.split(",")]
    roles = _roles(path, names)
    raw, first_line = read_numeric_table(path, header_line, names)

    columns: dict[str, np.ndarray] = {}
    time_name = roles["time"]
    columns["time_s"] = raw[time_name] * _TIME_SCALE_S[_TIME.match(time_name).group(1).lower()]
    columns["temp_c"] = _out_temp_to_c(path, raw[roles["temp"]], first_line)
    for axis in "xyz":
        # rate_dps = degrees(gyro_scale * logged)
        columns[f"gyro_{axis}_dps"] = degrees(gyro_scale * raw[roles[f"gyro_{axis}"]])
    for name, target in roles["other"].items():
        columns[target] = raw[name]

    dropped: dict[str, int] = {}
    if drop_spikes:
        spike = raw[roles["gyro_x"]] <= SPIKE_THRESHOLD_RAD_S
        dropped["spike"] = int(spike.sum())
        columns = {k: v[~spike] for k, v in columns.items()}
    meta = {"sensor": sensor or SENSOR, "gyro_scale": repr(float(gyro_scale)),
            "temp_from": "25 + int16(temp)/256 (LSM6DSM datasheet; uncalibrated)",
            "spikes": f"gyrox rad/s <= {SPIKE_THRESHOLD_RAD_S} dropped" if drop_spikes else "kept"}
    if chamber_log is not None:
        chamber, chamber_meta = _chamber_columns(Path(chamber_log), columns["time_s"], chamber_offset_s)
        columns.update(chamber)
        meta.update(chamber_meta)
    return finish(path, columns, meta, "psim", dropped=dropped, row_label="line", first_row=first_line)


def _roles(path: Path, names: list[str]) -> dict:
    """Which header column is time, temperature, each gyro axis; the others with their new names."""
    roles: dict = {"other": {}}
    for name in names:
        if _TIME.match(name):
            roles["time"] = name
        elif name.lower() == "temp":
            roles["temp"] = name
        elif (gyro := _GYRO.match(name)) is not None:
            unit = gyro.group(2).replace(" ", "").lower()
            if unit != "rad/s":
                raise RecordingError(f"{path}: column {name!r}: gyro unit {gyro.group(2) or 'missing'!r}, "
                                     "this format logs rad/s ('gyrox rad/s')")
            roles[f"gyro_{gyro.group(1).lower()}"] = name
        elif (mag := _MAG.match(name)) is not None:
            roles["other"][name] = f"mag{mag.group(1)}_{mag.group(2).lower()}_{snake(mag.group(3))}"
        elif (unit := _UNIT.match(name)) is not None:
            roles["other"][name] = f"{snake(unit.group(1))}_{snake(unit.group(2))}"
        else:
            roles["other"][name] = f"{snake(name)}_raw"
            log.warning("%s: column %r has no unit; kept as %s", path.name, name, roles["other"][name])
    wanted = {"time": "time (ms)", "temp": "temp", "gyro_x": "gyrox rad/s", "gyro_y": "gyroy rad/s",
              "gyro_z": "gyroz rad/s"}
    missing = [label for key, label in wanted.items() if key not in roles]
    if missing:
        raise RecordingError(f"{path}: not a psim TVC file: missing column(s) {', '.join(missing)} "
                             f"(header has {', '.join(names)})")
    return roles


def _out_temp_to_c(path: Path, word: np.ndarray, first_line: int) -> np.ndarray:
    """The OUT_TEMP word stored as uint16 -> degC."""
    finite = np.isfinite(word)
    bad = np.flatnonzero(finite & ((word != np.round(word)) | (word < 0) | (word > 65535)))
    if bad.size:
        raise RecordingError(f"{path}: line {first_line + int(bad[0])}: column 'temp': {word[bad[0]]!r} is not "
                             "a raw OUT_TEMP word (a whole number 0..65535)")
    signed = np.where(finite, word, 0).astype(np.int64).astype(np.uint16).view(np.int16)
    # T = 25 + int16(OUT_TEMP) / 256
    return np.where(finite, TEMP_OFFSET_C + signed / TEMP_LSB_PER_C, np.nan)


def _chamber_columns(path: Path, time_s: np.ndarray, offset_s: float
                     ) -> tuple[dict[str, np.ndarray], dict[str, str]]:
    """The chamber log, converted to degC and interpolated linearly onto ``time_s``."""
    header_line, header = read_header_line(path)
    names = [n.strip() for n in header.split(",")]
    try:
        import pandas as pd

        frame = pd.read_csv(path, skiprows=header_line - 1, dtype=str, keep_default_na=False,
                            encoding="utf-8-sig")
    except (ValueError, OSError) as err:
        raise RecordingError(f"{path}: cannot read the chamber log ({err})") from None
    frame.columns = [c.strip() for c in frame.columns]
    probes = [n for n in names if _UNIT.match(n) and _UNIT.match(n).group(2).upper() in ("F", "C")]
    if "Time" not in frame.columns or not probes:
        raise RecordingError(f"{path}: not a chamber log (needs 'Time' and probe columns like 'F2 (F)'; "
                             f"header has {', '.join(n for n in names if n)})")
    values = {p: pd.to_numeric(frame[p].str.strip(), errors="coerce").to_numpy() for p in probes}
    clock = frame["Time"].str.strip()
    rows = np.flatnonzero(np.logical_and.reduce([np.isfinite(v) for v in values.values()])
                          & clock.str.fullmatch(r"\d{1,2}:\d{2}").to_numpy())
    if rows.size < 2:
        raise RecordingError(f"{path}: fewer than two chamber-log rows with a time and every reading")
    minutes = np.array([int(h) * 60 + int(m) for h, m in (clock.iloc[r].split(":") for r in rows)], float)
    log_time_s = time_s[0] + offset_s + (minutes - minutes[0]) * 60.0
    outside = int(((time_s < log_time_s[0]) | (time_s > log_time_s[-1])).sum())
    if outside:
        raise RecordingError(f"{path}: with chamber_offset_s={offset_s}, {outside} sample(s) fall outside the "
                             f"chamber log ({clock.iloc[rows[0]]}..{clock.iloc[rows[-1]]})")
    columns = {}
    for probe in probes:
        what, unit = _UNIT.match(probe).groups()
        reading = values[probe][rows]
        temp_c = fahrenheit_to_c(reading) if unit.upper() == "F" else reading
        columns[f"chamber_{snake(what)}_c"] = np.interp(time_s, log_time_s, temp_c)
    meta = {"chamber_log": path.name,
            "chamber_alignment": f"assumed: log row {clock.iloc[rows[0]]} at the first sample + "
                                 f"{offset_s} s (the true alignment was not recorded); linear interpolation"}
    log.info("%s: chamber log attached with an assumed alignment (offset %s s)", path.name, offset_s)
    return columns, meta
