"""PX4 ULog (``.ulg``) logs, such as thermal-calibration logs, as recordings, read with pyulog.

What is read (PX4 ``msg/sensor_gyro.msg``, ``sensor_accel.msg``, ``sensor_gyro_fifo.msg``):

- ``sensor_gyro``: ``timestamp_sample`` (or ``timestamp`` in logs before it existed), microseconds
  since boot; ``x``, ``y``, ``z`` in rad/s (board frame, after the driver's rotation, before the
  vehicle calibration); ``temperature`` in degC; ``device_id``. Each IMU is one multi-instance:
  ``instance`` picks it (0 by default).
- ``sensor_accel`` (``accel``, on by default): the same ``instance``, merged onto the gyro samples by
  nearest timestamp (within two accel intervals, else the gyro row is dropped and counted as
  ``no_accel``), m/s^2 -> g; its ``temperature`` is kept as ``accel_temp_c``.
- ``sensor_gyro_fifo`` (``topic=sensor_gyro_fifo``): ``samples`` int16 values per message in
  ``x[]``, ``y[]``, ``z[]``, times ``scale`` -> rad/s, ``dt`` microseconds apart, the last one at
  ``timestamp_sample`` (as PX4Gyroscope::updateFIFO publishes them). The FIFO topic has no
  temperature: it is interpolated from ``sensor_gyro`` of the same ``device_id`` (or instance).

Not read: bookkeeping fields (error_count, clip counters, raw integers, integrals), other topics,
and the appended-data / dropout details beyond what pyulog handles. A log cut short (power lost)
keeps its complete messages; pyulog's own warnings are logged, never printed.
"""
from __future__ import annotations

import contextlib
import io
import logging
import os
import struct
from pathlib import Path

import numpy as np

from gyronet.recordings.data import Recording
from gyronet.errors import GyronetError, RecordingError
from gyronet.recordings.importers._common import STANDARD_GRAVITY_M_S2, degrees, finish

log = logging.getLogger(__name__)

ULOG_MAGIC = b"ULog\x01\x12\x35"
ULOG_HEADER_BYTES = 16  # magic (7), version (1), start timestamp (uint64)
TOPICS = ("sensor_gyro", "sensor_gyro_fifo")
ACCEL_TOLERANCE_INTERVALS = 2.0


def is_ulog(path: Path) -> bool:
    """True when the file starts with the ULog magic bytes."""
    try:
        with open(path, "rb") as handle:
            return handle.read(len(ULOG_MAGIC)) == ULOG_MAGIC
    except OSError:
        return False


def import_ulog(path: str | os.PathLike, instance: int = 0, topic: str = "sensor_gyro",
                accel: bool = True, sensor: str | None = None) -> Recording:
    """Convert one IMU of a PX4 ULog file to a recording.

    Parameters
    ----------
    path
        The ``.ulg`` file.
    instance
        The multi-instance of the gyro topic (which IMU).
    topic
        ``sensor_gyro`` or ``sensor_gyro_fifo``.
    accel
        Merge ``sensor_accel`` of the same instance as ``acc_*_g`` when the log has it.
    sensor
        Overrides the ``sensor`` metadata.

    Returns
    -------
    Recording
        ``time_s`` (since boot), ``temp_c``, ``gyro_*_dps``, and ``acc_*_g``, ``accel_temp_c`` if merged.
    """
    path = Path(path)
    if topic not in TOPICS:
        raise GyronetError(f"ulog topic must be one of {', '.join(TOPICS)}, got {topic!r}")
    ulog = _read(path)
    gyro = _dataset(path, ulog, topic, instance)
    if topic == "sensor_gyro":
        time_us, rate_rad_s = _gyro_time_us(gyro.data), [gyro.data[a] for a in "xyz"]
        if "temperature" not in gyro.data:
            raise RecordingError(f"{path}: sensor_gyro has no temperature field (too old a PX4 log)")
        temp_c = gyro.data["temperature"]
    else:
        time_us, rate_rad_s = _expand_fifo(path, gyro.data)
        temp_c = _fifo_temperature(path, ulog, gyro, instance, time_us)
    device_id = int(gyro.data["device_id"][0]) if "device_id" in gyro.data else None

    columns = {"time_s": time_us.astype(np.float64) * 1e-6, "temp_c": temp_c}
    for axis, values in zip("xyz", rate_rad_s):
        columns[f"gyro_{axis}_dps"] = degrees(values)
    dropped: dict[str, int] = {}
    if accel:
        far = _merge_accel(path, ulog, instance, time_us, columns)
        dropped["no_accel"] = int(far.sum())
        columns = {k: v[~far] for k, v in columns.items()}
    board = ulog.msg_info_dict.get("ver_hw")
    meta = {"sensor": sensor or f"PX4 {board or 'board'} {topic} instance {instance}"
            + (f" (device_id {device_id:#x})" if device_id is not None else ""),
            "px4_topic": topic, "px4_instance": instance, "px4_device_id": device_id,
            "px4_board": board, "time_base": "microseconds since boot / 1e6"}
    if ulog.file_corruption:
        log.warning("%s: pyulog reports corrupt data in the log; the readable messages were kept", path.name)
        meta["ulog_corruption"] = "true"
    return finish(path, columns, meta, "ulog", dropped=dropped, row_label="sample", first_row=0)


def _read(path: Path):
    try:
        from pyulog import ULog
    except ImportError:  # pragma: no cover - pyulog is a declared dependency
        raise GyronetError("reading ULog files needs pyulog: pip install pyulog") from None
    if not path.is_file():
        raise RecordingError(f"{path}: no such file")
    size = path.stat().st_size
    if size < ULOG_HEADER_BYTES:
        raise RecordingError(f"{path}: truncated ULog file ({size} bytes, the header alone is {ULOG_HEADER_BYTES})")
    if not is_ulog(path):
        raise RecordingError(f"{path}: not a ULog file (it does not start with the ULog magic bytes)")
    printed = io.StringIO()
    try:
        with contextlib.redirect_stdout(printed):
            ulog = ULog(str(path), ["sensor_gyro", "sensor_accel", "sensor_gyro_fifo"])
    except (struct.error, ValueError, IndexError, KeyError, UnicodeDecodeError, OverflowError) as err:
        raise RecordingError(f"{path}: unreadable ULog file ({type(err).__name__}: {err})") from None
    except Exception as err:  # pyulog.ULogException and its subclasses
        if type(err).__module__.startswith("pyulog"):
            raise RecordingError(f"{path}: unreadable ULog file ({err})") from None
        raise
    for line in printed.getvalue().splitlines():
        if line.strip():
            log.warning("%s: pyulog: %s", path.name, line.strip())
    return ulog


def _dataset(path: Path, ulog, topic: str, instance: int):
    found = {d.multi_id: d for d in ulog.data_list if d.name == topic}
    if not found:
        logged = sorted({d.name for d in ulog.data_list}) or ["none of sensor_gyro, sensor_accel, sensor_gyro_fifo"]
        raise RecordingError(f"{path}: no {topic} data in the log (it has {', '.join(logged)}); "
                             "a thermal-calibration log needs SDLOG_PROFILE with the thermal calibration bit")
    if instance not in found:
        raise RecordingError(f"{path}: no {topic} instance {instance} (the log has instance(s) "
                             f"{', '.join(str(i) for i in sorted(found))}); pass ulog.instance=<one of them>")
    return found[instance]


def _gyro_time_us(data: dict) -> np.ndarray:
    stamp = data.get("timestamp_sample")
    if stamp is None or not np.any(stamp):
        stamp = data["timestamp"]
    return np.asarray(stamp, dtype=np.int64)


def _expand_fifo(path: Path, data: dict) -> tuple[np.ndarray, list[np.ndarray]]:
    """One row per FIFO sample: times (us) and rates (rad/s), in time order."""
    width = sum(1 for k in data if k.startswith("x["))
    if width == 0 or "samples" not in data or "dt" not in data or "scale" not in data:
        raise RecordingError(f"{path}: sensor_gyro_fifo lacks x[], samples, dt or scale")
    count = np.clip(data["samples"].astype(np.int64), 0, width)
    valid = np.arange(width)[None, :] < count[:, None]
    # t_i = timestamp_sample - (samples - 1 - i) * dt
    age = (count[:, None] - 1 - np.arange(width)[None, :]) * data["dt"].astype(np.float64)[:, None]
    time_us = np.round(_gyro_time_us(data)[:, None] - age).astype(np.int64)[valid]
    rates = []
    for axis in "xyz":
        raw = np.stack([data[f"{axis}[{i}]"] for i in range(width)], axis=1).astype(np.float64)
        rates.append((raw * data["scale"].astype(np.float64)[:, None])[valid])
    return time_us, rates


def _fifo_temperature(path: Path, ulog, fifo, instance: int, time_us: np.ndarray) -> np.ndarray:
    gyros = [d for d in ulog.data_list if d.name == "sensor_gyro"]
    device = fifo.data.get("device_id", [None])[0]
    match = [d for d in gyros if device is not None and d.data.get("device_id", [None])[0] == device]
    match = match or [d for d in gyros if d.multi_id == instance]
    if not match or "temperature" not in match[0].data:
        raise RecordingError(f"{path}: sensor_gyro_fifo has no temperature and the log has no sensor_gyro "
                             "of the same device to take it from")
    source = match[0].data
    stamp = _gyro_time_us(source).astype(np.float64)
    when = time_us.astype(np.float64)
    temp_c = np.interp(when, stamp, source["temperature"].astype(np.float64))
    # outside sensor_gyro's span (beyond two of its intervals) there is no temperature: NaN, dropped
    margin_us = 2.0 * float(np.median(np.diff(stamp))) if len(stamp) > 1 else 0.0
    return np.where((when < stamp[0] - margin_us) | (when > stamp[-1] + margin_us), np.nan, temp_c)


def _merge_accel(path: Path, ulog, instance: int, time_us: np.ndarray, columns: dict) -> np.ndarray:
    """Add acc_*_g and accel_temp_c by nearest timestamp; return the mask of rows with no accel sample."""
    found = [d for d in ulog.data_list if d.name == "sensor_accel" and d.multi_id == instance]
    if not found:
        log.info("%s: no sensor_accel instance %d; no acc_*_g columns", path.name, instance)
        return np.zeros(len(time_us), dtype=bool)
    data = found[0].data
    stamp = _gyro_time_us(data).astype(np.float64)
    if len(stamp) < 2 or np.any(np.diff(stamp) <= 0):
        log.warning("%s: sensor_accel time stamps are not increasing; accel not merged", path.name)
        return np.zeros(len(time_us), dtype=bool)
    when = time_us.astype(np.float64)
    right = np.clip(np.searchsorted(stamp, when), 1, len(stamp) - 1)
    nearest = np.where(np.abs(stamp[right - 1] - when) <= np.abs(stamp[right] - when), right - 1, right)
    tolerance_us = ACCEL_TOLERANCE_INTERVALS * float(np.median(np.diff(stamp)))
    far = np.abs(stamp[nearest] - when) > tolerance_us
    for axis in "xyz":
        # acc_g = acc_m_s2 / g0
        columns[f"acc_{axis}_g"] = data[axis][nearest].astype(np.float64) / STANDARD_GRAVITY_M_S2
    if "temperature" in data:
        columns["accel_temp_c"] = data["temperature"][nearest].astype(np.float64)
    if far.mean() > 0.01:
        log.warning("%s: %.1f %% of gyro samples have no accel sample within %.0f us (dropped); "
                    "pass ulog.accel=false to keep them without accel", path.name, 100 * far.mean(), tolerance_us)
    return far
