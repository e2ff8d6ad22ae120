"""LP-Research LPMS log files (the CSV that LPMS-Control / OpenMAT / OpenZen write) as recordings.

Header variants seen in LP-Research's own code (every one is a comma-and-space separated line):

- OpenMAT ``LpSensor/LpmsSensorManager.cpp``, ``saveSensorData`` (repository pgsamila/openMat,
  also xkh500/openmat), early: ``SensorId, TimeStamp (s), FrameNumber, AccX (g), AccY (g), AccZ (g),
  GyroX (deg/s), ..., MagX (uT), ..., EulerX (deg), ..., QuatX, QuatY, QuatZ, QuatW (or QuatW first),
  LinAccX (m/s^2), ..., Pressure (hPa), Altitude (m), Temperature (degC), HeaveMotion (m)``.
  Rows come from ``LpmsSensor::checkSaveData``: ``openMatId, timeStamp, frameCount, a[3], g[3], ...``.
- OpenMAT later / LPMS-Control (``LpmsSensorManager.cpp`` and ``LpmsIoInterface::handleGetFlashLog``
  for the flash-log download): the same with ``LinAccX (g)`` and ``Pressure (kPa)``. The flash log
  converts the sensor's rad/s to deg/s (``* r2d``) before writing, so the header's deg/s holds.
- OpenZen's example recorder (``writeCsvHeader``): ``ImageIndex, TimeStamp (s), ...`` and the rest as
  above; its Temperature column holds ``gTemp``, the gyro's own temperature.
- LP-Research's mobile apps: ``..., LinAccX (m/s^2), ..., Pressure (mPa)`` (Android, no temperature,
  so not usable here) and ``EulerX(deg)``, ``Temperature(degC)`` without the space (iOS).

OpenZen documents ``g`` in deg/s (``docs/data.rst``, ZenImuData). An LPMS-IG1 can be set to output
rad/s (LP-Research knowledge base, "LPMS ASCII Format Output": "Raw GyroI (dps or rad/s)"), so a
``GyroX (rad/s)`` header is converted to deg/s, and a header without a unit needs ``gyro_unit``.
Outputs that were not enabled are logged as constants in every row (0, or the unit quaternion
``QuatW`` = 1 with ``QuatX..Z`` = 0); an output group whose every column is constant is dropped
(listed in ``disabled_outputs``), and a temperature or gyro that is 0 throughout is an error. A
file with several sensors (``SensorId``) needs ``sensor_id``. Frame counters and row indices are
not kept. Lost samples are counted from the timestamps (``missing_frames``: intervals longer than
1.5 median intervals, each worth ``round(interval / median) - 1`` samples), not from
``FrameNumber``, which OpenMAT counts on the host (``LpmsSensor.cpp``: ``frameCount``) and which
never skips when Bluetooth frames are lost.

Which gyro: the logged ``Gyro`` is ``currentData.g``, the host-corrected rate (OpenMAT
``LpSensor/LpmsSensor.cpp``: ``g = gyrMisalignMatrix * gRaw + gyrAlignmentBias``; OpenZen does the
same in ``ImuComponent.cpp``), not the raw gyro that LP-BUS streams; the recording says so
(``gyro_source=host_corrected``), a bundle trained on it records it, and ``stream.py`` refuses it
on the raw stream. Such logs do not record whether the sensor's gyro auto-calibration (legacy
register bit 30) was on: if it was, the sensor re-zeroed its gyro whenever it was still and part
of the thermal drift is gone from the log; a warning says so, louder when the gyro's median is
within ``AUTOCAL_SUSPECT_DPS`` of zero on every axis.
"""
from __future__ import annotations

import logging
import math
import os
import re
from pathlib import Path

import numpy as np

from gyronet.recordings.data import GAP_FACTOR, GYRO_COLUMNS, REQUIRED_COLUMNS, Recording
from gyronet.errors import RecordingError
from gyronet.recordings.csvtable.text import sniff, split_header
from gyronet.recordings.importers._common import (STANDARD_GRAVITY_M_S2, fahrenheit_to_c, finish, read_header_line,
                                       read_numeric_table, read_text, snake)

log = logging.getLogger(__name__)

_NAME = re.compile(r"(?P<base>[A-Za-z]+?)\s*(?P<axis>[XYZW])?\s*(?:[\(\[]\s*(?P<unit>[^\)\]]*?)\s*[\)\]])?\Z")
_BASES = {
    "timestamp": "time", "time": "time", "sensorid": "sensor_id", "openmatid": "sensor_id",
    "imageindex": "counter", "framenumber": "frame", "framecounter": "frame", "framecount": "frame",
    "acc": "acc", "accel": "acc", "gyro": "gyro", "gyr": "gyro", "mag": "mag", "euler": "euler",
    "quat": "quat", "linacc": "linacc", "angvel": "angvel", "angularvelocity": "angvel",
    "pressure": "pressure", "altitude": "altitude", "temperature": "temp", "temp": "temp",
    "heavemotion": "heave", "batterylevel": "battery",
}
_RATE_DPS = {"deg/s": 1.0, "dps": 1.0, "degs": 1.0, "deg/sec": 1.0, "rad/s": 180.0 / math.pi}
_ACC_G = {"g": 1.0, "m/s^2": 1.0 / STANDARD_GRAVITY_M_S2, "m/s2": 1.0 / STANDARD_GRAVITY_M_S2}
_TIME_S = {"s": 1.0, "": 1.0, "ms": 1e-3, "us": 1e-6}
_PRESSURE_KPA = {"kpa": 1.0, "hpa": 0.1, "pa": 1e-3}
AUTOCAL_SUSPECT_DPS = 0.002  # a median gyro this close to 0 on every axis looks re-zeroed by the sensor


def import_lpms(path: str | os.PathLike, sensor_id: int | None = None, gyro_unit: str = "auto",
                sensor: str | None = None) -> Recording:
    """Convert an LPMS log CSV to a recording.

    Parameters
    ----------
    path
        The log file written by LPMS-Control, OpenMAT or OpenZen.
    sensor_id
        Which ``SensorId`` to keep when the file holds several sensors.
    gyro_unit
        ``auto`` (from the header), or ``deg/s`` / ``rad/s`` for a header without units.
    sensor
        Overrides the ``sensor`` metadata.

    Returns
    -------
    Recording
        ``time_s``, ``temp_c``, ``gyro_*_dps``, ``acc_*_g`` and the other outputs, contract names.
    """
    path = Path(path)
    header_line, header = read_header_line(path)
    delimiter, decimal = sniff(read_text(path))  # a log re-saved by a spreadsheet: ';' and a decimal comma
    names = split_header(header, delimiter)
    while names and not names[-1]:
        names.pop()
    plan = [_plan(path, name, gyro_unit) for name in names]
    _check_plan(path, names, plan)
    raw, first_line = read_numeric_table(path, header_line, names, delimiter, decimal)

    rows = np.ones(len(raw[names[0]]), dtype=bool)
    ids = [n for n, (role, *_) in zip(names, plan) if role == "sensor_id"]
    chosen = _choose_sensor(path, raw[ids[0]], sensor_id) if ids else None
    if chosen is not None:
        rows = raw[ids[0]] == chosen

    columns: dict[str, np.ndarray] = {}
    meta: dict[str, object] = {"sensor": sensor or ("LP-Research LPMS" + (f" (SensorId {chosen:g})"
                                                                            if chosen is not None else "")),
                               "gyro_source": "host_corrected",
                               "gyro_autocalibration": "unknown (LPMS logs do not record it)"}
    for name, (role, target, convert) in zip(names, plan):
        if target is not None:
            columns[target] = convert(raw[name][rows])
    zero = {c for c, v in columns.items() if _all_zero(v)}
    for what, group in (("TimeStamp", ["time_s"]), ("Temperature", ["temp_c"]), ("Gyro", list(GYRO_COLUMNS))):
        if all(c in zero for c in group):
            raise RecordingError(f"{path}: {what} is 0 in every row: that output was not enabled when "
                                 "logging (enable it in LPMS-Control and record again)")
    disabled = _disabled_outputs(columns)
    for name in disabled:
        del columns[name]
    if disabled:
        meta["disabled_outputs"] = ";".join(disabled)
        log.info("%s: outputs constant in every row (not enabled), not kept: %s", path.name, ", ".join(disabled))
    meta["missing_frames"] = _missing_frames(columns["time_s"])
    _warn_gyro_source(path, columns)
    return finish(path, columns, meta, "lpms", row_label="line", first_row=first_line)


def _disabled_outputs(columns: dict[str, np.ndarray]) -> list[str]:
    """Columns of output groups (``quat_*``, ``mag_*``, ``pressure_kpa``...) constant in every row.

    A group is judged whole: a unit quaternion (w = 1, x = y = z = 0) is an output that was off,
    while one constant axis of a moving group is data. Single columns count as off only when 0.
    """
    groups: dict[str, list[str]] = {}
    for name in columns:
        if name not in REQUIRED_COLUMNS:
            groups.setdefault(_group(name), []).append(name)
    out = []
    for names in groups.values():
        if len(names) == 1:
            off = _all_zero(columns[names[0]])
        else:
            off = all(_constant(columns[n]) for n in names)
        out.extend(names if off else [])
    return out


def _group(name: str) -> str:
    """``quat_w`` -> ``quat``; ``mag_x_ut`` -> ``mag``; ``pressure_kpa`` -> ``pressure_kpa``."""
    parts = name.split("_")
    return parts[0] if len(parts) >= 2 and parts[1] in ("x", "y", "z", "w") else name


def _constant(values: np.ndarray) -> bool:
    finite = values[np.isfinite(values)]
    return finite.size > 1 and bool(np.all(finite == finite[0]))


def _warn_gyro_source(path: Path, columns: dict[str, np.ndarray]) -> None:
    medians = [float(np.nanmedian(columns[c])) for c in GYRO_COLUMNS]
    suspect = all(abs(m) < AUTOCAL_SUSPECT_DPS for m in medians)
    log.warning("%s: an LPMS log holds the host-corrected gyro (OpenMAT: alignment matrix and bias applied), not the "
                "raw LP-BUS gyro: a bundle trained on it is refused by stream.py (record with scripts/record.py "
                "instead); the sensor's gyro auto-calibration may have been on%s", path.name,
                f" and the gyro's median is within {AUTOCAL_SUSPECT_DPS} deg/s of 0 on every axis "
                f"({', '.join(f'{m:.2g}' for m in medians)}): it probably was, removing drift" if suspect else "")


def _plan(path: Path, name: str, gyro_unit: str):
    """(role, column name or None, converter) for one header cell."""
    match = _NAME.fullmatch(name)
    if match is None:
        target = snake(name)
        return "other", (target if "_" in target else f"{target}_raw"), _same
    base = match.group("base").lower()
    axis = (match.group("axis") or "").lower()
    unit_text = match.group("unit")
    unit = (unit_text or "").replace(" ", "").replace("°", "deg").replace("µ", "u").replace("²", "^2").lower()
    role = _BASES.get(base, "other")

    def wrong(expected: str):
        return RecordingError(f"{path}: column {name!r}: unit {unit_text or 'missing'!r} is not one this "
                              f"importer knows for it (expected {expected})")

    if role == "time":
        if unit not in _TIME_S:
            raise wrong("s or ms")
        return role, "time_s", _scale(_TIME_S[unit])
    if role in ("sensor_id", "counter", "frame"):
        return role, None, _same
    if role in ("gyro", "angvel"):
        given = gyro_unit.replace(" ", "").lower()
        if gyro_unit != "auto" and unit and unit != given:  # OpenZen writes (deg/s) whatever the sensor sends
            log.warning("%s: column %r: lpms.gyro_unit=%s overrides the header's unit", path.name, name, gyro_unit)
        if gyro_unit != "auto":
            unit = given
        if unit not in _RATE_DPS:
            hint = "; pass lpms.gyro_unit=deg/s or rad/s" if not unit else ""
            raise wrong("deg/s or rad/s" + hint)
        return role, f"{'gyro' if role == 'gyro' else 'angvel'}_{axis}_dps", _scale(_RATE_DPS[unit])
    if role in ("acc", "linacc"):
        if unit in _ACC_G:
            return role, f"{role}_{axis}_g", _scale(_ACC_G[unit])
        if unit:
            raise wrong("g or m/s^2")
        return role, f"{role}_{axis}_raw", _same
    if role == "temp":
        if unit in ("degc", "c"):
            return role, "temp_c", _same
        if unit in ("degf", "f"):
            return role, "temp_c", fahrenheit_to_c
        raise wrong("degC")
    if role == "pressure" and unit in _PRESSURE_KPA:
        return role, "pressure_kpa", _scale(_PRESSURE_KPA[unit])
    if role == "euler" and unit == "rad":
        return role, f"euler_{axis}_deg", np.degrees
    known = {"mag": "mag", "euler": "euler", "quat": "quat", "altitude": "altitude", "heave": "heave",
             "battery": "battery", "pressure": "pressure"}
    what = known.get(role, snake(match.group("base")))
    stem = f"{what}_{axis}" if axis else what
    if role == "quat":
        return role, stem, _same  # unitless, named as gyronet.deploy.stream names LP-BUS quaternions
    return role, f"{stem}_{snake(unit) if unit else 'raw'}", _same


def _check_plan(path: Path, names: list[str], plan: list) -> None:
    # a column the importer does not recognise keeps its name: a contract CSV's own names are no LPMS log
    known = [t for role, t, _ in plan if t is not None and role != "other"]
    targets = [t for _, t, _ in plan if t is not None]
    needed = {"time_s": "TimeStamp (s)", "temp_c": "Temperature (degC)", "gyro_x_dps": "GyroX (deg/s)",
              "gyro_y_dps": "GyroY (deg/s)", "gyro_z_dps": "GyroZ (deg/s)"}
    missing = [label for key, label in needed.items() if key not in known]
    if missing:
        raise RecordingError(f"{path}: not a usable LPMS log: missing {', '.join(missing)} "
                             f"(header has {', '.join(names)})")
    duplicates = sorted({t for t in targets if targets.count(t) > 1})
    if duplicates:
        raise RecordingError(f"{path}: two header columns map to {duplicates[0]!r}")


def _choose_sensor(path: Path, ids: np.ndarray, wanted: int | None) -> float | None:
    present = sorted({float(v) for v in ids[np.isfinite(ids)]})
    if wanted is not None:
        try:
            wanted = int(wanted)
        except (TypeError, ValueError):
            raise RecordingError(f"lpms.sensor_id must be a SensorId number (the file has {_ids(present)}), "
                                 f"got {wanted!r}") from None
        if float(wanted) not in present:
            raise RecordingError(f"{path}: no SensorId {wanted} (the file has {_ids(present)})")
        return float(wanted)
    if len(present) > 1:
        raise RecordingError(f"{path}: the file holds sensors {_ids(present)}; pass lpms.sensor_id=<one of them>")
    return present[0] if present else None


def _ids(values: list[float]) -> str:
    return ", ".join(f"{v:g}" for v in values)


def _missing_frames(time_s: np.ndarray) -> int:
    """Samples lost, from the timestamps: each interval over GAP_FACTOR medians lost round(interval / median) - 1."""
    step = np.diff(time_s[np.isfinite(time_s)])
    step = step[step > 0]
    if step.size == 0:
        return 0
    nominal = float(np.median(step))
    gaps = step[step > GAP_FACTOR * nominal]
    return int(np.sum(np.round(gaps / nominal) - 1))


def _all_zero(values: np.ndarray) -> bool:
    finite = values[np.isfinite(values)]
    return finite.size > 1 and not np.any(finite)


def _scale(factor: float):
    return lambda values: values * factor


def _same(values: np.ndarray) -> np.ndarray:
    return values
