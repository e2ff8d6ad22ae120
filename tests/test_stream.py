"""gyronet.deploy.stream: LP-BUS and CSV framings, the reconnecting reader, the sensor emulator."""
import math
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import serial

import gyronet.deploy.stream.reader as reader_module
from gyronet.deploy.stream.lpbus_setup import LpBusSetup
from gyronet.deploy.stream import (CsvLineParser, Fault, FaultCounter, FaultPlan, LpBusLayout, LpBusParser, Sample,
                            SampleCheck,
                            encode_csv_header, encode_csv_line, encode_lpbus, lpbus_frame, lrc, make_parser,
                            plan_stream, read_samples)

from gyronet.deploy.stream.events import SampleBlock, as_samples

ROOT = Path(__file__).resolve().parents[1]
ROW = {"time_s": 0.1, "gyro_x_dps": 1.0, "gyro_y_dps": 2.0, "gyro_z_dps": 3.0,
       "acc_x_g": 0.0, "acc_y_g": 0.0, "acc_z_g": 1.0, "temp_c": 25.0}
# The frame of ROW with the default fields (gyro, acc, temperature), checked by hand:
#   3a | 01 00 id 1 | 09 00 GET_SENSOR_DATA | 20 00 = 32 data bytes
#   28 00 00 00  timestamp 40 ticks of 400 Hz = 0.1 s
#   35 fa 8e 3c / 35 fa 0e 3d / 50 77 56 3d  gyro 1, 2, 3 deg/s as float32 rad/s (0.01745, ...)
#   00 00 00 00 x2, 00 00 80 3f  acc 0, 0, 1 g;  00 00 c8 41  temperature 25.0 degC
#   e7 06  LRC 0x06e7 = 1 + 9 + 32 + 1725 (the sum of the 32 data bytes) | 0d 0a
FRAME_HEX = ("3a 01 00 09 00 20 00 28 00 00 00 35 fa 8e 3c 35 fa 0e 3d 50 77 56 3d 00 00 00 00"
             " 00 00 00 00 00 00 80 3f 00 00 c8 41 e7 06 0d 0a")
FRAME = bytes.fromhex(FRAME_HEX)


def recording(n: int = 400, seed: int = 0) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    time_s = np.arange(n) * 0.1
    return {"time_s": time_s, "temp_c": 20.0 + 0.01 * np.arange(n),
            **{f"gyro_{a}_dps": rng.normal(0.0, 0.5, n) for a in "xyz"},
            "acc_x_g": np.zeros(n), "acc_y_g": np.zeros(n), "acc_z_g": np.ones(n), "vdd_v": 3.3 + 0.001 * rng.normal(size=n)}


def feed_in_chunks(parser, data: bytes, rng: np.random.Generator | None = None, max_chunk: int = 50) -> list:
    """Feed ``data`` in random chunks (one byte each when rng is None), then flush."""
    out, position = [], 0
    while position < len(data):
        size = 1 if rng is None else int(rng.integers(1, max_chunk + 1))
        out += parser.feed(data[position:position + size])
        position += size
    return out + parser.flush()


def reasons(items) -> list[str]:
    return [item.reason if isinstance(item, Fault) else "sample" for item in items]


# --- LP-BUS ---------------------------------------------------------------------------------

def test_lpbus_frame_matches_hand_checked_bytes():
    assert sum(FRAME[7:39]) == 1725
    assert lrc(1, 9, FRAME[7:39]) == 0x06E7
    assert encode_lpbus(ROW) == FRAME
    assert lpbus_frame(1, 9, FRAME[7:39]) == FRAME


def test_lpbus_parser_decodes_hand_checked_frame():
    (sample,) = LpBusParser().feed(FRAME)
    assert isinstance(sample, Sample)
    assert sample.time_s == 0.1
    assert sample.values["temp_c"] == 25.0 and sample.values["acc_z_g"] == 1.0
    # float32 rad/s back to deg/s: within float32 resolution of the sent value
    for axis, value in zip("xyz", (1.0, 2.0, 3.0)):
        assert sample.values[f"gyro_{axis}_dps"] == pytest.approx(value, rel=1e-7)


def test_lpbus_layout_orders_fields_and_maps_register_bits():
    layout = LpBusLayout(fields=("temperature", "acc", "gyro"))
    assert layout.fields == ("gyro", "acc", "temperature")
    assert layout.config_register == (1 << 12) | (1 << 11) | (1 << 13)
    assert layout.data_length == 4 + 7 * 4
    again = LpBusLayout.from_config_register(layout.config_register | (1 << 22))
    assert again.fields == layout.fields and again.precision == 16 and again.data_length == 4 + 7 * 2
    with pytest.raises(ValueError, match="unknown LP-BUS field"):
        LpBusLayout(fields=("gyro", "colour"))


@pytest.mark.parametrize("layout", [LpBusLayout(precision=16), LpBusLayout(timestamp="float"),
                                    LpBusLayout(fields=("gyro", "mag", "quaternion", "temperature", "heave"))])
def test_lpbus_layouts_round_trip(layout):
    row = {**ROW, "time_s": 12.5, "gyro_x_dps": -45.25, "mag_x_ut": 30.0, "mag_y_ut": -2.0, "mag_z_ut": 0.5,
           "quat_w": 1.0, "quat_x": 0.0, "quat_y": 0.0, "quat_z": 0.0, "heave_m": 0.25}
    (sample,) = LpBusParser(layout).feed(encode_lpbus(row, layout))
    assert sample.time_s == 12.5
    expected = layout.quantize(row)
    assert sample.row() == expected
    tolerance = 1e-3 * 180 / math.pi if layout.precision == 16 else 1e-5
    assert sample.values["gyro_x_dps"] == pytest.approx(-45.25, abs=tolerance)


def test_lpbus_round_trip_any_chunking():
    columns = recording(300)
    layout = LpBusLayout()
    rows = [{c: float(columns[c][i]) for c in layout.columns} for i in range(300)]
    stream = b"".join(encode_lpbus(row, layout) for row in rows)
    for rng in (None, np.random.default_rng(1), np.random.default_rng(2)):
        out = feed_in_chunks(LpBusParser(layout), stream, rng)
        assert [s.row() for s in out] == [layout.quantize(row) for row in rows]


def test_lpbus_resyncs_after_garbage_and_keeps_neighbours():
    frames = [encode_lpbus({**ROW, "time_s": 0.1 * (i + 1)}) for i in range(6)]
    header_like = bytes([0x3A, 0x01, 0x00, 0x09, 0x00, 0xFF, 0x7F])  # length 32767: not plausible
    bad_lrc = bytearray(frames[2])
    bad_lrc[-4] ^= 0x55
    bad_footer = frames[3][:-2] + b"\n\r"
    stream = (b"\x00\x3a\x3a\xff" + frames[0] + header_like + b"junk" + frames[1] + bytes(bad_lrc)
              + bad_footer + frames[4][:20] + frames[5])
    out = feed_in_chunks(LpBusParser(), stream)
    assert reasons(out) == ["garbage", "sample", "garbage", "sample", "bad_checksum", "bad_footer",
                            "truncated", "sample"]
    assert [s.time_s for s in out if isinstance(s, Sample)] == [0.1, 0.2, 0.6]


def test_lpbus_cut_header_and_tail_are_truncated():
    parser = LpBusParser()
    assert parser.feed(FRAME + FRAME[:5]) and parser.flush()[0].reason == "truncated"
    parser = LpBusParser()
    assert parser.feed(FRAME[:30]) == []
    assert reasons(parser.flush()) == ["truncated"]


def test_lpbus_value_checks():
    nan_frame = encode_lpbus({**ROW, "time_s": 0.2, "gyro_y_dps": math.nan})
    stale = encode_lpbus({**ROW, "time_s": 0.05})
    other_fields = encode_lpbus({**ROW, "mag_x_ut": 1.0, "mag_y_ut": 1.0, "mag_z_ut": 1.0},
                                LpBusLayout(fields=("gyro", "acc", "mag", "temperature")))
    out = LpBusParser().feed(FRAME + nan_frame + stale + other_fields + encode_lpbus({**ROW, "time_s": 0.3}))
    assert reasons(out) == ["sample", "nan", "time_not_increasing", "bad_length", "sample"]
    assert "gyro_y_dps" in out[1].detail


def test_lpbus_sensor_id_filter():
    other = encode_lpbus({**ROW, "time_s": 0.2}, sensor_id=7)
    out = LpBusParser(LpBusLayout(sensor_id=1)).feed(FRAME + other)
    assert reasons(out) == ["sample"]
    assert reasons(LpBusParser(LpBusLayout(sensor_id=1)).flush()) == []


# --- CSV lines ------------------------------------------------------------------------------

def test_csv_round_trip_any_chunking_is_exact():
    columns = recording(200)
    names = list(columns)
    rows = [{c: float(columns[c][i]) for c in names} for i in range(200)]
    stream = b"# sensor=emulated\n" + encode_csv_header(names) + b"".join(encode_csv_line(r, names) for r in rows)
    for rng in (None, np.random.default_rng(3)):
        out = feed_in_chunks(CsvLineParser(), stream, rng)
        assert [s.row() for s in out] == rows


def test_csv_faults_each_have_their_reason():
    header = b"time_s,temp_c,gyro_x_dps\r\n"
    stream = (b"1.0,2.0,3.0\n" + header + b"0.1,25.0,0.5\n" + b"\xff\xfe\x80\n" + b"0.2,25.0,abc\n"
              + b"0.3,25.0\n" + b"0.4,25.0,0.5,9\n" + b"0.5,nan,0.5\n" + header + b"0.6,25.0,inf\n"
              + b"0.05,25.0,0.5\n" + b"0.7,25.1,0.6\n" + b"0.8,25")
    out = feed_in_chunks(CsvLineParser(), stream)
    assert reasons(out) == ["no_header", "sample", "garbage", "non_numeric", "truncated", "bad_field_count",
                            "nan", "nan", "time_not_increasing", "sample", "truncated"]
    assert out[-2].values == {"temp_c": 25.1, "gyro_x_dps": 0.6}


def test_csv_new_header_replaces_old_and_long_lines_are_one_fault():
    stream = (b"time_s,a_v\n0.1,1\n" + b"x" * 5000 + b"\n" + b"b_v,time_s\n2,0.2\n")
    for rng in (None, np.random.default_rng(4)):
        out = feed_in_chunks(CsvLineParser(max_line_bytes=100), stream, rng, max_chunk=300)
        assert reasons(out) == ["sample", "garbage", "sample"]
        assert out[-1].row() == {"time_s": 0.2, "b_v": 2.0}


def test_fault_counter():
    counter = FaultCounter()
    counter.update([Sample(0.1, {}), Fault("garbage"), Fault("garbage"), Fault("nan")])
    assert counter.n_samples == 1 and counter.n_faults == 3
    assert counter.as_dict() == {"garbage": 2, "nan": 1}
    assert "1 good samples" in counter.summary()
    with pytest.raises(ValueError):
        Fault("made_up")


# --- the emulator's plan ----------------------------------------------------------------------

@pytest.mark.parametrize("protocol", ["lpbus", "csv"])
def test_planned_faults_are_what_the_parser_counts(protocol):
    columns = recording(1500)
    faults = FaultPlan(garbage_rate=0.1, corrupt_rate=0.05, truncate_rate=0.05, nan_rate=0.03,
                       out_of_range_every=40, gap_s_at=((30.0, 5.0),), seed=5)
    plan = plan_stream(columns, protocol, faults)
    log = plan.log
    assert log["injected"]["gap"] == 50 and all(min(v, 1) for k, v in log["injected"].items() if k not in ("port_drop", "new_clock"))
    assert log["clock_offsets_s"] == []
    stream = plan.preamble + b"".join(event.data for event in plan.events)
    out = feed_in_chunks(make_parser(protocol), stream, np.random.default_rng(6), max_chunk=200)
    counter = FaultCounter()
    counter.update(out)
    assert counter.as_dict() == log["expected_faults"]
    layout = LpBusLayout()
    expected = []
    for index in log["good_indices"]:
        row = {c: float(columns[c][index]) for c in columns}
        if index in log["out_of_range_indices"]:
            row["temp_c"] = faults.out_of_range_temp_c
        expected.append(layout.quantize(row) if protocol == "lpbus" else row)
    assert [s.row() for s in out if isinstance(s, Sample)] == expected


def test_plan_decisions_do_not_move_with_garbage():
    columns = recording(500)
    quiet = plan_stream(columns, "lpbus", FaultPlan(corrupt_rate=0.1, seed=2)).log
    noisy = plan_stream(columns, "lpbus", FaultPlan(corrupt_rate=0.1, garbage_rate=0.5, seed=2)).log
    assert quiet["good_indices"] == noisy["good_indices"]


def test_plan_refuses_what_it_cannot_send():
    columns = recording(10)
    del columns["acc_x_g"]
    with pytest.raises(ValueError, match="acc_x_g"):
        plan_stream(columns, "lpbus")
    with pytest.raises(ValueError, match="NaN"):
        plan_stream(recording(10), "lpbus", FaultPlan(nan_rate=0.1), LpBusLayout(precision=16))
    with pytest.raises(ValueError, match="rates"):
        FaultPlan(corrupt_rate=0.7, truncate_rate=0.7)


# --- the reader -------------------------------------------------------------------------------

def test_read_samples_over_loop_url():
    port = serial.serial_for_url("loop://", timeout=0.01)
    frames = [encode_lpbus({**ROW, "time_s": 0.1 * (i + 1)}) for i in range(5)]
    port.write(b"\x00\x01" + b"".join(frames))
    got = []
    items = read_samples(port, LpBusParser(), should_stop=lambda: len(got) >= 6)
    for item in items:
        got.append(item)
    assert reasons(got) == ["garbage"] + ["sample"] * 5
    assert not port.is_open  # the reader closes the port it owns


class ScriptedPort:
    """A port whose reads return scripted chunks, then fail."""

    def __init__(self, chunks):
        self.chunks = list(chunks)
        self.closed = False

    @property
    def in_waiting(self):
        return len(self.chunks[0]) if self.chunks and isinstance(self.chunks[0], bytes) else 0

    def read(self, size):
        if not self.chunks:
            return b""
        chunk = self.chunks.pop(0)
        if isinstance(chunk, Exception):
            raise chunk
        return chunk

    def close(self):
        self.closed = True


def test_read_samples_reconnects_after_port_loss(monkeypatch):
    frames = [encode_lpbus({**ROW, "time_s": 0.1 * (i + 1)}) for i in range(4)]
    first = ScriptedPort([frames[0], frames[1][:12], serial.SerialException("unplugged")])
    second = ScriptedPort([frames[2] + frames[3]])
    attempts = iter([serial.SerialException("not yet"), OSError("still not"), second])

    def fake_open(url, baud, timeout_s):
        result = next(attempts)
        if isinstance(result, Exception):
            raise result
        return result

    monkeypatch.setattr(reader_module, "open_port", fake_open)
    waits = []
    got = []
    for item in read_samples(first, LpBusParser(), url="/dev/fake", sleep=waits.append,
                             should_stop=lambda: len(got) >= 5):
        got.append(item)
    assert reasons(got) == ["sample", "port_lost", "truncated", "sample", "sample"]
    assert waits == [0.1, 0.2]  # exponential backoff between the failed attempts
    assert first.closed and second.closed


def test_read_samples_gives_up_when_told():
    waits = []
    out = list(read_samples(None, LpBusParser(), url="/nonexistent/port", give_up_s=0.3,
                            sleep=waits.append))
    assert out == [] and sum(waits) >= 0.3


# --- the pty emulator -------------------------------------------------------------------------

def test_pty_emulator_survives_port_drops(tmp_path):
    from gyronet.deploy.stream.pty_sensor import PtySensor, play

    columns = recording(120)
    plan = plan_stream(columns, "csv", FaultPlan(garbage_rate=0.1, truncate_rate=0.05,
                                                 drop_port_at_s=(4.0, 8.0), seed=1))
    link = tmp_path / "sensor"
    sensor = PtySensor(link, tmp_path / "port.txt")
    done = threading.Event()

    def emulate():
        try:
            play(plan, sensor, speed=0, reader_timeout_s=10, port_down_s=0.2)
        finally:
            sensor.close()
            sensor.remove_link()
            done.set()

    thread = threading.Thread(target=emulate, daemon=True)
    thread.start()
    counter, times = FaultCounter(), []
    start = time.monotonic()
    for item in read_samples(None, CsvLineParser(), url=str(link), give_up_s=1.0, backoff_s=0.05,
                             should_stop=lambda: time.monotonic() - start > 15):
        counter.add(item)
        if isinstance(item, Sample):
            times.append(item.time_s)
    thread.join(5)
    assert done.is_set()
    assert (tmp_path / "port.txt").read_text().startswith("/dev/")
    expected = dict(plan.log["expected_faults"])
    expected["port_lost"] += 1  # the emulator closing at the end
    assert counter.as_dict() == expected
    assert times == [float(columns["time_s"][i]) for i in plan.log["good_indices"]]


def test_emulator_script_bad_input_is_one_line(tmp_path):
    bad = tmp_path / "bad.csv"
    bad.write_text("time_s,temp_c\n0.0,1.0\n")
    result = subprocess.run([sys.executable, "scripts/emulate_sensor.py", f"input={bad}",
                             f"hydra.run.dir={tmp_path / 'run'}"], cwd=ROOT, capture_output=True, text=True,
                            timeout=60)
    assert result.returncode == 2
    assert result.stderr.strip().startswith("error:") and len(result.stderr.strip().splitlines()) == 1
    assert "gyro_x_dps" in result.stderr


def test_configs_build_the_library_objects():
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    with initialize_config_dir(str(ROOT / "conf"), version_base="1.3"):
        emulate = compose("emulate", overrides=["input=x.csv", "faults.drop_port_at_s=[1,2]"])
    with initialize_config_dir(str(ROOT / "conf" / "deploy"), version_base="1.3"):
        stream = compose("stream", overrides=["model=m", "port=p", "output=o.csv", "lpbus.fields=[temperature,gyro]"])
    faults = FaultPlan(**OmegaConf.to_container(emulate.faults))
    assert faults.drop_port_at_s == (1.0, 2.0)
    assert LpBusLayout(**OmegaConf.to_container(emulate.lpbus)) == LpBusLayout(sensor_id=1)
    setup = LpBusSetup(**OmegaConf.to_container(stream.lpbus))
    assert setup.passive_layout().fields == ("gyro", "temperature") and setup.configure == "auto"
    assert stream.model == "m"


# --- issue 10: corrupt header lines, numbers as offline, restarted clocks ---------------------

NAMES = ["time_s", "temp_c", "gyro_x_dps", "gyro_y_dps", "gyro_z_dps", "acc_x_g", "acc_y_g", "acc_z_g"]
NEEDED = ["time_s", "temp_c", "gyro_x_dps", "gyro_y_dps", "gyro_z_dps"]


def csv_rows(n: int, start_s: float = 0.0) -> list[dict[str, float]]:
    columns = recording(n)
    return [{c: float(columns[c][i]) + (start_s if c == "time_s" else 0.0) for c in NAMES} for i in range(n)]


@pytest.mark.parametrize("required", [(), NEEDED])
def test_csv_header_like_corrupt_line_keeps_the_header(required):
    # a corrupt line that reads 'time_s,temp_c' was taken as the new header: 18,921 of 20,000 lost
    rows = csv_rows(300)
    lines = [encode_csv_line(r, NAMES) for r in rows]
    stray = [b"time_s,temp_c\n", b"time_s,temp_c,gyro_x_dps,gyro_y_dps\n",  # cut headers
             b"time_s,temp_c,gyro_x_dps,gyro_y_dps,gyro_z_dps\n",  # carries the needed columns, fits no line
             encode_csv_header(NAMES)]  # the same header re-sent: skipped, no fault
    stream = encode_csv_header(NAMES) + b"".join(lines[:100]) + stray[0] + b"".join(lines[100:150]) + stray[1] \
        + b"".join(lines[150:200]) + stray[2] + b"".join(lines[200:250]) + stray[3] + b"".join(lines[250:])
    for rng in (None, np.random.default_rng(7)):
        out = feed_in_chunks(CsvLineParser(required=required), stream, rng)
        assert [s.row() for s in out if isinstance(s, Sample)] == rows
        faults = [f for f in out if isinstance(f, Fault)]
        assert [f.reason for f in faults] == ["bad_header"] * 3
        if required:  # refused at once, naming what it lacks
            assert "gyro_z_dps" in faults[0].detail and "gyro_z_dps" in faults[1].detail


def test_csv_header_without_a_needed_column_is_refused_and_a_real_new_header_is_taken():
    parser = CsvLineParser(required=NEEDED)
    first = [{"time_s": 0.1 * i, "temp_c": 25.0, "gyro_x_dps": 1.0, "gyro_y_dps": 2.0, "gyro_z_dps": 3.0}
             for i in range(1, 4)]
    names = list(first[0])
    renamed = ["time_s", "gyro_z_dps", "gyro_y_dps", "gyro_x_dps", "temp_c", "vdd_v"]
    later = [{**r, "time_s": r["time_s"] + 1.0, "vdd_v": 3.3} for r in first]
    stream = (b"time_s,temp_c,gyro_x_dps,gyro_y_dps\n" + encode_csv_header(names)
              + b"".join(encode_csv_line(r, names) for r in first)
              + b"time_s,temp_c,gyro_x_dps,gyro_y_dps\n0.35,25.0,1.0,2.0\n"  # re-sent without gyro_z_dps
              + encode_csv_header(renamed) + b"".join(encode_csv_line(r, renamed) for r in later))
    out = feed_in_chunks(parser, stream)
    assert reasons(out) == ["bad_header", "sample", "sample", "sample", "bad_header", "truncated",
                            "sample", "sample", "sample"]
    assert [s.row() for s in out if isinstance(s, Sample)] == first + later
    assert parser.header == renamed


# strings Python's float() reads that the offline loader (pandas) refuses, or reads as not finite
REFUSED = {"1_000": "non_numeric", "1_0.5": "non_numeric", "0x10": "non_numeric", "１２": "garbage",
           "١": "garbage", "1e": "non_numeric", "--1": "non_numeric", "": "non_numeric", "1 2": "non_numeric",
           "0b1": "non_numeric", "\x1c1": "non_numeric", "true": "non_numeric",
           "nan": "nan", "NaN": "nan", "-nan": "nan", "nAn": "nan", "+nan": "nan", "inf": "nan", "-inf": "nan",
           "infinity": "nan", "-Infinity": "nan", "INF": "nan", "1e400": "nan"}
ACCEPTED = {" 1": 1.0, "1 ": 1.0, "\t1": 1.0, "1e5": 1e5, "1E-5": 1e-5, "+1.5": 1.5, ".5": 0.5, "5.": 5.0,
            "-0": -0.0, "0001": 1.0, "1e+05": 1e5, "+.5e1": 5.0, "1e-400": 0.0, "\x0b1": 1.0}


def read_cell_offline(cell: str) -> float | None:
    """What the offline loader does with one cell: its value, or None when it refuses it."""
    import io

    import pandas as pd

    try:
        value = pd.read_csv(io.StringIO(f"time_s,gyro_x_dps\n0.1,{cell}\n"), dtype=np.float64)["gyro_x_dps"]
    except ValueError:
        return None
    return float(value.iloc[0]) if len(value) == 1 and np.isfinite(value.iloc[0]) else None


@pytest.mark.parametrize("cell", sorted(REFUSED) + sorted(ACCEPTED))
def test_csv_numbers_read_as_offline(cell):
    out = CsvLineParser().feed(f"time_s,gyro_x_dps\n0.1,{cell}\n".encode("utf-8"))
    if cell in ACCEPTED:
        assert reasons(out) == ["sample"] and out[0].values["gyro_x_dps"] == ACCEPTED[cell]
        assert read_cell_offline(cell) == ACCEPTED[cell]
    else:
        assert reasons(out) == [REFUSED[cell]]
        # the offline loader refuses it too (pandas takes 'true' as 1.0; the live path does not)
        assert read_cell_offline(cell) is None or cell == "true"


def test_restarted_clock_starts_a_new_segment_instead_of_dropping_samples():
    first, second = csv_rows(30, start_s=100.0), csv_rows(40)  # replugged: its clock starts at 0 again
    stale = {**first[-1], "time_s": first[-1]["time_s"] - 0.5}  # a stale sample: back by 0.5 s
    jump = {**second[-1], "time_s": second[-1]["time_s"] + 7200.0}  # a clock jumping 2 h ahead, then nothing
    rows = first + [stale] + second + [jump]
    stream = encode_csv_header(NAMES) + b"".join(encode_csv_line(r, NAMES) for r in rows)
    parser = CsvLineParser()
    out = feed_in_chunks(parser, stream)
    # the new clock is taken once 5 samples in a row follow it (as many as the temperature guard needs)
    assert reasons(out) == ["sample"] * 30 + ["time_not_increasing"] + ["time_jump"] * 4 + ["sample"] * 36 + ["time_jump"]
    samples = [s for s in out if isinstance(s, Sample)]
    assert [s.row() for s in samples] == first + second[4:]
    assert [i for i, s in enumerate(samples) if s.new_segment] == [30]
    assert parser.check.n_restarts == 1
    # the same check in the LP-BUS parser, with the thresholds set
    check = SampleCheck(restart_back_s=5.0, restart_jump_s=None)
    frames = b"".join(encode_lpbus({**ROW, "time_s": t}) for t in (10.0, 10.1, 6.0, 1.0, 1.1, 1.2, 1.3, 1.4, 9000.0))
    out = LpBusParser(check=check).feed(frames)
    assert reasons(out) == ["sample", "sample", "time_not_increasing"] + ["time_jump"] * 4 + ["sample", "sample"]
    assert [s.new_segment for s in out if isinstance(s, Sample)] == [False, False, True, False]


def test_a_stale_or_repeated_sample_never_confirms_a_new_clock():
    check = SampleCheck()
    times = (99.8, 99.9, 100.0, 0.0, 0.1, 0.2, 0.3, 99.5, 100.0, 0.4, 0.5)
    out = [check.check(t, {"gyro_x_dps": 0.0}) for t in times]
    assert reasons(out) == ["sample"] * 3 + ["time_jump"] * 4 + ["time_not_increasing"] * 2 + ["sample"] * 2
    assert [s.time_s for s in out if isinstance(s, Sample) and s.new_segment] == [0.4] and check.n_restarts == 1


@pytest.mark.parametrize("blocks", [False, True])
def test_after_a_reopened_port_a_corrupted_stamp_is_still_one_fault(blocks):
    """The reopened port lets the next sample start a new clock at once; once the old clock has gone on (by the
    flood path too), a corrupted stamp is a fault again."""
    rows = csv_rows(400, start_s=100.0)
    rows[300] = {**rows[300], "time_s": 10.0}
    encode = [encode_csv_line(r, NAMES) for r in rows]
    parser = CsvLineParser(blocks=blocks)
    out = parser.feed(encode_csv_header(NAMES) + b"".join(encode[:200]))  # whole reads: the flood path's
    parser.check.reopened()
    out += parser.feed(b"".join(encode[200:])) + parser.flush()
    assert any(isinstance(item, SampleBlock) for item in out) == blocks
    out = as_samples(out)
    assert reasons(out).count("time_jump") == 1 and parser.check.n_restarts == 0


def test_one_corrupted_stamp_is_one_lost_sample_not_a_restart():
    """A stamp corrupted back by 90 s, or 2 h ahead, then the old clock goes on: the lone sample is the fault
    (once taken as a restart, its start-up window closed on that one sample: a bias for good)."""
    rows = csv_rows(60, start_s=100.0)
    rows[20] = {**rows[20], "time_s": 10.0}
    rows[40] = {**rows[40], "time_s": rows[40]["time_s"] + 7200.0}
    stream = encode_csv_header(NAMES) + b"".join(encode_csv_line(r, NAMES) for r in rows)
    parser = CsvLineParser()
    out = feed_in_chunks(parser, stream)
    assert [i for i, r in enumerate(reasons(out)) if r != "sample"] == [20, 40]
    assert set(reasons(out)) == {"sample", "time_jump"} and parser.check.n_restarts == 0
    assert not any(s.new_segment for s in out if isinstance(s, Sample))


def test_plan_replugs_with_a_restarted_clock():
    columns = recording(300)
    plan = plan_stream(columns, "lpbus", FaultPlan(restart_clock_at_s=(10.0,), seed=1))
    assert plan.log["clock_offsets_s"] == [[100, -10.0]] and plan.log["expected_faults"] == {"port_lost": 1}
    drop = next(i for i, event in enumerate(plan.events) if event.drop)
    before, after = (b"".join(event.data for event in events) for events in (plan.events[:drop], plan.events[drop:]))
    # the reader tells the check that the port was lost and reopened: the new clock is taken at once
    parser = LpBusParser()
    out = feed_in_chunks(parser, before)
    parser.check.reopened()
    out += feed_in_chunks(parser, after)
    times = [s.time_s for s in out]
    assert len(out) == 300 and times[99:102] == [9.9, 0.0, 0.1]
    assert [i for i, s in enumerate(out) if s.new_segment] == [100]
    # the same bytes with no loss between: 4 time_jump faults, until the fifth sample confirms the new clock
    out = feed_in_chunks(LpBusParser(), before + after)
    assert reasons(out) == ["sample"] * 100 + ["time_jump"] * 4 + ["sample"] * 196
    assert [s.time_s for s in out if isinstance(s, Sample)][99:101] == [9.9, 0.4]
