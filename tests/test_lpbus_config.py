"""Issue 13: talking to LP-BUS sensors of both generations, and refusing what cannot be decoded.

The emulated sensor (gyronet.deploy.stream.lpbus_device) sits behind an in-memory port here; the pty
tests are in test_lpbus_live.py. Frames "as the reference parser expects" are built with
``struct`` from the reference's own description (OpenZen ImuComponent.cpp / ImuIg1Component.cpp),
not with gyronet's encoder.
"""
import logging
import math
import struct
from dataclasses import replace

import pytest

from gyronet.deploy.stream import LpBusLayout, LpBusParser, Sample, encode_lpbus
from gyronet.deploy.stream.lpbus_config import Wanted, configure_sensor
from gyronet.deploy.stream.lpbus_device import EmulatedLpms
from gyronet.deploy.stream import lpbus_legacy as legacy
from gyronet.deploy.stream.lpbus_link import LpBusLink, SensorError
from gyronet.deploy.stream.lpbus_probe import FirstFrames, LayoutError
from gyronet.deploy.stream.lpbus_setup import LpBusSetup, is_serial_device

WANTED = Wanted(fields=("gyro", "acc", "temperature"), rate_hz=100)
ROW = {"time_s": 1.5, "gyro_x_dps": 0.25, "gyro_y_dps": -1.0, "gyro_z_dps": 2.0, "acc_x_g": 0.01,
       "acc_y_g": -0.02, "acc_z_g": 0.99, "temp_c": 31.5}


class FakePort:
    """A port wired to an emulated sensor: what the host writes, the sensor answers at once."""

    def __init__(self, device, waiting: bytes = b"", mute: bool = False):
        self.device, self.inbox, self.mute = device, bytearray(waiting), mute

    def write(self, data: bytes) -> None:
        for reply in self.device.feed(data):
            if not self.mute:
                self.inbox += reply

    @property
    def in_waiting(self) -> int:
        return len(self.inbox)

    def read(self, n: int) -> bytes:
        out = bytes(self.inbox[:n])
        del self.inbox[:n]
        return out


@pytest.mark.parametrize("model, generation, first_commands", [
    ("LPMS-CU2", "legacy", [6, 21, 91, 47, 4]),
    ("LPMS-B2", "legacy", [6, 21, 91, 47, 4]),
    ("LPMS-IG1-RS232", "ig1", [6, 21, 20, 31]),
    ("LPMS-BE1", "ig1", [6, 21, 20, 31]),
])
def test_both_generations_are_identified_set_up_and_left_streaming(model, generation, first_commands):
    device = EmulatedLpms(model=model, rate_hz=50, fields=("quaternion",), precision=16, gyro_autocalibration=True)
    row_bytes = encode_lpbus(ROW | {"quat_w": 1.0, "quat_x": 0.0, "quat_y": 0.0, "quat_z": 0.0}, device.layout())
    info = configure_sensor(FakePort(device, waiting=row_bytes * 3), WANTED, timeout_s=0.2)  # still streaming
    assert (info.generation, info.model, info.rate_hz) == (generation, model, 100.0)
    assert device.commands[:len(first_commands)] == first_commands and device.commands[-1] == 7
    assert device.streaming and device.rate_hz == 100 and device.precision == 32
    assert not device.gyro_autocalibration and not info.gyro_autocalibration
    assert "gyro auto-calibration off" in info.changed and not device.saved
    assert replace(device.layout(), sensor_id=None) == info.layout
    # what the sensor now sends decodes to the columns it was sent from
    (sample,) = LpBusParser(info.layout).feed(encode_lpbus(ROW, device.layout()))
    assert isinstance(sample, Sample)
    for column, value in ROW.items():
        assert sample.row()[column] == pytest.approx(value, rel=1e-6, abs=1e-6)


def test_ig1_sends_acc_first_in_deg_and_the_be1_gyro_is_its_second():
    ig1 = configure_sensor(FakePort(EmulatedLpms(model="LPMS-IG1-RS232")), WANTED, 0.2).layout
    be1 = configure_sensor(FakePort(EmulatedLpms(model="LPMS-BE1")), WANTED, 0.2).layout
    assert ig1.columns[1:4] == ["acc_x_g", "acc_y_g", "acc_z_g"] and not ig1.radians and ig1.timestamp_hz == 500
    assert ig1.config_register == (1 << 0) | (1 << 2) | (1 << 16)
    assert be1.config_register == (1 << 0) | (1 << 3) | (1 << 16)


def test_legacy_timestamps_follow_firmware_and_rate():
    old = configure_sensor(FakePort(EmulatedLpms(firmware=(1, 3, 4))), WANTED, 0.2).layout
    fast = configure_sensor(FakePort(EmulatedLpms()), replace(WANTED, rate_hz=800), 0.2).layout
    assert old.timestamp == "float"
    assert fast.timestamp == "count" and fast.timestamp_hz == 800  # OpenZen: * 0.00125 above 400 Hz


def test_save_writes_the_registers():
    device = EmulatedLpms()
    info = configure_sensor(FakePort(device), replace(WANTED, save=True), 0.2)
    assert device.saved and 15 in device.commands and "saved to the sensor's flash" in info.changed


def test_a_rate_the_sensor_lacks_is_refused_unless_any_rate():
    device = EmulatedLpms(rate_hz=50)
    with pytest.raises(SensorError, match=r"5, 10, 25, 50, 100, 200, 400, 800 Hz, not 2 Hz; pass resample=true"):
        configure_sensor(FakePort(device), replace(WANTED, rate_hz=2), 0.2)
    assert device.streaming  # left as it was found
    info = configure_sensor(FakePort(device), replace(WANTED, rate_hz=2, any_rate=True), 0.2)
    assert info.rate_hz == 50


LEGACY_SETS, IG1_SETS = {10, 11, 75, 23}, {30, 34, 136, 64}  # SET_TRANSMIT_DATA, rate, precision, auto-calibration


@pytest.mark.parametrize("model, wanted, refused", [
    ("LPMS-CU2", replace(WANTED, rate_hz=7), "not 7 Hz"),
    ("LPMS-CU2", replace(WANTED, precision=8), "lpbus.precision is 16 or 32"),
    ("LPMS-IG1-RS232", replace(WANTED, rate_hz=7), "not 7 Hz"),
    ("LPMS-IG1-RS232", replace(WANTED, precision=8), "lpbus.precision is 16 or 32"),
    ("LPMS-IG1-RS232", replace(WANTED, rate_hz=1000), "would stream at 1000 Hz, above its 500 Hz timestamp clock"),
])
def test_a_refused_setting_leaves_the_sensor_as_it_was_found(model, wanted, refused):
    """The outputs were set before the rate was checked: a refused rate left the sensor half set up."""
    device = EmulatedLpms(model=model, rate_hz=50, fields=("quaternion",), precision=16, gyro_autocalibration=True)
    with pytest.raises(SensorError, match=refused):
        configure_sensor(FakePort(device), wanted, 0.2)
    assert not set(device.commands) & (LEGACY_SETS | IG1_SETS)
    assert device.fields == ("quaternion",) and device.rate_hz == 50 and device.streaming


def test_record_is_told_to_choose_a_rate_and_stream_to_resample(tmp_path):
    from gyronet.deploy.stream.lpbus_setup import start_lpbus

    setup = LpBusSetup(configure=True, rate_hz=7, timeout_s=0.2)
    with pytest.raises(SensorError, match="choose lpbus.rate_hz from these rates") as recording:
        start_lpbus(FakePort(EmulatedLpms()), "sensor", setup)
    assert "resample" not in str(recording.value)
    with pytest.raises(SensorError, match="pass resample=true"):
        start_lpbus(FakePort(EmulatedLpms()), "sensor", setup, meta={"fs_hz": 7})


@pytest.mark.parametrize("rate_hz", [None, 1000])  # kept as it is, or asked for what it already streams at
def test_ig1_above_its_timestamp_clock_is_refused_before_anything_is_sent(rate_hz):
    device = EmulatedLpms(model="LPMS-IG1-RS232", rate_hz=1000, fields=("quaternion",), precision=16,
                          gyro_autocalibration=True)
    with pytest.raises(SensorError, match="1000 Hz, above its 500 Hz timestamp clock"):
        configure_sensor(FakePort(device), replace(WANTED, rate_hz=rate_hz), 0.2)
    assert not set(device.commands) & IG1_SETS and device.fields == ("quaternion",)


class StrangeIg1(EmulatedLpms):
    """An IG1 that reports an output bit no reference lists."""

    def _ig1(self, command, payload):
        if command == 31:
            return self._frame(31, struct.pack("<I", self.layout().config_register | 1 << 20))
        return super()._ig1(command, payload)


def test_unknown_register_bits_are_refused_by_name():
    with pytest.raises(SensorError, match=r"LPMS-IG1-RS232: IG1 output register 0x00110005 sets bit\(s\) \[20\]"):
        configure_sensor(FakePort(StrangeIg1(model="LPMS-IG1-RS232")), WANTED, 0.2)


class StubbornSensor(EmulatedLpms):
    """Acknowledges ENABLE_GYR_AUTOCAL but keeps auto-calibration on."""

    def _legacy(self, command, payload):
        if command == 23:
            return self._ack()
        return super()._legacy(command, payload)


def test_an_acknowledged_setting_the_sensor_does_not_report_is_refused():
    with pytest.raises(SensorError, match="acknowledged the settings but reports gyro auto-calibration on"):
        configure_sensor(FakePort(StubbornSensor()), WANTED, 0.2)


def test_outputs_the_generation_lacks_are_refused_by_name():
    with pytest.raises(SensorError, match=r"LPMS-CU2: unknown LP-BUS field\(s\) \['gyro_aligned'\] for legacy"):
        configure_sensor(FakePort(EmulatedLpms()), Wanted(fields=("gyro_aligned", "temperature")), 0.2)


def test_a_silent_port_is_one_clear_error():
    with pytest.raises(SensorError, match=r"no answer to GOTO_COMMAND_MODE \(command 6\) within 0.05 s"):
        configure_sensor(FakePort(EmulatedLpms(), mute=True), WANTED, 0.05)


class LatePort(FakePort):
    """The reply to the first ``late`` command comes after the host's timeout: just before the next reply."""

    def __init__(self, device, late: int):
        super().__init__(device)
        self.late, self.held = late, b""

    def write(self, data: bytes) -> None:
        replies = b"".join(self.device.feed(data))
        self.inbox += self.held
        self.held = b""
        if self.late is not None and self.device.commands[-1] == self.late:
            self.late, self.held = None, replies
        else:
            self.inbox += replies


def test_a_late_ack_is_never_taken_for_a_later_commands_reply():
    device = EmulatedLpms(model="LPMS-CU2")
    link = LpBusLink(LatePort(device, late=legacy.SET_STREAM_FREQ), timeout_s=0.05)
    link.set(legacy.GOTO_COMMAND_MODE, "GOTO_COMMAND_MODE")
    with pytest.raises(SensorError, match=r"no answer to SET_STREAM_FREQ \(command 11\)"):
        link.set_int(legacy.SET_STREAM_FREQ, "SET_STREAM_FREQ", 100)
    with pytest.raises(SensorError, match=r"refused SET_STREAM_FREQ \(command 11, NACK\)"):  # not the late ACK
        link.set_int(legacy.SET_STREAM_FREQ, "SET_STREAM_FREQ", 123)
    assert device.commands == [6, 11, 21, 11]
    # a command-mode ACK late past the timeout: command mode is asked again, then the set-up goes on in step
    device = EmulatedLpms(model="LPMS-CU2", rate_hz=50, fields=("quaternion",), gyro_autocalibration=True)
    info = configure_sensor(LatePort(device, late=legacy.GOTO_COMMAND_MODE), WANTED, timeout_s=0.05)
    assert device.commands[:3] == [6, 6, 21] and device.commands[-1] == 7
    assert info.rate_hz == 100 and info.layout.fields == WANTED.fields and not info.gyro_autocalibration


class NoOutputs(EmulatedLpms):
    """An IG1 that refuses SET_IMU_TRANSMIT_DATA."""

    def _ig1(self, command, payload):
        return None if command == 30 else super()._ig1(command, payload)


def test_nack_names_the_command():
    with pytest.raises(SensorError, match=r"refused SET_IMU_TRANSMIT_DATA \(command 30, NACK\)"):
        configure_sensor(FakePort(NoOutputs(model="LPMS-IG1-RS232")), WANTED, 0.2)


def test_configure_auto_means_a_real_serial_device(tmp_path):
    assert not is_serial_device("loop://") and not is_serial_device("socket://localhost:1")
    link = tmp_path / "sensor"
    link.symlink_to("/dev/pts/7")
    assert not is_serial_device(str(link)) and is_serial_device("/dev/ttyUSB0")
    assert LpBusSetup(configure="auto").wants_configure("/dev/ttyUSB0")
    assert not LpBusSetup(configure="auto").wants_configure(str(link))


# --- frames as the reference parsers expect them, built by hand -----------------------------

def reference_frame(command: int, data: bytes, sensor_id: int = 1) -> bytes:
    """Modbus.cpp's LP frame: 0x3A, id, command, length (u16 each), data, LRC = sum of all, 0x0D 0x0A."""
    checksum = (sensor_id + command + len(data) + sum(data)) & 0xFFFF
    return struct.pack("<BHHH", 0x3A, sensor_id, command, len(data)) + data + struct.pack("<H", checksum) + b"\r\n"


def legacy_frame(count: int, gyro_rad_s, acc_g, temp_c) -> bytes:
    """ImuComponent.cpp parseSensorData, 32-bit: uint32 count, raw gyro (rad/s), raw acc (g), temperature."""
    return reference_frame(9, struct.pack("<I3f3ff", count, *gyro_rad_s, *acc_g, temp_c))


def ig1_frame(count: int, acc_g, gyro_dps, temp_c) -> bytes:
    """ImuIg1Component.cpp parseSensorData: uint32 count, acc raw, gyro 0 raw (deg/s), temperature."""
    return reference_frame(9, struct.pack("<I3f3ff", count, *acc_g, *gyro_dps, temp_c))


def f32(value: float) -> float:
    return struct.unpack("<f", struct.pack("<f", value))[0]


def test_reference_built_frames_decode_as_the_reference_reads_them():
    legacy = LpBusParser(LpBusLayout()).feed(legacy_frame(400, (0.1, -0.2, 0.3), (0.0, 0.0, 1.0), 30.0))[0]
    ig1 = LpBusParser(LpBusLayout(generation="ig1")).feed(ig1_frame(500, (0.0, 0.0, 1.0), (1.5, -2.5, 3.5), 30.0))[0]
    assert legacy.time_s == 400 * 0.0025 and ig1.time_s == 500 * 0.002
    assert legacy.values["gyro_x_dps"] == pytest.approx(f32(0.1) * 180 / math.pi, rel=1e-7)
    assert ig1.values["gyro_y_dps"] == -2.5 and ig1.values["acc_z_g"] == 1.0


def test_same_length_misreads_are_refused_by_the_first_frames():
    """Issue 13's two silent misreads, each 32 data bytes: refused naming the register bits, not decoded."""
    ig1 = b"".join(ig1_frame(i, (0.01, -0.02, 0.99), (0.05, -0.03, 0.01), 25.0) for i in range(20))
    acc_angvel = b"".join(legacy_frame(i, (0.0, 0.0, 1.0), (0.01, 0.02, -0.01), 25.0) for i in range(20))  # acc first
    for stream in (ig1, acc_angvel):
        parser = LpBusParser(LpBusLayout())
        parser.probe = FirstFrames(parser.layout, 20, "port P")
        with pytest.raises(LayoutError, match=r"register bits legacy 11, 12, 13\).*\|a\| = 0.0\d+ g"):
            parser.feed(stream)
    right = LpBusParser(LpBusLayout(generation="ig1"))
    right.probe = FirstFrames(right.layout, 20)
    assert all(isinstance(item, Sample) for item in right.feed(ig1))


def test_frames_are_held_until_the_first_frames_check_passes():
    """Fed a frame at a time (a pty read each), a misread is refused before any of it gets out; a port lost
    before the check is done has the frames so far judged at the flush."""
    misread = [ig1_frame(i, (0.01, -0.02, 0.99), (0.05, -0.03, 0.01), 25.0) for i in range(20)]
    parser = LpBusParser(LpBusLayout())
    parser.probe = FirstFrames(parser.layout, 20)
    with pytest.raises(LayoutError):
        for frame in misread:
            assert parser.feed(frame) == []
    cut = LpBusParser(LpBusLayout())
    cut.probe = FirstFrames(cut.layout, 20)
    assert cut.feed(b"".join(misread[:5])) == []
    with pytest.raises(LayoutError, match="the first 5 frames"):
        cut.flush()
    right = LpBusParser(LpBusLayout(generation="ig1"))
    right.probe = FirstFrames(right.layout, 20)
    assert [right.feed(frame) for frame in misread[:19]] == [[]] * 19
    assert len(right.feed(misread[19])) == 20 and len(right.feed(misread[0])) == 1  # then frame by frame


def test_a_stream_faster_than_its_timestamp_clock_says_which_setting():
    # 1 kHz frames counted at 400 Hz: 60 % of them repeat a time
    frames = b"".join(legacy_frame(int(i * 0.4), (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), 25.0) for i in range(20))
    parser = LpBusParser(LpBusLayout())
    parser.probe = FirstFrames(parser.layout, 20)
    with pytest.raises(LayoutError, match="12 of 19 times do not increase.*set lpbus.timestamp_hz"):
        parser.feed(frames)


@pytest.mark.parametrize("ticks_per_frame, given, warned", [(1, False, True), (4, False, False), (1, True, False)])
def test_listening_at_400_hz_ticks_warns_that_800_hz_reads_the_same(caplog, ticks_per_frame, given, warned):
    """A legacy sensor at 800 Hz counts at 800 Hz: read at 400 Hz ticks, it passed as 400 Hz with every time doubled
    (unless the user set lpbus.timestamp_hz=400: then the ticks are known)."""
    frames = b"".join(legacy_frame(i * ticks_per_frame, (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), 25.0) for i in range(20))
    parser = LpBusParser(LpBusLayout())
    parser.probe = FirstFrames(parser.layout, 20, clock_given=given)
    caplog.set_level(logging.WARNING, logger="gyronet.deploy.stream.lpbus_probe")
    assert len(parser.feed(frames)) == 20
    assert any("set lpbus.timestamp_hz=800" in r.getMessage() for r in caplog.records) == warned


def test_an_800_hz_clock_read_at_400_hz_names_the_setting():
    # a legacy sensor at 800 Hz counts at 800 Hz (OpenZen): one tick a frame, read at 400 Hz ticks
    frames = b"".join(legacy_frame(i, (0.0, 0.0, 0.0), (0.0, 0.0, 1.0), 25.0) for i in range(20))
    parser = LpBusParser(LpBusLayout())
    parser.probe = FirstFrames(parser.layout, 20, expected_hz=800.0)
    with pytest.raises(LayoutError, match=r"the timestamp counts at 800 Hz \(set lpbus.timestamp_hz=800"):
        parser.feed(frames)
    right = LpBusParser(LpBusLayout(timestamp_hz=800.0))
    right.probe = FirstFrames(right.layout, 20, expected_hz=800.0)
    assert len(right.feed(frames)) == 20


def test_without_acceleration_the_quaternion_and_the_clock_are_checked_else_the_log_says_so(caplog):
    row = {"time_s": 0.0, "gyro_x_dps": 0.5, "gyro_y_dps": -0.2, "gyro_z_dps": 0.1, "temp_c": 31.5,
           "quat_w": 0.6, "quat_x": 0.0, "quat_y": 0.0, "quat_z": 0.8,
           "euler_x_deg": 12.0, "euler_y_deg": -40.0, "euler_z_deg": 170.0}

    def frames(layout, step_s):
        return b"".join(encode_lpbus({**row, "time_s": i * step_s}, layout) for i in range(20))

    def probed(layout):
        parser = LpBusParser(layout)
        parser.probe = FirstFrames(layout, 20, "port P")  # no bundle: record.py
        return parser

    # quaternion + euler + temperature read as gyro + quaternion + temperature: the same 32 data bytes
    shifted = frames(LpBusLayout(("quaternion", "euler", "temperature")), 0.01)
    with pytest.raises(LayoutError, match=r"register bits legacy 12, 13, 18\): the quaternion reads \|q\| = 3.16 "):
        probed(LpBusLayout(("gyro", "quaternion", "temperature"))).feed(shifted)
    assert len(probed(LpBusLayout(("quaternion", "euler", "temperature"))).feed(shifted)) == 20
    # an IG1 at 100 Hz (500 Hz ticks) read as legacy (400 Hz ticks): 80 Hz, no legacy rate
    ig1 = frames(LpBusLayout(("gyro", "temperature"), generation="ig1"), 0.01)
    with pytest.raises(LayoutError, match=r"at 80 Hz by its times, no rate a legacy sensor streams at, but 100 Hz "
                                          r"times 400/500: the timestamp counts at 500 Hz"):
        probed(LpBusLayout(("gyro", "temperature"))).feed(ig1)
    with caplog.at_level(logging.WARNING, logger="gyronet.deploy.stream.lpbus_probe"):
        assert len(probed(LpBusLayout(("gyro", "temperature"), generation="ig1")).feed(ig1)) == 20
    assert "fit ig1 LP-BUS" in caplog.text and "in their times and temperature, but which output sits where could " \
        "not be checked" in caplog.text


def test_setup_refuses_a_bundle_trained_on_the_host_corrected_gyro():
    from gyronet.errors import BundleError
    from gyronet.deploy.stream.lpbus_setup import start_lpbus

    with pytest.raises(BundleError, match="host_corrected gyro.*LP-BUS carries the raw gyro"):
        start_lpbus(None, "loop://", LpBusSetup(configure=False), {"fs_hz": 10.0, "gyro_source": "host_corrected"})
    start = start_lpbus(None, "loop://", LpBusSetup(configure=False), {"fs_hz": 10.0, "gyro_source": "raw"})
    assert start.sensor is None and start.probe is not None


def test_bundles_record_which_gyro_they_were_trained_on(paper_csv, bundle, tmp_path):
    import torch

    from gyronet.bundle.schema import gyro_source_of, validate_meta
    from gyronet.bundle.compensator import Compensator
    from gyronet.recordings.data import load_recording, write_recording
    from gyronet.training.dataset import DriftData
    from gyronet.errors import BundleError
    from gyronet.training.pipeline import _meta

    assert gyro_source_of([{}, {}]) is None
    assert gyro_source_of([{"gyro_source": "raw"}, {"gyro_source": "host_corrected"}]) == "host_corrected"
    recording = load_recording(paper_csv).slice(slice(0, 4000))
    log = write_recording(tmp_path / "lpms.csv", recording.columns, {**recording.meta, "gyro_source": "host_corrected"})
    data = DriftData(str(log))
    meta = _meta(torch.nn.Linear(data.n_features, 3), data)
    assert meta["gyro_source"] == "host_corrected"
    validate_meta({**meta, "format": 1})
    with pytest.raises(BundleError, match="'gyro_source' must be one of"):
        validate_meta({**meta, "format": 1, "gyro_source": "filtered"})
    older = Compensator.load(bundle).meta  # a bundle without the field (trained on the simulator) still streams
    from gyronet.deploy.stream.lpbus_setup import start_lpbus

    assert "gyro_source" not in older and start_lpbus(None, "loop://", LpBusSetup(configure=False), older).layout


# --- property: any output selection of either generation round-trips, any chunking ----------

from hypothesis import given, strategies as st  # noqa: E402

from gyronet.deploy.stream.lpbus_layout import generation_fields  # noqa: E402


@given(generation=st.sampled_from(["legacy", "ig1"]), bits=st.integers(0, 2 ** 17 - 1),
       precision=st.sampled_from([16, 32]), radians=st.booleans(), cut=st.integers(1, 200))
def test_any_register_of_either_generation_decodes_what_was_sent(generation, bits, precision, radians, cut):
    table = generation_fields(generation)
    fields = tuple(f.name for f in table if bits >> (f.bit % 17) & 1)
    layout = LpBusLayout(fields, precision, generation=generation, radians=True if generation == "legacy" else radians)
    again = (LpBusLayout.from_config_register(layout.config_register) if generation == "legacy" else
             LpBusLayout.from_transmit_register(layout.config_register, precision, radians=layout.radians))
    assert again == layout
    value = {c: 0.5 + 0.01 * k for k, c in enumerate(layout.columns)}  # a column read into another's place shows
    row = value | {"time_s": 2.0}
    frames = b"".join(encode_lpbus(row | {"time_s": 2.0 + i}, layout) for i in range(3))
    parser = LpBusParser(layout)
    items = parser.feed(frames[:cut]) + parser.feed(frames[cut:])
    assert [item.time_s for item in items] == [2.0, 3.0, 4.0]
    for item in items:
        for spec in layout.specs:  # 16-bit: within half a step of the reference's scale
            step = 1.0 / spec.scale(layout.radians) if precision == 16 else 1e-6
            step = math.degrees(step) if spec.angular and layout.radians and precision == 16 else step
            for column in spec.columns:
                assert item.values[column] == pytest.approx(value[column], abs=step / 2 + 1e-9)


@given(commands=st.lists(st.tuples(st.integers(0, 200), st.binary(max_size=40)), min_size=1, max_size=8),
       garbage=st.lists(st.binary(max_size=12).filter(lambda b: 0x3A not in b), min_size=9, max_size=9),
       cut=st.integers(0, 400))
def test_replies_are_found_among_garbage_at_any_split(commands, garbage, cut):
    from gyronet.deploy.stream.lpbus import lpbus_frame
    from gyronet.deploy.stream.lpbus_link import FrameReader

    stream = b"".join(g + lpbus_frame(1, c, d) for g, (c, d) in zip(garbage, commands)) + garbage[-1]
    reader = FrameReader()
    found = list(reader.feed(stream[:cut])) + list(reader.feed(stream[cut:]))
    assert [(c, d) for _, c, d in found] == commands
