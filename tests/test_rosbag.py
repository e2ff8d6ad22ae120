"""ROS bag import (gyronet.recordings.importers.rosbag): bags written with rosbags' own Writers, in all three
storage formats, read back; topic choice, the causal temperature join, lost samples, one-line errors;
convert.py and allan.py on a bag."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from rosbags.rosbag1 import Writer as Writer1
from rosbags.rosbag2 import StoragePlugin, Writer as Writer2
from rosbags.typesys import Stores, get_typestore

from gyronet.recordings.data import load_recording  # noqa: E402
from gyronet.errors import RecordingError  # noqa: E402
from gyronet.recordings.importers import detect_format, import_recording  # noqa: E402
from gyronet.recordings.importers.rosbag import import_rosbag, read_rates  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
G0 = 9.80665
T0_NS = 1_700_000_000_123_456_789  # a Unix-time stamp: microseconds must survive it
FORMATS = ("bag", "db3", "mcap")


def imu_stream(n: int = 200, fs_hz: float = 50.0, seed: int = 0) -> dict:
    """IMU samples: stamps (ns, with 3 us jitter), rates rad/s, specific force m/s^2."""
    rng = np.random.default_rng(seed)
    stamp_ns = T0_NS + np.round(np.arange(n) * 1e9 / fs_hz + rng.uniform(-3e3, 3e3, n)).astype(np.int64)
    return {"stamp_ns": stamp_ns, "rate_rad_s": rng.normal(0.0, 0.01, (n, 3)) + [0.001, -0.002, 0.003],
            "acc_m_s2": rng.normal(0.0, 0.05, (n, 3)) + [0.0, 0.0, G0]}


def temp_stream(start_ns: int, n: int = 6, interval_s: float = 1.0) -> dict:
    """A temperature topic at 1 Hz, rising 0.5 degC a message."""
    return {"stamp_ns": start_ns + (np.arange(n) * interval_s * 1e9).astype(np.int64),
            "temp_c": 20.0 + 0.5 * np.arange(n)}


def write_bag(path: Path, storage: str, imus: dict[str, dict], temps: dict[str, dict] | None = None,
              temp_type: str = "sensor_msgs/msg/Temperature", acc_covariance: float = 0.0) -> Path:
    """A bag with rosbags' Writer: ``.bag`` (ROS 1), or a ROS 2 folder with a ``.db3`` or ``.mcap`` file.

    Each message is recorded 2 ms after its header stamp (or at ``imu["received_ns"]``), in receive order.
    """
    ros1 = storage == "bag"
    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    types = store.types
    serialize = store.serialize_ros1 if ros1 else store.serialize_cdr
    if ros1:
        writer = Writer1(path.with_suffix(".bag"))
    else:
        plugin = StoragePlugin.SQLITE3 if storage == "db3" else StoragePlugin.MCAP
        writer = Writer2(path, version=9, storage_plugin=plugin)

    def header(stamp_ns: int):
        stamp = types["builtin_interfaces/msg/Time"](sec=int(stamp_ns // 10**9), nanosec=int(stamp_ns % 10**9))
        extra = {"seq": 0} if ros1 else {}
        return types["std_msgs/msg/Header"](**extra, stamp=stamp, frame_id="imu_link")

    vector = types["geometry_msgs/msg/Vector3"]
    records = []
    with writer:
        for topic, imu in imus.items():
            conn = writer.add_connection(topic, "sensor_msgs/msg/Imu", typestore=store)
            received_ns = imu.get("received_ns", imu["stamp_ns"] + 2_000_000)
            for stamp_ns, rate, acc, bag_ns in zip(imu["stamp_ns"], imu["rate_rad_s"], imu["acc_m_s2"], received_ns):
                msg = types["sensor_msgs/msg/Imu"](
                    header=header(stamp_ns), orientation=types["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
                    orientation_covariance=np.full(9, -1.0), angular_velocity=vector(x=rate[0], y=rate[1], z=rate[2]),
                    angular_velocity_covariance=np.zeros(9), linear_acceleration=vector(x=acc[0], y=acc[1], z=acc[2]),
                    linear_acceleration_covariance=np.full(9, acc_covariance))
                records.append((int(bag_ns), conn, serialize(msg, "sensor_msgs/msg/Imu")))
        for topic, temp in (temps or {}).items():
            conn = writer.add_connection(topic, temp_type, typestore=store)
            for stamp_ns, value in zip(temp["stamp_ns"], temp["temp_c"]):
                if temp_type == "sensor_msgs/msg/Temperature":
                    msg = types[temp_type](header=header(stamp_ns), temperature=float(value), variance=0.0)
                else:
                    msg = types[temp_type](data=float(value))
                records.append((int(stamp_ns) + 2_000_000, conn, serialize(msg, temp_type)))
        for bag_ns, conn, raw in sorted(records, key=lambda r: r[0]):
            writer.write(conn, bag_ns, raw)
    return path.with_suffix(".bag") if ros1 else path


def storage_file(bag: Path, storage: str) -> Path:
    """The bag's data file: the .bag itself, or the .db3 / .mcap inside the ROS 2 folder."""
    return bag if storage == "bag" else next(bag.glob(f"*.{storage}"))


@pytest.mark.parametrize("storage", FORMATS)
def test_round_trip_values_units_and_stamps(tmp_path, storage):
    imu = imu_stream()
    temp = temp_stream(T0_NS - 500_000_000)
    bag = write_bag(tmp_path / "rec", storage, {"/imu/data": imu}, {"/imu/temperature": temp})
    for source in {bag, storage_file(bag, storage)}:  # a ROS 2 bag: its folder and its data file
        assert detect_format(source) == "rosbag"
        rec = import_recording(source)
        assert len(rec) == len(imu["stamp_ns"])
        # time_s from the header stamps (not the bag's +2 ms), to the nanosecond
        np.testing.assert_allclose(rec.time_s, (imu["stamp_ns"] - imu["stamp_ns"][0]) * 1e-9, rtol=0, atol=1e-9)
        assert rec.meta["stamp_origin_ns"] == str(imu["stamp_ns"][0])
        np.testing.assert_allclose(rec.gyro_dps, np.degrees(imu["rate_rad_s"]), rtol=1e-12)
        acc_g = np.column_stack([rec.columns[f"acc_{a}_g"] for a in "xyz"])
        np.testing.assert_allclose(acc_g, imu["acc_m_s2"] / G0, rtol=1e-12)
        # causal: the latest temperature stamped at or before each sample
        expected = temp["temp_c"][np.searchsorted(temp["stamp_ns"], imu["stamp_ns"], side="right") - 1]
        np.testing.assert_array_equal(rec.temp_c, expected)
        assert rec.meta["source_format"] == "rosbag" and rec.meta["dropped_rows"] == "0"
        assert rec.meta["ros_imu_topic"] == "/imu/data" and rec.meta["ros_temp_topic"] == "/imu/temperature"
        assert rec.meta["lost_samples"] == "0" and float(rec.meta["fs_hz"]) == pytest.approx(50.0, rel=1e-3)


def test_join_never_looks_ahead_and_counts_what_has_no_temperature(tmp_path):
    imu = imu_stream(n=600)  # 12 s
    temp = temp_stream(imu["stamp_ns"][0] + 1_000_000_000, n=4)  # from 1 s to 4 s, then silent: stale after 9 s
    bag = write_bag(tmp_path / "rec", "mcap", {"/imu": imu}, {"/temp": temp})
    rec = import_rosbag(bag)
    before = int((imu["stamp_ns"] < temp["stamp_ns"][0]).sum())
    stale = int((imu["stamp_ns"] > temp["stamp_ns"][-1] + 5 * 1_000_000_000).sum())
    assert before == 50 and stale > 0
    assert rec.meta["dropped_detail"] == f"before_first_temp:{before};stale_temp:{stale}"
    assert len(rec) == 600 - before - stale
    stamp_ns = rec.time_s * 1e9 + imu["stamp_ns"][0]
    for t_ns, value in zip(stamp_ns, rec.temp_c):
        source = temp["stamp_ns"][list(temp["temp_c"]).index(value)]
        assert source <= t_ns + 1 and t_ns - source <= 5e9 + 1
    assert len(import_rosbag(bag, temp_max_age_s=100.0)) == 600 - before


def test_lost_samples_and_receive_order(tmp_path):
    imu = imu_stream(n=300)
    keep = np.ones(300, dtype=bool)
    keep[[10, 11, 12, 100, 250]] = False
    imu = {k: v[keep] for k, v in imu.items()}
    # the recorder received message 50 after 51 (30 ms late at 50 Hz): the import sorts by stamp
    imu["received_ns"] = imu["stamp_ns"] + 2_000_000
    imu["received_ns"][50] += 30_000_000
    bag = write_bag(tmp_path / "rec", "bag", {"/imu": imu}, {"/t": temp_stream(T0_NS - 10**9, n=10)})
    rec = import_rosbag(bag)
    assert rec.meta["lost_samples"] == "5" and rec.meta["reordered"] == "2"
    np.testing.assert_allclose(rec.gyro_dps, np.degrees(imu["rate_rad_s"]), rtol=1e-12)


def test_topic_choice(tmp_path):
    a, b = imu_stream(seed=1), imu_stream(seed=2)
    temps = {"/a/temp": temp_stream(T0_NS - 10**9), "/b/temp": temp_stream(T0_NS - 10**9)}
    bag = write_bag(tmp_path / "two", "db3", {"/a/imu": a, "/b/imu": b}, temps)
    with pytest.raises(RecordingError, match=r"several sensor_msgs/msg/Imu topics \(/a/imu, /b/imu\); "
                                             r"pass rosbag.imu_topic="):
        import_rosbag(bag)
    with pytest.raises(RecordingError, match="pass rosbag.temp_topic="):
        import_rosbag(bag, imu_topic="/b/imu")
    rec = import_rosbag(bag, imu_topic="/b/imu", temp_topic="/b/temp")
    np.testing.assert_allclose(rec.gyro_dps, np.degrees(b["rate_rad_s"]), rtol=1e-12)
    with pytest.raises(RecordingError, match=r"no topic '/c/imu' \(the bag has /a/imu"):
        import_rosbag(bag, imu_topic="/c/imu")
    with pytest.raises(RecordingError, match="topic /a/temp is sensor_msgs/msg/Temperature, not sensor_msgs/msg/Imu"):
        import_rosbag(bag, imu_topic="/a/temp")


def test_a_float_temperature_topic_at_its_bag_time_and_no_accel(tmp_path):
    imu = imu_stream()
    temp = temp_stream(T0_NS - 10**9)
    bag = write_bag(tmp_path / "rec", "mcap", {"/imu": imu}, {"/chip_temp": temp},
                    temp_type="std_msgs/msg/Float32", acc_covariance=-1.0)
    with pytest.raises(RecordingError, match="no sensor_msgs/Temperature topic"):
        import_rosbag(bag)  # not picked by type: a Float32 could be anything
    rec = import_rosbag(bag, temp_topic="/chip_temp")
    assert not any(c.startswith("acc_") for c in rec.columns)  # covariance -1: not provided
    received_ns = temp["stamp_ns"] + 2_000_000
    expected = temp["temp_c"][np.searchsorted(received_ns, imu["stamp_ns"], side="right") - 1]
    np.testing.assert_allclose(rec.temp_c, expected, rtol=1e-6)  # Float32


def test_one_line_errors(tmp_path):
    imu = imu_stream()
    no_temp = write_bag(tmp_path / "no_temp", "db3", {"/imu": imu})
    with pytest.raises(RecordingError) as err:
        import_rosbag(no_temp)
    text = str(err.value)
    assert "\n" not in text and "no sensor_msgs/Temperature topic (the bag has /imu (sensor_msgs/msg/Imu))" in text
    assert "a recording needs temp_c" in text and "sensor_msgs/Temperature topic" in text
    assert len(read_rates(no_temp)) == len(imu["stamp_ns"])  # Allan analysis needs no temperature

    only_temp = write_bag(tmp_path / "only_temp", "bag", {}, {"/t": temp_stream(T0_NS)})
    with pytest.raises(RecordingError, match=r"no sensor_msgs/Imu topic \(the bag has /t \(sensor_msgs/msg/Temperature\)\)"):
        import_rosbag(only_temp)

    unstamped = dict(imu, stamp_ns=np.zeros_like(imu["stamp_ns"]))
    zero = write_bag(tmp_path / "zero", "mcap", {"/imu": unstamped}, {"/t": temp_stream(T0_NS)})
    with pytest.raises(RecordingError, match="every header stamp on /imu is zero .*pass rosbag.stamp=bag"):
        import_rosbag(zero)

    other_clock = write_bag(tmp_path / "clock", "mcap", {"/imu": imu}, {"/t": temp_stream(10**9)})
    with pytest.raises(RecordingError, match="different clocks, pass rosbag.stamp=bag"):
        import_rosbag(other_clock)

    damaged = tmp_path / "damaged.bag"
    damaged.write_bytes(b"#ROSBAG V2.0\n" + b"\x00\x17garbage" * 10)
    with pytest.raises(RecordingError, match=r"damaged.bag: unreadable ROS bag \("):
        import_rosbag(damaged)


def _run(script: str, *overrides: str, cwd: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    return subprocess.run([sys.executable, str(ROOT / "scripts" / script), *overrides, f"hydra.run.dir={cwd / 'hydra'}"],
                          cwd=cwd, env=env, capture_output=True, text=True, timeout=300)


def test_allan_from_a_bag_equals_allan_from_its_csv(tmp_path):
    from gyronet.allan import allan_report
    from gyronet.recordings.importers import convert

    imu = imu_stream(n=3000, fs_hz=50.0)
    bag = write_bag(tmp_path / "rec", "mcap", {"/imu": imu}, {"/t": temp_stream(T0_NS - 10**9, n=70)})
    convert(bag, tmp_path / "rec.csv")
    back = load_recording(tmp_path / "rec.csv")
    from_bag = read_rates(bag)
    from_csv = allan_report(back.time_s, back.gyro_dps)
    report = allan_report(from_bag.time_s, from_bag.gyro_dps)
    for axis in "xyz":
        np.testing.assert_allclose(report[axis]["adev_dps"], from_csv[axis]["adev_dps"], rtol=1e-6)
    # white rate noise of 0.01 rad/s at 50 Hz: N = sigma / sqrt(fs), deg/sqrt(h)
    assert report["x"]["arw_deg_rthr"] == pytest.approx(np.degrees(0.01) / np.sqrt(50.0) * 60.0, rel=0.15)


def test_convert_script_on_a_bag_folder(tmp_path):
    imu = imu_stream(n=300)
    write_bag(tmp_path / "rec", "db3", {"/imu": imu}, {"/imu/temperature": temp_stream(T0_NS - 10**9, n=10)})
    done = _run("convert.py", "input=rec", "output=rec.csv", "rosbag.stamp=header", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    back = load_recording(tmp_path / "rec.csv")
    np.testing.assert_allclose(back.time_s, (imu["stamp_ns"] - imu["stamp_ns"][0]) * 1e-9, rtol=0, atol=1e-9)
    np.testing.assert_allclose(back.gyro_dps, np.degrees(imu["rate_rad_s"]), rtol=1e-9)
    assert back.meta["source_format"] == "rosbag" and back.meta["source_file"] == "rec"
    assert "rec (rosbag): 300 samples kept" in done.stdout + done.stderr  # the folder, not its metadata.yaml


@pytest.mark.slow
def test_allan_script_reads_bags_and_convert_refuses_one_without_temperature(tmp_path):
    imu = imu_stream(n=3000, fs_hz=50.0)
    bag = write_bag(tmp_path / "rec", "bag", {"/imu": imu}, {"/imu/temperature": temp_stream(T0_NS - 10**9, n=70)})
    done = _run("allan.py", f"input={bag}", "output=bag.json", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    report = allan_report_of(read_rates(bag))
    from_script = json.loads((tmp_path / "bag.json").read_text())
    for axis in "xyz":
        np.testing.assert_allclose(from_script[axis]["adev_dps"], report[axis]["adev_dps"], rtol=1e-9)

    no_temp = write_bag(tmp_path / "no_temp", "mcap", {"/imu": imu})
    done = _run("allan.py", f"input={no_temp}", "output=nt.json", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    assert json.loads((tmp_path / "nt.json").read_text())["x"]["adev_dps"] == from_script["x"]["adev_dps"]
    failed = _run("convert.py", f"input={no_temp}", "output=x.csv", cwd=tmp_path)
    assert failed.returncode == 2 and "Traceback" not in failed.stderr
    assert failed.stderr.strip().splitlines()[-1].startswith(f"error: {no_temp}: no sensor_msgs/Temperature topic")
    assert not (tmp_path / "x.csv").exists()


def allan_report_of(recording):
    from gyronet.allan import allan_report

    return allan_report(recording.time_s, recording.gyro_dps)


def test_a_zero_header_stamp_among_real_ones_is_left_out_not_the_time_base(tmp_path):
    """A driver's first message often carries stamp 0: it became the origin, every time_s a Unix time."""
    imu = imu_stream()
    imu["stamp_ns"] = imu["stamp_ns"].copy()
    imu["stamp_ns"][0] = 0
    imu["received_ns"] = T0_NS + np.arange(len(imu["stamp_ns"])) * 20_000_000
    bag = write_bag(tmp_path / "rec", "bag", {"/imu/data": imu}, {"/imu/temperature": temp_stream(T0_NS - 10**9)})
    rec = import_recording(bag)
    assert len(rec) == len(imu["stamp_ns"]) - 1 and rec.meta["zero_stamps"] == "1"
    assert rec.meta["stamp_origin_ns"] == str(imu["stamp_ns"][1]) and rec.time_s[-1] < 10.0
