"""ROS bags (ROS 1 ``.bag``; ROS 2 ``.db3``, ``.mcap`` or a bag folder) as recordings, read with rosbags.

So that recordings made for allan_variance_ros or imu_utils can be trained on. What is read:

- One ``sensor_msgs/Imu`` topic (``imu_topic``; found by type when the bag has exactly one):
  ``angular_velocity`` rad/s -> ``gyro_*_dps``; ``linear_acceleration`` m/s^2 -> ``acc_*_g``, left
  out when ``linear_acceleration_covariance[0]`` is -1 in every message (ROS's "not provided");
  ``header.stamp`` -> ``time_s`` (``stamp=bag``: the time the recorder received the message, for
  drivers that leave the header stamp at zero).
- One temperature topic (``temp_topic``; found when the bag has exactly one
  ``sensor_msgs/Temperature``): ``temperature`` degC at its ``header.stamp``. A named
  ``std_msgs/Float32`` or ``Float64`` topic is read too, at its bag time (it has no header).
- The join is causal: each IMU sample takes the last temperature stamped at or before it (a
  zero-order hold, what a live system sees), never a later one. IMU samples before the first
  temperature, or more than ``temp_max_age_s`` after the latest one (default: 5 temperature
  intervals), are dropped and counted (``before_first_temp``, ``stale_temp``).
- ``time_s`` is seconds since the first IMU stamp, computed in integer nanoseconds so that
  microseconds survive Unix-time stamps; that first stamp is kept as ``stamp_origin_ns``.
- A bag is in receive order: messages are sorted by stamp (the count is ``reordered``).
  ``lost_samples`` is counted from the stamps: an interval of k median intervals (rounded) means
  k - 1 samples lost; intervals over 5 medians are breaks in the record, as CONTRACT.md allows.

Not read: orientation, covariances, other topics.
"""
from __future__ import annotations

import hashlib
import logging
import os
from pathlib import Path

import numpy as np

from gyronet.recordings.data import BREAK_FACTOR, GYRO_COLUMNS, Recording
from gyronet.errors import GyronetError, RecordingError
from gyronet.recordings.importers._common import ACC_COLUMNS, STANDARD_GRAVITY_M_S2, degrees, finish

log = logging.getLogger(__name__)

IMU_TYPE = "sensor_msgs/msg/Imu"
TEMP_TYPE = "sensor_msgs/msg/Temperature"
SCALAR_TEMP_TYPES = ("std_msgs/msg/Float32", "std_msgs/msg/Float64")
SUFFIXES = (".bag", ".db3", ".mcap")
STAMPS = ("header", "bag")
_MAGIC = (b"#ROSBAG V2.0\n", b"\x89MCAP0\r\n")
TEMP_ADVICE = ("a recording needs temp_c, the sensor's own temperature (docs/reference/recording-format.md): "
               "record the driver's sensor_msgs/Temperature topic with the IMU (rosbag record / ros2 bag record both "
               "topics), or name a std_msgs/Float32 topic with rosbag.temp_topic=...")


def is_rosbag(path: str | os.PathLike) -> bool:
    """True for a ``.bag``, ``.db3`` or ``.mcap`` file (or its magic bytes), or a ROS 2 bag folder."""
    path = Path(path)
    if path.is_dir():
        return (path / "metadata.yaml").is_file()
    if path.suffix.lower() in SUFFIXES:
        return True
    try:
        with open(path, "rb") as handle:
            head = handle.read(16)
    except OSError:
        return False
    return any(head.startswith(magic) for magic in _MAGIC)


def import_rosbag(path: str | os.PathLike, imu_topic: str | None = None, temp_topic: str | None = None,
                  temp_max_age_s: float | None = None, stamp: str = "header",
                  sensor: str | None = None) -> Recording:
    """Convert one IMU of a ROS bag, with its temperature, to a recording.

    Parameters
    ----------
    path
        A ROS 1 ``.bag``, a ROS 2 ``.db3`` or ``.mcap`` file, or a ROS 2 bag folder.
    imu_topic, temp_topic
        The topics to read; None picks the only one of its type.
    temp_max_age_s
        An IMU sample whose latest temperature is older than this is dropped; None: 5 intervals
        of the temperature topic.
    stamp
        ``header`` (the driver's sample time) or ``bag`` (the recorder's receive time).
    sensor
        Overrides the ``sensor`` metadata.

    Returns
    -------
    Recording
        ``time_s``, ``temp_c``, ``gyro_*_dps`` and, when the bag has them, ``acc_*_g``.
    """
    path = Path(path)
    if temp_max_age_s is not None and not (isinstance(temp_max_age_s, (int, float)) and temp_max_age_s > 0):
        raise GyronetError(f"rosbag.temp_max_age_s must be a positive number of seconds or null, got {temp_max_age_s!r}")
    with _open(path) as reader:
        imu_name = _pick(path, reader, imu_topic, (IMU_TYPE,), "imu_topic", "no sensor_msgs/Imu topic")
        temp_name = _pick(path, reader, temp_topic, (TEMP_TYPE, *SCALAR_TEMP_TYPES), "temp_topic",
                          "no sensor_msgs/Temperature topic", auto_types=(TEMP_TYPE,), advice=f"; {TEMP_ADVICE}")
        imu_ns, columns, meta = _read_imu(path, reader, imu_name, stamp)
        temp_ns, temp_c = _read_temperature(path, reader, temp_name, stamp)
    columns["temp_c"], dropped = _join_causal(path, imu_ns, temp_ns, temp_c, temp_max_age_s)
    keep = np.isfinite(columns["temp_c"])
    columns = {k: v[keep] for k, v in columns.items()}
    meta.update(ros_temp_topic=temp_name, sensor=sensor or meta["sensor"])
    # a bag folder is hashed here, whole: finish() would hash one file
    return finish(path, columns, meta, "rosbag", dropped=dropped, row_label="IMU message", first_row=0,
                  sha256=_sha256(path))


def read_rates(path: str | os.PathLike, imu_topic: str | None = None, stamp: str = "header") -> Recording:
    """The IMU topic alone (``time_s``, ``gyro_*_dps``, ``acc_*_g``): what Allan analysis needs, no temperature."""
    path = Path(path)
    with _open(path) as reader:
        imu_name = _pick(path, reader, imu_topic, (IMU_TYPE,), "imu_topic", "no sensor_msgs/Imu topic")
        _, columns, meta = _read_imu(path, reader, imu_name, stamp)
    keep = np.logical_and.reduce([np.isfinite(v) for v in columns.values()])
    keep &= np.concatenate([[True], np.diff(columns["time_s"]) > 0])  # stamps are sorted: drop repeats
    if not keep.all():
        log.info("%s: %d IMU message(s) with NaN, inf or a repeated stamp dropped", path.name, int((~keep).sum()))
    return Recording({k: v[keep] for k, v in columns.items()}, {k: str(v) for k, v in meta.items()}, str(path))


class _open:
    """rosbags' AnyReader on one bag, its errors as one-line RecordingErrors."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def __enter__(self):
        try:
            from rosbags.highlevel import AnyReader
            from rosbags.typesys import Stores, get_typestore
        except ImportError:  # pragma: no cover - rosbags is a declared dependency
            raise GyronetError("reading ROS bags needs rosbags: pip install rosbags") from None
        if not self.path.exists():
            raise RecordingError(f"{self.path}: no such file or folder")
        # ROS 2 sqlite bags before Iron carry no message definitions; Imu and Temperature never changed
        try:  # the constructor refuses a file that is no bag at all (format=rosbag on a CSV)
            self.reader = AnyReader([self.path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
            self.reader.open()
        except Exception as err:  # noqa: BLE001 -- rosbags raises many kinds for a damaged bag
            raise RecordingError(f"{self.path}: unreadable ROS bag ({type(err).__name__}: {_first_line(err)})") from None
        return self.reader

    def __exit__(self, *exc) -> None:
        self.reader.close()


def _first_line(err: BaseException) -> str:
    return (str(err).strip().splitlines() or [""])[0][:200]


def _pick(path: Path, reader, given: str | None, types: tuple[str, ...], option: str, none_found: str,
          auto_types: tuple[str, ...] | None = None, advice: str = "") -> str:
    """The topic to read: ``given`` (checked), or the only one of ``auto_types`` in the bag."""
    topics = {name: info.msgtype for name, info in reader.topics.items()}
    listing = ", ".join(f"{n} ({t})" for n, t in sorted(topics.items())) or "no topics"
    if given is not None:
        if given not in topics:
            raise RecordingError(f"{path}: no topic {given!r} (the bag has {listing})")
        if topics[given] not in types:
            raise RecordingError(f"{path}: topic {given} is {topics[given]}, not {' or '.join(types)}")
        return given
    found = sorted(n for n, t in topics.items() if t in (auto_types or types))
    if not found:
        raise RecordingError(f"{path}: {none_found} (the bag has {listing}){advice}")
    if len(found) > 1:
        raise RecordingError(f"{path}: several {(auto_types or types)[0]} topics ({', '.join(found)}); "
                             f"pass rosbag.{option}=<one of them>")
    return found[0]


def _messages(path: Path, reader, topic: str):
    """(message, bag time ns) of one topic; a message that cannot be decoded is a one-line error."""
    connections = [c for c in reader.connections if c.topic == topic]
    for index, (connection, bag_ns, raw) in enumerate(reader.messages(connections=connections)):
        try:
            yield reader.deserialize(raw, connection.msgtype), bag_ns
        except Exception as err:  # noqa: BLE001 -- rosbags' SerdeError and struct errors alike
            raise RecordingError(f"{path}: {topic} message {index}: cannot decode it "
                                 f"({type(err).__name__}: {_first_line(err)})") from None


def _stamp_ns(msg, bag_ns: int, stamp: str) -> int:
    if stamp == "bag" or not hasattr(msg, "header"):
        return int(bag_ns)
    return int(msg.header.stamp.sec) * 1_000_000_000 + int(msg.header.stamp.nanosec)


def _read_imu(path: Path, reader, topic: str, stamp: str) -> tuple[np.ndarray, dict, dict]:
    """IMU stamps (ns, sorted), contract columns and metadata."""
    if stamp not in STAMPS:
        raise GyronetError(f"rosbag stamp must be one of {', '.join(STAMPS)}, got {stamp!r}")
    count = reader.topics[topic].msgcount
    stamps, table, frame_id = np.zeros(count, dtype=np.int64), np.zeros((count, 7)), ""
    n = 0
    for n, (msg, bag_ns) in enumerate(_messages(path, reader, topic), start=1):
        if n > count:  # pragma: no cover - the bag's index undercounts: grow
            stamps, table = np.resize(stamps, 2 * n), np.resize(table, (2 * n, 7))
        rate, acc = msg.angular_velocity, msg.linear_acceleration
        stamps[n - 1] = _stamp_ns(msg, bag_ns, stamp)
        table[n - 1] = (rate.x, rate.y, rate.z, acc.x, acc.y, acc.z, msg.linear_acceleration_covariance[0])
        frame_id = frame_id or msg.header.frame_id
    if n == 0:
        raise RecordingError(f"{path}: topic {topic} has no messages")
    stamped = _checked_stamps(path, topic, stamps[:n], stamp)
    stamp_ns, table = stamps[:n][stamped], table[:n][stamped]
    order = np.argsort(stamp_ns, kind="stable")
    reordered = int(np.count_nonzero(order != np.arange(len(order))))
    stamp_ns, table = stamp_ns[order], table[order]
    origin_ns = int(stamp_ns[0])
    # time_s = (stamp - first stamp) / 1e9, exact in integers before the one division
    columns = {"time_s": (stamp_ns - origin_ns).astype(np.float64) * 1e-9}
    for i, name in enumerate(GYRO_COLUMNS):
        columns[name] = degrees(table[:, i])
    if np.any(table[:, 6] != -1.0):
        for i, name in enumerate(ACC_COLUMNS):
            # acc_g = acc_m_s2 / g0
            columns[name] = table[:, 3 + i] / STANDARD_GRAVITY_M_S2
    lost, breaks = _lost_samples(stamp_ns)
    if lost:
        log.warning("%s: %s: %d sample(s) lost by the stamps (%d break(s) over %g intervals)", path.name, topic,
                    lost, breaks, BREAK_FACTOR)
    if reordered:
        log.info("%s: %s: %d message(s) recorded out of stamp order, sorted", path.name, topic, reordered)
    meta = {"sensor": f"ROS {topic}" + (f" (frame {frame_id})" if frame_id else ""), "ros_imu_topic": topic,
            "ros_frame_id": frame_id or None, "ros_stamp": stamp, "stamp_origin_ns": origin_ns,
            "time_base": f"{stamp} stamp minus stamp_origin_ns, s", "lost_samples": lost, "reordered": reordered}
    meta["zero_stamps"] = int(n - len(stamp_ns))
    return stamp_ns, columns, meta


def _checked_stamps(path: Path, topic: str, stamp_ns: np.ndarray, stamp: str) -> np.ndarray:
    """Which messages have a stamp: a zero header stamp among real ones (a driver's first message) is none."""
    if stamp == "header" and not np.any(stamp_ns):
        raise RecordingError(f"{path}: every header stamp on {topic} is zero (the driver does not fill it); "
                             "pass rosbag.stamp=bag to use the time each message was recorded")
    stamped = stamp_ns != 0 if stamp == "header" else np.ones(len(stamp_ns), dtype=bool)
    if not stamped.all():
        log.warning("%s: %s: %d message(s) with a zero header stamp left out", path.name, topic, np.sum(~stamped))
    return stamped


def _lost_samples(stamp_ns: np.ndarray) -> tuple[int, int]:
    """Samples missing between stamps (k median intervals: k - 1 lost), and the breaks among them."""
    if len(stamp_ns) < 3:
        return 0, 0
    step = np.diff(stamp_ns).astype(np.float64)
    median = float(np.median(step))
    if median <= 0:
        return 0, 0
    intervals = np.rint(step / median)
    return int(np.clip(intervals - 1, 0, None).sum()), int(np.count_nonzero(step > BREAK_FACTOR * median))


def _read_temperature(path: Path, reader, topic: str, stamp: str) -> tuple[np.ndarray, np.ndarray]:
    """Temperature stamps (ns, sorted) and values (degC)."""
    stamps, values = [], []
    for msg, bag_ns in _messages(path, reader, topic):
        stamps.append(_stamp_ns(msg, bag_ns, stamp))
        values.append(msg.temperature if hasattr(msg, "temperature") else msg.data)
    if not stamps:
        raise RecordingError(f"{path}: temperature topic {topic} has no messages; {TEMP_ADVICE}")
    stamp_ns, values = np.asarray(stamps, dtype=np.int64), np.asarray(values, dtype=np.float64)
    stamped = _checked_stamps(path, topic, stamp_ns, stamp)
    order = np.argsort(stamp_ns[stamped], kind="stable")
    return stamp_ns[stamped][order], values[stamped][order]


def _join_causal(path: Path, imu_ns: np.ndarray, temp_ns: np.ndarray, temp_c: np.ndarray,
                 max_age_s: float | None) -> tuple[np.ndarray, dict[str, int]]:
    """Each IMU sample's latest temperature at or before it (NaN when none or too old), and the drop counts."""
    if max_age_s is None:
        max_age_s = BREAK_FACTOR * float(np.median(np.diff(temp_ns))) * 1e-9 if len(temp_ns) > 1 else np.inf
    # index of the last temperature stamped at or before each IMU stamp; -1: none yet
    latest = np.searchsorted(temp_ns, imu_ns, side="right") - 1
    before = latest < 0
    age_s = (imu_ns - temp_ns[np.clip(latest, 0, None)]) * 1e-9
    stale = ~before & (age_s > max_age_s)
    if (before | stale).all():
        raise RecordingError(
            f"{path}: no IMU sample has a temperature at or up to {max_age_s:.3g} s before it (IMU stamps "
            f"{imu_ns[0]}..{imu_ns[-1]} ns, temperature {temp_ns[0]}..{temp_ns[-1]} ns); if the two use "
            "different clocks, pass rosbag.stamp=bag, or raise rosbag.temp_max_age_s")
    joined = np.where(before | stale, np.nan, temp_c[np.clip(latest, 0, None)])
    return joined, {"before_first_temp": int(before.sum()), "stale_temp": int(stale.sum())}


def _sha256(path: Path) -> str:
    """sha256 of the bag file, or of a bag folder's files in name order."""
    digest = hashlib.sha256()
    for part in sorted(p for p in path.iterdir() if p.is_file()) if path.is_dir() else [path]:
        with open(part, "rb") as handle:
            for block in iter(lambda: handle.read(1 << 20), b""):
                digest.update(block)
    return digest.hexdigest()


__all__ = ["import_rosbag", "is_rosbag", "read_rates"]
