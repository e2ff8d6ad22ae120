"""Issue 13 end to end through a pseudo-terminal (real pyserial on a pty): an emulated LPMS of either
generation is set up by the live path and by record.py, then streams; live equals offline."""
import json
import time

import numpy as np
import pandas as pd
import pytest

from gyronet.bundle.compensator import Compensator
from gyronet.recordings.data import GYRO_COLUMNS, load_recording
from gyronet.deploy.stream import FaultPlan
from gyronet.deploy.stream.lpbus_device import EmulatedLpms
from gyronet.deploy.stream.lpbus_probe import LayoutError
from gyronet.deploy.stream.lpbus_setup import LpBusSetup
from gyronet.deploy.stream.pty_device import fill_columns
from gyronet.deploy.stream.pty_sensor import play_in_thread
from conftest import LPBUS_SAMPLES as N_SAMPLES

FAST = {"backoff_s": 0.05, "max_backoff_s": 0.2, "give_up_s": 0.5}


def started(thread, link, timeout_s: float = 10.0):
    """Wait until the emulator's pty link exists (the port must be there when the set-up starts)."""
    deadline = time.monotonic() + timeout_s
    while not link.exists() and time.monotonic() < deadline:
        time.sleep(0.01)
    return thread


def power_on(model: str) -> EmulatedLpms:
    """A sensor as it might come out of its box: other outputs, 16-bit, auto-calibration on."""
    return EmulatedLpms(model=model, rate_hz=50, fields=("quaternion", "temperature"), precision=16,
                        gyro_autocalibration=True)


def offline(bundle, columns, plan, layout):
    """compensate.py on the good samples as they read after their trip through the final layout."""
    rows = [layout.quantize({c: float(columns[c][i]) for c in layout.columns}) for i in plan.log["good_indices"]]
    compensator = Compensator.load(bundle)
    compensator.reset()
    inputs = {c: np.array([row[c] for row in rows]) for c in compensator.input_columns}
    return inputs, compensator.process(inputs)


@pytest.mark.parametrize("model", ["LPMS-CU2", "LPMS-IG1-RS232"])
def test_configured_sensor_streams_and_live_equals_offline(bundle, lpbus_recording, tmp_path, model):
    from gyronet.deploy.stream.live import run_stream

    recording = load_recording(lpbus_recording)
    device = power_on(model)
    faults = FaultPlan(garbage_rate=0.03, corrupt_rate=0.03, truncate_rate=0.02, seed=4)
    link = tmp_path / "sensor"
    thread = started(play_in_thread(None, link, device=device, columns=recording.columns, faults=faults,
                                    preroll_frames=5), link)
    summary = run_stream(bundle, str(link), tmp_path / "live.csv", allan_every_s=0, summary_path=tmp_path / "s.json",
                         reconnect={**FAST, "wait_at_start": False}, resample=True,
                         lpbus=LpBusSetup(configure=True, timeout_s=2.0))
    thread.join(10)
    plan = thread.plan
    sensor = json.loads((tmp_path / "s.json").read_text())["sensor"]
    assert sensor["model"] == model and sensor["gyro_autocalibration"] is False and sensor["configured"]
    assert not device.gyro_autocalibration and device.precision == 32
    assert summary["faults"] == {**plan.log["expected_faults"], "port_lost": 1}  # the emulator ends: port gone
    layout = device.layout()
    inputs, out = offline(bundle, recording.columns, plan, layout)
    live = pd.read_csv(tmp_path / "live.csv", comment="#")
    assert len(live) == len(plan.log["good_indices"]) > 0.85 * N_SAMPLES
    np.testing.assert_array_equal(live["time_s"].to_numpy(), inputs["time_s"])
    np.testing.assert_allclose(live[list(GYRO_COLUMNS)].to_numpy(), out.rate_dps, rtol=0, atol=1e-9)
    # against the CSV itself (float64), the float32 frames cost about 1e-7 deg/s
    csv = {c: np.asarray(recording.columns[c])[plan.log["good_indices"]] for c in inputs}
    compensator = Compensator.load(bundle)
    compensator.reset()
    from_csv = compensator.process(csv).rate_dps
    float32_error_dps = np.max(np.abs(live[list(GYRO_COLUMNS)].to_numpy() - from_csv))
    print(f"{model}: live - compensate.py on the CSV: max {float32_error_dps:.3g} deg/s")
    assert float32_error_dps < 1e-6


def test_rate_the_bundle_needs_is_refused_without_resample(bundle, lpbus_recording, tmp_path):
    from gyronet.deploy.stream.live import run_stream
    from gyronet.deploy.stream.lpbus_link import SensorError

    recording = load_recording(lpbus_recording)
    link = tmp_path / "sensor"
    thread = started(play_in_thread(None, link, device=power_on("LPMS-CU2"), columns=recording.columns,
                                    command_wait_s=0.5), link)
    with pytest.raises(SensorError, match=r"not 2 Hz; pass resample=true"):
        run_stream(bundle, str(link), tmp_path / "live.csv", allan_every_s=0, lpbus=LpBusSetup(configure=True))
    assert thread.is_alive()  # the emulator, left waiting for a reader (a daemon thread)
    assert not (tmp_path / "live.csv").exists()


def test_passive_reader_of_an_ig1_with_the_legacy_layout_is_refused(bundle, lpbus_recording, tmp_path):
    from gyronet.deploy.stream.live import run_stream

    recording = load_recording(lpbus_recording)
    device = EmulatedLpms(model="LPMS-IG1-RS232", fields=("acc", "gyro", "temperature"), rate_hz=10, precision=32)
    link = tmp_path / "sensor"
    started(play_in_thread(None, link, device=device, columns=recording.columns, command_wait_s=0.2),
                     link)
    with pytest.raises(LayoutError, match=r"register bits legacy 11, 12, 13\).*lpbus.configure=true"):
        run_stream(bundle, str(link), tmp_path / "live.csv", allan_every_s=0, reconnect=FAST,
                   lpbus=LpBusSetup(configure=False))
    assert len(pd.read_csv(tmp_path / "live.csv", comment="#")) == 0


def test_record_sets_the_sensor_up_and_writes_a_recording(lpbus_recording, tmp_path, monkeypatch, caplog):
    from gyronet.deploy.stream import record
    from gyronet.deploy.stream.record import record_stream

    monkeypatch.setattr(record, "PROGRESS_S", 0.0)  # a progress line every sample
    caplog.set_level("INFO", logger="gyronet.deploy.stream.record")

    recording = load_recording(lpbus_recording)
    recording.columns["time_s"] = np.arange(N_SAMPLES) / 100.0  # played at the rate the sensor is set to
    device = power_on("LPMS-BE1")
    link = tmp_path / "sensor"
    thread = started(play_in_thread(None, link, device=device, columns=recording.columns), link)
    summary = record_stream(str(link), tmp_path / "run.csv", lpbus=LpBusSetup(configure=True, rate_hz=100),
                            reconnect=FAST)
    thread.join(10)
    saved = load_recording(tmp_path / "run.csv")
    assert saved.meta["sensor"] == "LPMS-BE1" and saved.meta["fs_hz"] == "100" and "fs_hz_from_stamps" not in summary
    assert saved.meta["gyro_source"] == "raw" and saved.meta["gyro_autocalibration"] == "off"
    assert summary["n_samples"] == len(saved) == N_SAMPLES and device.rate_hz == 100
    progress = [r.getMessage() for r in caplog.records if "samples, up to time_s=" in r.getMessage()]
    assert progress and progress[-1].startswith(f"recorded {N_SAMPLES} samples, up to time_s=")
    layout = device.layout()
    filled = fill_columns(recording.columns, layout)
    rows = [layout.quantize({c: float(filled[c][i]) for c in layout.columns}) for i in range(N_SAMPLES)]
    for column in ("time_s", "temp_c", *GYRO_COLUMNS, "acc_z_g"):
        np.testing.assert_array_equal(saved.columns[column], [row[column] for row in rows])


def test_record_writes_the_rate_the_stamps_show_when_the_sensor_reports_another(lpbus_recording, tmp_path, caplog):
    """An emulator set to 100 Hz playing a file stamped 50 Hz apart: the reported rate made a file no loader took."""
    from gyronet.deploy.stream.record import record_stream

    recording = load_recording(lpbus_recording)
    recording.columns["time_s"] = np.arange(N_SAMPLES) / 50.0
    link = tmp_path / "sensor"
    thread = started(play_in_thread(None, link, device=power_on("LPMS-CU2"), columns=recording.columns), link)
    summary = record_stream(str(link), tmp_path / "run.csv", lpbus=LpBusSetup(configure=True, rate_hz=100),
                            reconnect=FAST)
    thread.join(10)
    saved = load_recording(tmp_path / "run.csv")
    assert saved.meta["fs_hz"] == "50" and saved.fs_hz == 50.0 and summary["fs_hz_from_stamps"] == 50.0
    assert len(saved) == N_SAMPLES
    warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert any(w.startswith("the sensor reported 100 Hz, but its time stamps are 50 Hz apart") for w in warnings)


@pytest.mark.slow
def test_scripts_configure_an_emulated_ig1_and_refuse_a_silent_port_in_one_line(bundle, lpbus_recording, tmp_path):
    """emulate_sensor.py sensor.model=... -> pty -> stream.py lpbus.configure=true; record.py on a mute port."""
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    link = tmp_path / "sensor"
    emulator = subprocess.Popen([sys.executable, "scripts/emulate_sensor.py", f"input={lpbus_recording}", "speed=0",
                                 "sensor.model=LPMS-IG1-RS232", f"link={link}", f"log_file={tmp_path / 'emu.json'}",
                                 f"hydra.run.dir={tmp_path / 'emu'}"], cwd=root, stdout=subprocess.DEVNULL,
                                stderr=subprocess.STDOUT)
    try:
        started(emulator, link, timeout_s=60)
        result = subprocess.run([sys.executable, "scripts/stream.py", f"model={bundle}", f"port={link}",
                                 f"output={tmp_path / 'live.csv'}", "lpbus.configure=true", "resample=true",
                                 "reconnect.give_up_s=0.5", "allan_every_s=0", f"hydra.run.dir={tmp_path / 'run'}"],
                                cwd=root, capture_output=True, text=True, timeout=120)
        emulator.wait(60)
    finally:
        emulator.kill()
    assert result.returncode == 0, result.stderr[-2000:]
    summary = json.loads((tmp_path / "run" / "stream_summary.json").read_text())
    emulated = json.loads((tmp_path / "emu.json").read_text())
    assert summary["sensor"]["model"] == "LPMS-IG1-RS232" and "acc" in summary["sensor"]["layout"]
    assert summary["n_samples"] == len(emulated["good_indices"]) == N_SAMPLES
    assert emulated["commands"][:4] == [6, 21, 20, 31] and emulated["commands"][-1] == 7
    failed = subprocess.run([sys.executable, "scripts/record.py", "port=loop://", f"output={tmp_path / 'r.csv'}",
                             "lpbus.configure=true", "lpbus.timeout_s=0.2", f"hydra.run.dir={tmp_path / 'rec'}"],
                            cwd=root, capture_output=True, text=True, timeout=120)
    assert failed.returncode == 2 and len(failed.stderr.strip().splitlines()) == 1
    assert failed.stderr.startswith("error: loop://: no answer to GOTO_COMMAND_MODE (command 6)")


def test_reference_built_frames_replayed_through_a_pty_decode_exactly(tmp_path):
    """Frames packed with struct as OpenZen's parsers read them (test_lpbus_config.reference_frame), not by
    gyronet's encoder, played through a pty and read by pyserial: every value as the reference computes it."""
    import math
    import struct

    from gyronet.deploy.stream import LpBusLayout, LpBusParser, Sample, read_samples
    from gyronet.deploy.stream.emulator import Event, StreamPlan
    from gyronet.deploy.stream.reader import open_port
    from test_lpbus_config import ig1_frame, legacy_frame

    def f32(value):
        return struct.unpack("<f", struct.pack("<f", value))[0]

    cases = {"legacy": [legacy_frame(4 * i, (0.01 * i, -0.02, 0.03), (0.0, 0.001 * i, 1.0), 20.0 + i)
                        for i in range(50)],
             "ig1": [ig1_frame(5 * i, (0.0, 0.001 * i, 1.0), (0.5 * i, -2.0, 0.25), 20.0 + i) for i in range(50)]}
    for generation, frames in cases.items():
        link = tmp_path / f"{generation}-sensor"
        plan = StreamPlan([Event(float(i), frame) for i, frame in enumerate(frames)], b"", {})
        started(play_in_thread(plan, link), link)
        port = open_port(str(link))
        samples = [item for item in read_samples(port, LpBusParser(LpBusLayout(generation=generation)),
                                                 url=str(link), give_up_s=0.3, backoff_s=0.05)
                   if isinstance(item, Sample)]
        assert len(samples) == 50
        for i, sample in enumerate(samples):
            if generation == "legacy":  # count * 0.0025 s; rad/s * 180/pi
                assert sample.time_s == pytest.approx(4 * i * 0.0025, rel=1e-12)
                assert sample.values["gyro_x_dps"] == pytest.approx(math.degrees(f32(0.01 * i)), rel=1e-12)
                assert sample.values["acc_y_g"] == f32(0.001 * i)
            else:  # count * 0.002 s; deg/s as sent, acc first
                assert sample.time_s == pytest.approx(5 * i * 0.002, rel=1e-12)
                assert sample.values["gyro_x_dps"] == f32(0.5 * i) and sample.values["acc_y_g"] == f32(0.001 * i)
            assert sample.values["temp_c"] == f32(20.0 + i)
