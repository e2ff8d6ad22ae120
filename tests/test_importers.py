"""Importers: psim TVC CSV, LPMS log CSV, PX4 ULog, conforming CSV; and scripts/convert.py end to end."""
from __future__ import annotations

import math
import re
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from gyronet.recordings.data import load_recording, write_recording
from gyronet.errors import GyronetError, RecordingError
from gyronet.recordings.importers import convert, detect_format, import_recording

ROOT = Path(__file__).resolve().parents[1]
PSIM_DIR = Path(__file__).resolve().parents[2] / "shared" / "data" / "real" / "psim-tvc"
PSIM_CSV = PSIM_DIR / "TVCtest3_7_20.csv"
CHAMBER_CSV = PSIM_DIR / "ETUColdTest3_7_20.csv"
needs_psim = pytest.mark.skipif(not PSIM_CSV.is_file(), reason="shared/data/real/psim-tvc not present")
G0 = 9.80665


def one_line_error(excinfo) -> str:
    text = str(excinfo.value)
    assert "\n" not in text and "Traceback" not in text
    return text


# ----------------------------------------------------------------------------------------- psim

PSIM_HEADER = "time (ms),mag1x [T],mag1y [T],mag1z [T],gyrox rad/s,gyroy rad/s,gyroz rad/s,temp"


def write_psim(path: Path, rows: list[str], header: str = PSIM_HEADER) -> Path:
    path.write_text(header + "\n" + "\n".join(rows) + "\n")
    return path


def test_psim_fixture_converts_units_and_drops_the_spike(tmp_path):
    src = write_psim(tmp_path / "tvc.csv", [
        "1000,-1.46E-05,2.72E-05,2.82E-05,-6.53E-02,5.71E-02,2.96E-02,65236",
        "1020,-1.46E-05,2.69E-05,2.78E-05,-9.00E-02,5.65E-02,2.90E-02,65233",  # a spike
        "1040,-1.43E-05,2.68E-05,2.82E-05,-6.48E-02,5.79E-02,2.86E-02,256",
        "1040,-1.43E-05,2.68E-05,2.82E-05,-6.48E-02,5.79E-02,2.86E-02,256",  # duplicate time
        "1060,-1.43E-05,2.68E-05,,-6.48E-02,5.79E-02,2.86E-02,0",  # empty cell
    ])
    rec = import_recording(src, "psim")
    np.testing.assert_allclose(rec.time_s, [1.0, 1.04])
    # T = 25 + int16(temp)/256: 65236 is -300 as int16
    np.testing.assert_allclose(rec.temp_c, [25 - 300 / 256, 26.0])
    np.testing.assert_allclose(rec.columns["gyro_x_dps"], np.degrees(0.5 * np.array([-0.0653, -0.0648])))
    np.testing.assert_allclose(rec.columns["mag1_x_t"], [-1.46e-5, -1.43e-5])
    assert rec.meta["dropped_rows"] == "3"
    assert rec.meta["dropped_detail"] == "spike:1;nan:1;duplicate_time:1"
    assert rec.meta["source_format"] == "psim" and rec.meta["source_file"] == "tvc.csv"
    kept = import_recording(src, "psim", drop_spikes=False, gyro_scale=1.0)
    assert len(kept) == 3 and kept.columns["gyro_x_dps"][1] == pytest.approx(math.degrees(-0.09))


@pytest.mark.parametrize("header, rows, expected", [
    (PSIM_HEADER.replace(",temp", ""), ["1000,0,0,0,0.1,0.1,0.1"], "missing column(s) temp"),
    (PSIM_HEADER.replace("gyrox rad/s", "gyrox deg/s"), ["1000,0,0,0,0.1,0.1,0.1,256"], "gyro unit 'deg/s'"),
    (PSIM_HEADER, ["1000,0,0,0,0.1,0.1,0.1,23.5"], "not a raw OUT_TEMP word"),
    (PSIM_HEADER, ["1000,0,0,0,0.1,0.1,0.1,256", "1020,0,0,0,abc,0.1,0.1,256", "1040,0,0,0,0.1,0.1,0.1,256"],
     "line 3: column 'gyrox rad/s': non-numeric value 'abc'"),
    (PSIM_HEADER, ["2000,0,0,0,0.1,0.1,0.1,256", "1000,0,0,0,0.1,0.1,0.1,256"], "goes back"),
])
def test_psim_malformed_inputs_give_one_line_errors(tmp_path, header, rows, expected):
    src = write_psim(tmp_path / "bad.csv", rows, header)
    with pytest.raises(RecordingError) as excinfo:
        import_recording(src, "psim")
    text = one_line_error(excinfo)
    assert str(src) in text and expected in text


@needs_psim
def test_real_psim_file_rows_temperature_bursts_and_bias_slope():
    rec = import_recording(PSIM_CSV)
    assert rec.meta["source_format"] == "psim" and rec.meta["fs_hz"] == "50"
    assert len(rec) == 6250 - 3 and rec.meta["dropped_rows"] == "3"
    assert rec.temp_c[0] == pytest.approx(23.9, abs=0.1) and rec.temp_c[-1] == pytest.approx(15.6, abs=0.1)
    burst = np.concatenate([[0], np.cumsum(np.diff(rec.time_s) > 1.0)])
    assert burst[-1] + 1 == 25
    temp_mean = np.array([rec.temp_c[burst == k].mean() for k in range(25)])
    slopes = {}
    for axis in "xyz":
        bias = np.array([rec.columns[f"gyro_{axis}_dps"][burst == k].mean() for k in range(25)])
        slopes[axis] = np.polyfit(temp_mean, bias, 1)[0] * 1000.0  # mdps/degC
    # the data's PROVENANCE.md: x about +30 mdps/degC, y about -14 (the authors' own reading of the test)
    assert slopes["x"] == pytest.approx(30.0, abs=3.0)
    assert slopes["y"] == pytest.approx(-14.0, abs=3.0)
    assert abs(slopes["z"]) < 5.0
    assert len(import_recording(PSIM_CSV, "psim", drop_spikes=False)) == 6250


def test_a_chamber_log_is_converted_and_interpolated_at_its_assumed_offset(tmp_path):
    """The chamber-log path without the real file: degF and degC probes, an offset, a sample outside, not a log."""
    src = write_psim(tmp_path / "tvc.csv", [
        "1000,-1.46E-05,2.72E-05,2.82E-05,-6.53E-02,5.71E-02,2.96E-02,256",
        "1020,-1.46E-05,2.69E-05,2.78E-05,-6.53E-02,5.65E-02,2.90E-02,256",
    ])
    chamber = tmp_path / "chamber.csv"
    chamber.write_text("\ufeffTime,F2 (F),C1 (C),,\n15:45,68,20.0,,\n15:50,77,25.0,,\nnotes,,,,\n")
    # the first sample 150 s after the 15:45 row: halfway to 15:50
    rec = import_recording(src, "psim", chamber_log=chamber, chamber_offset_s=-150.0)
    np.testing.assert_allclose(rec.columns["chamber_f2_c"], [22.5, 22.5 + 5.0 / 300.0 * 0.02], rtol=1e-12)
    np.testing.assert_allclose(rec.columns["chamber_c1_c"], [22.5, 22.5 + 5.0 / 300.0 * 0.02], rtol=1e-12)
    assert "-150.0 s" in rec.meta["chamber_alignment"] and rec.meta["chamber_log"] == "chamber.csv"
    with pytest.raises(RecordingError, match=re.escape("2 sample(s) fall outside the chamber log (15:45..15:50)")):
        import_recording(src, "psim", chamber_log=chamber, chamber_offset_s=1.0)  # the log starts after them
    (tmp_path / "not_a_log.csv").write_text("when,what\n1,2\n")
    with pytest.raises(RecordingError, match="not a chamber log"):
        import_recording(src, "psim", chamber_log=tmp_path / "not_a_log.csv")


@needs_psim
def test_real_chamber_log_is_attached_with_its_assumed_alignment(tmp_path):
    rec = import_recording(PSIM_CSV, "psim", chamber_log=CHAMBER_CSV)
    assert {"chamber_f2_c", "chamber_f3_c", "chamber_f4_c", "chamber_c1_c"} <= set(rec.columns)
    assert rec.columns["chamber_f2_c"][0] == pytest.approx((70 - 32) * 5 / 9)  # 15:45 row, 70 degF
    assert rec.columns["chamber_c1_c"][0] == pytest.approx(21.5)
    assert "assumed" in rec.meta["chamber_alignment"]
    with pytest.raises(RecordingError, match="outside the chamber log"):
        import_recording(PSIM_CSV, "psim", chamber_log=CHAMBER_CSV, chamber_offset_s=5000.0)


# ----------------------------------------------------------------------------------------- lpms

LPMS_LATER = ("SensorId, TimeStamp (s), FrameNumber, AccX (g), AccY (g), AccZ (g), GyroX (deg/s), GyroY (deg/s), "
              "GyroZ (deg/s), MagX (uT), MagY (uT), MagZ (uT), EulerX (deg), EulerY (deg), EulerZ (deg), QuatW, "
              "QuatX, QuatY, QuatZ, LinAccX (g), LinAccY (g), LinAccZ (g), Pressure (kPa), Altitude (m), "
              "Temperature (degC), HeaveMotion (m)")
LPMS_EARLY = LPMS_LATER.replace("QuatW, QuatX, QuatY, QuatZ", "QuatX, QuatY, QuatZ, QuatW").replace(
    "(g), LinAccY (g), LinAccZ (g)", "(m/s^2), LinAccY (m/s^2), LinAccZ (m/s^2)").replace("(kPa)", "(hPa)")
LPMS_OPENZEN = LPMS_LATER.replace("SensorId", "ImageIndex")
LPMS_IOS = LPMS_LATER.replace("EulerX (deg)", "EulerX(deg)").replace("Temperature (degC)", "Temperature(degC)")
LPMS_RAD = LPMS_LATER.replace("(deg/s)", "(rad/s)")


def lpms_rows(n: int = 5, sensor: int = 1, gyro: float = 0.5, temp_c: float = 31.25, fs_hz: float = 100.0,
              pressure: float = 0.0, temp_step_c: float = 0.01) -> list[str]:
    rows = []
    for i in range(n):
        d = 0.001 * i  # enabled outputs move a little from row to row; disabled ones are constant
        values = [sensor, i / fs_hz, i, 0.01 + d, -0.02, -1.0, gyro, -gyro, 2 * gyro, -5.5 + d, -19.5, -50.3,
                  -0.4 + d, -0.02, 13.98, 0.99 - d, 0.003, 0.0006, -0.12, 0.001 + d, -0.001, 0.002, pressure, 0.0,
                  temp_c + temp_step_c * i, 0.0]
        rows.append(", ".join(f"{v:.6f}" if isinstance(v, float) else str(v) for v in values))
    return rows


def with_cell(rows: list[str], row: int, column: int, text: str) -> list[str]:
    cells = rows[row].split(", ")
    cells[column] = text
    return rows[:row] + [", ".join(cells)] + rows[row + 1:]


def write_lpms(path: Path, header: str, rows: list[str]) -> Path:
    path.write_text(header + "\n" + "\n".join(rows) + "\n")
    return path


@pytest.mark.parametrize("header", [LPMS_LATER, LPMS_EARLY, LPMS_OPENZEN, LPMS_IOS])
def test_lpms_header_variants_give_the_same_core_columns(tmp_path, header):
    src = write_lpms(tmp_path / "log.csv", header, lpms_rows(pressure=101.3))
    assert detect_format(src) == "lpms"
    rec = import_recording(src)
    np.testing.assert_allclose(rec.time_s, np.arange(5) / 100.0)
    np.testing.assert_allclose(rec.temp_c, 31.25 + 0.01 * np.arange(5))
    np.testing.assert_allclose(rec.gyro_dps, np.tile([0.5, -0.5, 1.0], (5, 1)))
    np.testing.assert_allclose(rec.columns["acc_z_g"], -1.0)
    assert {"mag_x_ut", "euler_z_deg", "quat_w", "linacc_x_g", "pressure_kpa"} <= set(rec.columns)
    linacc_scale = 1 / G0 if "m/s^2" in header else 1.0
    assert rec.columns["linacc_x_g"][0] == pytest.approx(0.001 * linacc_scale)
    assert rec.columns["pressure_kpa"][0] == pytest.approx(10.13 if "(hPa)" in header else 101.3)
    assert rec.meta["fs_hz"] == "100" and rec.meta["dropped_rows"] == "0"
    assert "altitude_m" not in rec.columns and "altitude_m" in rec.meta["disabled_outputs"]


def test_lpms_rad_per_s_is_converted_and_bad_rows_are_counted(tmp_path):
    rows = lpms_rows(6, gyro=0.1)
    rows.insert(3, rows[2])  # a repeated time stamp
    rows[-1] = rows[-1][:40]  # logging stopped mid-line
    rec = import_recording(write_lpms(tmp_path / "rad.csv", LPMS_RAD, rows), "lpms")
    np.testing.assert_allclose(rec.columns["gyro_x_dps"], math.degrees(0.1))
    assert len(rec) == 5 and rec.meta["dropped_rows"] == "2"
    assert rec.meta["dropped_detail"] == "nan:1;duplicate_time:1"


def test_an_lpms_log_re_saved_by_a_spreadsheet_or_quoted_reads_the_same(tmp_path):
    rows = lpms_rows(pressure=101.3)
    plain = import_recording(write_lpms(tmp_path / "plain.csv", LPMS_LATER, rows), "lpms")
    german = [";".join(c.replace(".", ",") for c in row.split(", ")) for row in rows]  # a German Excel's save
    quoted = [",".join(f'"{c}"' for c in row.split(", ")) for row in rows]  # Python's csv.QUOTE_ALL
    for name, header, body in (("excel.csv", LPMS_LATER.replace(", ", ";"), german),
                               ("quoted.csv", ",".join(f'"{n}"' for n in LPMS_LATER.split(", ")), quoted)):
        src = write_lpms(tmp_path / name, header, body)
        assert detect_format(src) == "lpms"
        rec = import_recording(src)
        assert set(rec.columns) == set(plain.columns), name
        for column in plain.columns:
            np.testing.assert_allclose(rec.columns[column], plain.columns[column], rtol=1e-12, err_msg=name)


def test_stamps_too_coarse_for_the_rate_are_named(tmp_path, caplog):
    """OpenMAT's float32 time stamp after hours repeats at 400 Hz: a third of the rows went with an INFO line."""
    rows = lpms_rows(60, fs_hz=400.0)
    rows = [", ".join([cells[0], f"{float(cells[1]) // 0.005 * 0.005:.4f}", *cells[2:]])
            for cells in (row.split(", ") for row in rows)]  # stamps on a 5 ms grid
    with caplog.at_level("WARNING", logger="gyronet.recordings.importers"):
        rec = import_recording(write_lpms(tmp_path / "coarse.csv", LPMS_LATER, rows), "lpms")
    assert len(rec) == 30 and "30 of 60 rows repeat the time stamp before them" in caplog.text


def test_lpms_two_sensors_need_a_sensor_id(tmp_path):
    rows = [r for pair in zip(lpms_rows(sensor=1, gyro=0.5), lpms_rows(sensor=2, gyro=-3.0)) for r in pair]
    src = write_lpms(tmp_path / "two.csv", LPMS_LATER, rows)
    with pytest.raises(RecordingError, match=r"holds sensors 1, 2; pass lpms.sensor_id"):
        import_recording(src, "lpms")
    rec = import_recording(src, "lpms", sensor_id=2)
    assert len(rec) == 5 and np.all(rec.columns["gyro_x_dps"] == -3.0)
    with pytest.raises(RecordingError, match=r"lpms.sensor_id must be a SensorId number \(the file has 1, 2\), got 'abc'"):
        import_recording(src, "lpms", sensor_id="abc")
    assert rec.meta["sensor"] == "LP-Research LPMS (SensorId 2)"


def test_lpms_header_without_units_needs_gyro_unit(tmp_path):
    header = "TimeStamp, GyrX, GyrY, GyrZ, Temperature (degC)"
    src = write_lpms(tmp_path / "bare.csv", header, ["0.0, 0.1, 0.2, 0.3, 25", "0.01, 0.1, 0.2, 0.3, 25"])
    with pytest.raises(RecordingError, match="pass lpms.gyro_unit"):
        import_recording(src, "lpms")
    rec = import_recording(src, "lpms", gyro_unit="rad/s")
    assert rec.columns["gyro_z_dps"][0] == pytest.approx(math.degrees(0.3))
    # OpenZen writes "(deg/s)" whatever the sensor sends: the option, given, wins over the header
    src = write_lpms(tmp_path / "said.csv", LPMS_LATER, lpms_rows(gyro=0.1))
    assert import_recording(src, "lpms", gyro_unit="rad/s").columns["gyro_x_dps"][0] == pytest.approx(math.degrees(0.1))
    # and a contract CSV is no LPMS log, though its columns have the names an LPMS log would be given
    with pytest.raises(RecordingError, match="not a usable LPMS log"):
        import_recording(write_lpms(tmp_path / "contract.csv", "time_s,temp_c,gyro_x_dps,gyro_y_dps,gyro_z_dps",
                                    ["0,25,1,2,3", "0.01,25,1,2,3"]), "lpms")


@pytest.mark.parametrize("header, rows, expected", [
    (LPMS_LATER.replace("GyroY (deg/s)", "GyroY (rpm)"), lpms_rows(), "column 'GyroY (rpm)': unit 'rpm'"),
    (LPMS_LATER.replace(", Temperature (degC)", ", Battery (%)"), lpms_rows(), "missing Temperature (degC)"),
    (LPMS_LATER, lpms_rows(3, temp_c=0.0, temp_step_c=0.0), "Temperature is 0 in every row"),
    (LPMS_LATER, with_cell(lpms_rows(3), row=1, column=3, text="x"), "line 3: column 'AccX (g)': non-numeric"),
    ("SensorId, FrameNumber", ["1, 0"], "missing TimeStamp (s)"),
    (LPMS_LATER, lpms_rows(2) + [lpms_rows(3)[2] + ", 7.0, 8.0"], "malformed row (Error tokenizing data"),
])
def test_lpms_malformed_inputs_give_one_line_errors(tmp_path, header, rows, expected):
    src = write_lpms(tmp_path / "bad.csv", header, rows)
    with pytest.raises(RecordingError) as excinfo:
        import_recording(src, "lpms")
    text = one_line_error(excinfo)
    assert str(src) in text and expected in text


# ----------------------------------------------------------------------------------------- ulog

def _msg(kind: str, payload: bytes) -> bytes:
    """One ULog message: uint16 size, uint8 type, payload (pyulog's core.py, ULog file format)."""
    return struct.pack("<HB", len(payload), ord(kind)) + payload


GYRO_FORMAT = ("sensor_gyro:uint64_t timestamp;uint64_t timestamp_sample;uint32_t device_id;float x;float y;"
               "float z;float temperature;uint32_t error_count;")
ACCEL_FORMAT = GYRO_FORMAT.replace("sensor_gyro", "sensor_accel")
FIFO_FORMAT = ("sensor_gyro_fifo:uint64_t timestamp;uint64_t timestamp_sample;uint32_t device_id;float dt;"
               "float scale;uint8_t samples;int16_t[4] x;int16_t[4] y;int16_t[4] z;")


def ulog_bytes(gyro: dict[int, list[tuple]], accel: list[tuple] = (), fifo: list[tuple] = ()) -> bytes:
    """A minimal valid ULog: header, info, formats, subscriptions, data messages in time order.

    ``gyro`` maps instance -> [(t_us, x, y, z, temp_c)], rad/s; ``accel`` [(t_us, x, y, z, temp)]
    m/s^2 for instance 0; ``fifo`` [(t_us, dt_us, scale, samples, xs, ys, zs)] for instance 0.
    """
    out = b"ULog\x01\x12\x35" + struct.pack("<BQ", 1, 0)
    key = b"char[4] ver_hw"
    out += _msg("I", struct.pack("<B", len(key)) + key + b"TEST")
    for fmt in (GYRO_FORMAT, ACCEL_FORMAT, FIFO_FORMAT):
        out += _msg("F", fmt.encode())
    subscriptions = [(i, "sensor_gyro") for i in sorted(gyro)] + [(0, "sensor_accel"), (0, "sensor_gyro_fifo")]
    msg_ids = {}
    for msg_id, (instance, name) in enumerate(subscriptions):
        msg_ids[(name, instance)] = msg_id
        out += _msg("A", struct.pack("<BH", instance, msg_id) + name.encode())
    records = []
    for instance, samples in gyro.items():
        for t, x, y, z, temp in samples:
            body = struct.pack("<QQIffffI", t + 50, t, 0x220000 + instance, x, y, z, temp, 0)
            records.append((t, struct.pack("<H", msg_ids[("sensor_gyro", instance)]) + body))
    for t, x, y, z, temp in accel:
        body = struct.pack("<QQIffffI", t + 50, t, 0x210000, x, y, z, temp, 0)
        records.append((t, struct.pack("<H", msg_ids[("sensor_accel", 0)]) + body))
    for t, dt, scale, n, xs, ys, zs in fifo:
        body = struct.pack("<QQIffB4h4h4h", t + 50, t, 0x220000, dt, scale, n, *xs, *ys, *zs)
        records.append((t, struct.pack("<H", msg_ids[("sensor_gyro_fifo", 0)]) + body))
    for _, payload in sorted(records, key=lambda r: r[0]):
        out += _msg("D", payload)
    return out


def gyro_samples(n: int = 10, dt_us: int = 2500, t0_us: int = 1_000_000, offset: float = 0.0) -> list[tuple]:
    return [(t0_us + i * dt_us, 0.01 + offset, -0.02, 0.03 * i, 30.0 - 0.1 * i) for i in range(n)]


def test_ulog_round_trip(tmp_path):
    src = tmp_path / "thermal.ulg"
    src.write_bytes(ulog_bytes({0: gyro_samples(), 1: gyro_samples(offset=1.0)}))
    assert detect_format(src) == "ulog"
    rec = import_recording(src, accel=False)
    np.testing.assert_allclose(rec.time_s, 1.0 + 0.0025 * np.arange(10))
    np.testing.assert_allclose(rec.columns["gyro_x_dps"], math.degrees(0.01), rtol=1e-6)
    np.testing.assert_allclose(rec.columns["gyro_z_dps"], np.degrees(np.float32(0.03) * np.arange(10)), rtol=1e-6)
    np.testing.assert_allclose(rec.temp_c, 30.0 - 0.1 * np.arange(10), rtol=1e-6)
    assert rec.meta["fs_hz"] == "400" and rec.meta["px4_board"] == "TEST"
    assert rec.meta["px4_device_id"] == str(0x220000)
    other = import_recording(src, "ulog", instance=1, accel=False)
    np.testing.assert_allclose(other.columns["gyro_x_dps"], math.degrees(1.01), rtol=1e-6)
    with pytest.raises(RecordingError, match=r"no sensor_gyro instance 2 .*instance\(s\) 0, 1"):
        import_recording(src, "ulog", instance=2)


def test_ulog_accel_is_merged_by_nearest_timestamp(tmp_path):
    accel = [(1_000_000 + i * 5000 + 300, 0.0, 0.0, -G0 * (1 + 0.01 * i), 31.0) for i in range(5)]
    src = tmp_path / "acc.ulg"
    src.write_bytes(ulog_bytes({0: gyro_samples(16)}, accel=accel))
    rec = import_recording(src, "ulog")
    # gyro every 2.5 ms from 1.0 s; accel every 5 ms from 1.0003 s to 1.0203 s: the last three gyro
    # samples (1.0325 s on) are more than two accel intervals (10 ms) from any accel sample
    expected = [-(1 + 0.01 * min(round((i * 2500 - 300) / 5000), 4)) for i in range(len(rec))]
    np.testing.assert_allclose(rec.columns["acc_z_g"], expected, rtol=1e-6)
    assert rec.columns["accel_temp_c"][0] == pytest.approx(31.0)
    assert len(rec) == 13 and rec.meta["dropped_detail"] == "no_accel:3"


def test_ulog_fifo_samples_are_expanded_and_take_sensor_gyro_temperature(tmp_path):
    fifo = [(1_000_000 + k * 4000, 1000.0, 0.001, 4, [10 * k + i for i in range(4)], [0] * 4, [-5] * 4)
            for k in range(3)]
    src = tmp_path / "fifo.ulg"
    src.write_bytes(ulog_bytes({0: gyro_samples(10, dt_us=2500, t0_us=990_000)}, fifo=fifo))
    rec = import_recording(src, "ulog", topic="sensor_gyro_fifo", accel=False)
    # the last of each message's 4 samples sits at timestamp_sample, the others dt = 1 ms before it
    np.testing.assert_allclose(rec.time_s, 0.997 + 0.001 * np.arange(12))
    counts = np.array([10 * k + i for k in range(3) for i in range(4)])
    np.testing.assert_allclose(rec.columns["gyro_x_dps"], np.degrees(np.float32(0.001) * counts), rtol=1e-6)
    np.testing.assert_allclose(rec.columns["gyro_z_dps"], np.degrees(np.float32(0.001) * -5), rtol=1e-6)
    assert rec.meta["fs_hz"] == "1000"
    # sensor_gyro: 30 degC at 0.990 s falling 0.1 degC per 2.5 ms, interpolated onto the FIFO times
    np.testing.assert_allclose(rec.temp_c, 30.0 - 0.1 * (rec.time_s - 0.990) / 0.0025, rtol=1e-6)


@pytest.mark.parametrize("cut, expected", [
    (10, "truncated ULog file (10 bytes"),
    ("definitions", "no sensor_gyro data in the log"),
])
def test_truncated_ulog_gives_one_line_errors(tmp_path, cut, expected):
    full = ulog_bytes({0: gyro_samples()})
    if cut == "definitions":  # formats and subscriptions, not one data message
        cut = len(ulog_bytes({0: []}))
    src = tmp_path / "cut.ulg"
    src.write_bytes(full[:cut])
    with pytest.raises(RecordingError) as excinfo:
        import_recording(src)
    text = one_line_error(excinfo)
    assert str(src) in text and expected in text


def test_ulog_cut_mid_message_keeps_the_complete_messages(tmp_path):
    full = ulog_bytes({0: gyro_samples(10)})
    src = tmp_path / "cut.ulg"
    src.write_bytes(full[:-20])  # the last data message is incomplete
    rec = import_recording(src, accel=False)
    assert len(rec) == 9


def test_not_a_ulog_despite_the_extension(tmp_path):
    src = tmp_path / "fake.ulg"
    src.write_bytes(b"this is not a ulog file at all")
    with pytest.raises(RecordingError, match="does not start with the ULog magic"):
        import_recording(src)


# ------------------------------------------------------------------------------ csv, auto, script

def test_conforming_csv_passes_through_and_bad_files_do_not(tmp_path, paper_csv):
    rec = import_recording(paper_csv)
    assert rec.meta["source_format"] == "csv" and len(rec) == len(load_recording(paper_csv))
    bad = tmp_path / "bad.csv"
    bad.write_text("time_s,temp_c,gyro_x_dps,gyro_y_dps\n0,1,2,3\n")
    with pytest.raises(RecordingError, match=r"missing required column\(s\) gyro_z_dps"):
        import_recording(bad)
    unknown = tmp_path / "other.csv"
    unknown.write_text("t,rate\n0,1\n")
    with pytest.raises(RecordingError, match="cannot tell the format .* pass format=psim|lpms|ulog|csv"):
        import_recording(unknown)


def test_unknown_format_and_option_are_errors(tmp_path):
    src = write_lpms(tmp_path / "log.csv", LPMS_LATER, lpms_rows())
    with pytest.raises(GyronetError, match="unknown format"):
        import_recording(src, "xlsx")
    with pytest.raises(GyronetError, match="format lpms has no option drop_spikes"):
        import_recording(src, "lpms", drop_spikes=True)


def test_convert_keeps_every_digit_of_a_unix_time(tmp_path):
    """12 significant digits gave Unix time 10 ms steps: a 400 Hz file came back with repeated stamps."""
    src = tmp_path / "epoch.csv"
    time_s = 1765000000.0 + np.arange(50) / 400.0
    write_recording(src, {"time_s": time_s, "temp_c": np.full(50, 20.0),
                          **{c: np.zeros(50) for c in ("gyro_x_dps", "gyro_y_dps", "gyro_z_dps")}},
                    float_format="%.17g")
    convert(src, tmp_path / "out.csv")
    np.testing.assert_array_equal(load_recording(tmp_path / "out.csv").time_s, load_recording(src).time_s)


def test_convert_writes_a_recording_that_loads_back(tmp_path):
    src = tmp_path / "t.ulg"
    src.write_bytes(ulog_bytes({0: gyro_samples(20, t0_us=123_456_789_123)}))
    out = convert(src, tmp_path / "out.csv")
    back = load_recording(tmp_path / "out.csv")
    np.testing.assert_allclose(back.time_s, out.time_s, rtol=0, atol=1e-7)
    assert back.meta["source_format"] == "ulog" and back.meta["dropped_rows"] == "0"


def run_convert(tmp_path: Path, *overrides: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "scripts/convert.py", *overrides, f"hydra.run.dir={tmp_path / 'hydra'}"],
                          cwd=ROOT, capture_output=True, text=True, timeout=120)


def test_script_converts_and_fails_cleanly(tmp_path):
    good = write_lpms(tmp_path / "log.csv", LPMS_LATER, lpms_rows())
    bad = write_lpms(tmp_path / "bad.csv", LPMS_LATER.replace("(deg/s)", "(rpm)"), lpms_rows())
    done = run_convert(tmp_path, f"input={good}", f"output={tmp_path / 'out.csv'}", "sensor=bench unit 7")
    assert done.returncode == 0, done.stderr
    assert load_recording(tmp_path / "out.csv").meta["sensor"] == "bench unit 7"
    failed = run_convert(tmp_path, f"input={bad}", f"output={tmp_path / 'out2.csv'}", "format=lpms")
    assert failed.returncode != 0 and "Traceback" not in failed.stderr
    assert failed.stderr.strip().splitlines()[-1].startswith(f"error: {bad}: column 'GyroX (rpm)'")
    assert not (tmp_path / "out2.csv").exists()


# ------------------------------------------------------------- spreadsheet dialects of the contract

CONTRACT_HEADER = "time_s,temp_c,gyro_x_dps,gyro_y_dps,gyro_z_dps"
CONTRACT_ROWS = [(0.0, 20.5, 0.25, -1.5, 2.0), (0.1, 20.75, 0.5, -1.25, 2.5), (0.2, 21.0, 0.75, -1.0, 3.0)]


def _dialect(delimiter: str = ",", decimal: str = ".", trailing: str = "") -> str:
    def cell(v: float) -> str:
        return repr(v).replace(".", decimal)

    rows = [delimiter.join(cell(v) for v in row) + trailing for row in CONTRACT_ROWS]
    return "\n".join(["# sensor=bench", CONTRACT_HEADER.replace(",", delimiter) + trailing, *rows]) + "\n"


DIALECTS = {
    "semicolon": _dialect(";").encode(),
    "decimal_comma": _dialect(";", ",").encode(),
    "tab_decimal_comma": _dialect("\t", ",").encode(),
    "utf16": _dialect().encode("utf-16"),
    "utf16_semicolon": _dialect(";", ",").encode("utf-16"),
    "trailing_comma": _dialect(trailing=",").encode(),
}


@pytest.mark.parametrize("name", sorted(DIALECTS))
def test_spreadsheet_dialects_are_read_as_csv_recordings(tmp_path, name):
    src = tmp_path / f"{name}.csv"
    src.write_bytes(DIALECTS[name])
    assert detect_format(src) == "csv"
    for fmt in ("auto", "csv"):
        rec = import_recording(src, fmt)
        np.testing.assert_array_equal(np.column_stack([rec.time_s, rec.temp_c, rec.gyro_dps]), CONTRACT_ROWS)
        assert rec.meta["sensor"] == "bench"
    out = convert(src, tmp_path / "out.csv")
    back = load_recording(tmp_path / "out.csv")  # the contract's own comma CSV now
    np.testing.assert_array_equal(back.gyro_dps, out.gyro_dps)


@pytest.mark.parametrize("delimiter", [";", "\t"])
def test_a_text_cell_with_a_comma_does_not_make_the_decimals_commas(tmp_path, delimiter):
    text = _dialect(delimiter).splitlines()
    text = [text[0], text[1] + delimiter + "note", *(row + delimiter + '"ok, stable"' for row in text[2:])]
    src = tmp_path / "noted.csv"
    src.write_text("\n".join(text) + "\n")
    rec = import_recording(src, "csv")
    np.testing.assert_array_equal(np.column_stack([rec.time_s, rec.temp_c, rec.gyro_dps]), CONTRACT_ROWS)


def test_commands_point_a_semicolon_file_to_convert(tmp_path):
    src = tmp_path / "semi.csv"
    src.write_bytes(DIALECTS["decimal_comma"])
    with pytest.raises(RecordingError) as excinfo:
        load_recording(src)
    text = one_line_error(excinfo)
    assert "cells are separated by ';', not ','; convert it first: python scripts/convert.py" in text


@pytest.mark.parametrize("tool", ["psim", "lpms", "upper case"])
def test_another_tool_s_log_given_as_a_recording_says_how_to_read_it(tmp_path, tool):
    """train.py data.path=<a raw psim or LPMS log> said only which columns were missing."""
    if tool == "psim":
        src, hint = write_psim(tmp_path / "log.csv", ["0, 1, 2, 3, 4, 5, 6, 20"]), "format=psim"
    elif tool == "lpms":
        src, hint = write_lpms(tmp_path / "log.csv", LPMS_LATER, lpms_rows()), "format=lpms"
    else:
        src = tmp_path / "log.csv"
        src.write_text("Time_s,Temp_C,gyro_x_dps,gyro_y_dps,gyro_z_dps\n0,20,0,0,0\n1,20,0,0,0\n")
        hint = "names are lower case: time_s, temp_c"
    with pytest.raises(RecordingError) as excinfo:
        load_recording(src)
    text = one_line_error(excinfo)
    assert text.startswith(f"{src}: missing required column(s)") and text.endswith(hint)
    if tool != "upper case":
        assert f"python scripts/convert.py input={src} output=F.csv {hint}" in text
        assert detect_format(src) == tool


def test_script_converts_a_semicolon_decimal_comma_file(tmp_path):
    src = tmp_path / "excel.csv"
    src.write_bytes(DIALECTS["decimal_comma"])
    for fmt in ("auto", "csv"):
        done = run_convert(tmp_path, f"input={src}", f"output={tmp_path / fmt}.csv", f"format={fmt}")
        assert done.returncode == 0, done.stderr
        np.testing.assert_array_equal(load_recording(tmp_path / f"{fmt}.csv").temp_c, [20.5, 20.75, 21.0])


def test_lpms_and_psim_logs_saved_as_utf16_or_with_extra_cells(tmp_path):
    src = tmp_path / "log16.csv"
    src.write_bytes((LPMS_LATER + "\n" + "\n".join(lpms_rows()) + "\n").encode("utf-16"))
    assert detect_format(src) == "lpms"
    np.testing.assert_allclose(import_recording(src).gyro_dps, np.tile([0.5, -0.5, 1.0], (5, 1)))
    # every row one cell longer than the header: refused, not read with the last cell dropped
    extra = write_psim(tmp_path / "extra.csv", ["1000,0,0,0,0.1,0.1,0.1,256,9", "1020,0,0,0,0.1,0.1,0.1,256,9"])
    with pytest.raises(RecordingError) as excinfo:
        import_recording(extra, "psim")
    assert "malformed row: the first data row has more cells than the header's 8" in one_line_error(excinfo)


# --- issue 13: which gyro, lost samples from the timestamps, constant disabled outputs -----------

def test_lpms_lost_samples_are_counted_from_the_timestamps_not_frame_number(tmp_path):
    rows = lpms_rows(40)
    kept = rows[:10] + rows[15:30] + rows[37:]  # two holes of 5 and 7 rows; FrameNumber renumbered 0..n
    renumbered = []
    for index, row in enumerate(kept):
        cells = row.split(", ")
        cells[2] = str(index)  # OpenMAT counts frames on the host: it never skips
        renumbered.append(", ".join(cells))
    rec = import_recording(write_lpms(tmp_path / "holes.csv", LPMS_LATER, renumbered), "lpms")
    assert rec.meta["missing_frames"] == "12" and len(rec) == 28


def test_lpms_says_which_gyro_and_warns_about_auto_calibration(tmp_path, caplog):
    rec = import_recording(write_lpms(tmp_path / "log.csv", LPMS_LATER, lpms_rows(gyro=0.0001)), "lpms")
    assert rec.meta["gyro_source"] == "host_corrected"
    assert "gyro auto-calibration may have been on and the gyro's median is within 0.002" in caplog.text
    caplog.clear()
    import_recording(write_lpms(tmp_path / "moving.csv", LPMS_LATER, lpms_rows(gyro=0.5)), "lpms")
    assert "host-corrected gyro" in caplog.text and "within 0.002" not in caplog.text


def test_lpms_drops_a_constant_unit_quaternion_but_keeps_moving_outputs(tmp_path):
    rows = []
    for row in lpms_rows(6):
        cells = row.split(", ")
        cells[15:19] = ["1.000000", "0.000000", "0.000000", "0.000000"]  # quaternion output off: w = 1
        rows.append(", ".join(cells))
    rec = import_recording(write_lpms(tmp_path / "noquat.csv", LPMS_LATER, rows), "lpms")
    assert not any(c.startswith("quat_") for c in rec.columns)
    assert "quat_w" in rec.meta["disabled_outputs"] and "mag_x_ut" in rec.columns and "euler_x_deg" in rec.columns


def test_a_quoted_contract_header_is_recognised(tmp_path):
    src = tmp_path / "quoted.csv"
    src.write_text('"time_s","temp_c","gyro_x_dps","gyro_y_dps","gyro_z_dps"\n0,20,1,2,3\n0.1,20,1,2,3\n')
    assert detect_format(src) == "csv"  # the loader reads it; the format sniffer split it without unquoting
