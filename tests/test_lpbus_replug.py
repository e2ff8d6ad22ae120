"""Issue 13, a replug: the sensor comes back power-cycled on a new pty (the emulator's ``replugs``); the
live path and record.py set it up again, or check its first frames again, or refuse it by name."""
import logging
import time

import numpy as np
import pandas as pd
import pytest

from gyronet.recordings.data import GYRO_COLUMNS, load_recording
from gyronet.deploy.stream.lpbus_device import EmulatedLpms
from gyronet.deploy.stream.lpbus_link import SensorError
from gyronet.deploy.stream.lpbus_probe import LayoutError
from gyronet.deploy.stream.lpbus_setup import LpBusSetup
from gyronet.deploy.stream.pty_sensor import play_in_thread
from conftest import LPBUS_SAMPLES as N_SAMPLES
from test_lpbus_live import FAST, offline, power_on, started

SPLIT = N_SAMPLES // 2


def halves(path):
    """The recording cut in two, the second half's clock from 0 again (a power-cycled sensor)."""
    columns = load_recording(path).columns
    first = {c: np.asarray(v)[:SPLIT] for c, v in columns.items()}
    second = {c: np.asarray(v)[SPLIT:] for c, v in columns.items()}
    second["time_s"] = second["time_s"] - second["time_s"][0]
    return first, second


def run_live(bundle, link, tmp_path, lpbus, **options):
    from gyronet.deploy.stream.live import run_stream

    return run_stream(bundle, str(link), tmp_path / "live.csv", allan_every_s=0, reconnect=FAST, resample=True,
                      lpbus=lpbus, **options)


def test_a_power_cycled_sensor_is_set_up_again_and_live_equals_offline_per_segment(bundle, lpbus_recording,
                                                                                   tmp_path, caplog):
    first, second = halves(lpbus_recording)
    again = power_on("LPMS-CU2")  # back with its power-on outputs, 16-bit, auto-calibration on
    link = tmp_path / "sensor"
    thread = started(play_in_thread(None, link, device=power_on("LPMS-CU2"), columns=first,
                                    replugs=[(again, second)], preroll_frames=3), link)
    with caplog.at_level(logging.INFO, logger="gyronet.deploy.stream.lpbus_setup"):
        summary = run_live(bundle, link, tmp_path, LpBusSetup(configure=True, timeout_s=2.0))
    thread.join(10)
    assert again.commands[0] == 6 and again.commands[-1] == 7  # the host talked to the sensor that came back
    assert not again.gyro_autocalibration and again.precision == 32
    reopened = [r.getMessage() for r in caplog.records if "reopened" in r.getMessage()]
    assert len(reopened) == 1 and "LPMS-CU2 set up again: outputs" in reopened[0]
    assert "gyro auto-calibration off" in reopened[0]
    assert summary["faults"] == {"port_lost": 2} and summary["clock_restarts"] == 1
    live = pd.read_csv(tmp_path / "live.csv", comment="#")
    assert len(live) == N_SAMPLES
    for rows, columns, plan in [(live[:SPLIT], first, thread.plans[0]), (live[SPLIT:], second, thread.plans[1])]:
        inputs, out = offline(bundle, columns, plan, again.layout())  # each segment from the power-on state
        np.testing.assert_array_equal(rows["time_s"].to_numpy(), inputs["time_s"])
        np.testing.assert_allclose(rows[list(GYRO_COLUMNS)].to_numpy(), out.rate_dps, rtol=0, atol=1e-9)


def test_another_sensor_behind_the_reopened_port_ends_the_run_by_name(bundle, lpbus_recording, tmp_path):
    first, second = halves(lpbus_recording)
    link = tmp_path / "sensor"
    started(play_in_thread(None, link, device=power_on("LPMS-CU2"), columns=first,
                           replugs=[(power_on("LPMS-IG1-RS232"), second)]), link)
    with pytest.raises(SensorError, match=r"not the one set up at the start: sensor ig1 LPMS-IG1-RS232, firmware "
                                          r"v2\.0\.5, not legacy LPMS-CU2, firmware 2\.0\.5; frames .*GET_IMU_TRANS"):
        run_live(bundle, link, tmp_path, LpBusSetup(configure=True, timeout_s=2.0))
    assert len(pd.read_csv(tmp_path / "live.csv", comment="#")) == SPLIT  # what came before, kept whole


def test_a_listening_run_checks_the_first_frames_again_after_a_reopen(bundle, lpbus_recording, tmp_path):
    """Legacy gyro + acc + temperature, then an IG1 sending acc + gyro + temperature: the same frame length."""
    first, second = halves(lpbus_recording)
    legacy = EmulatedLpms(model="LPMS-CU2", fields=("gyro", "acc", "temperature"), precision=32, rate_hz=100)
    ig1 = EmulatedLpms(model="LPMS-IG1-RS232", fields=("acc", "gyro", "temperature"), precision=32, rate_hz=100)
    link = tmp_path / "sensor"
    started(play_in_thread(None, link, device=legacy, columns=first, replugs=[(ig1, second)],
                           command_wait_s=0.2), link)
    with pytest.raises(LayoutError, match=r"sensor, reopened: the first 20 frames do not read as .*register bits "
                                          r"legacy 11, 12, 13\).*1 g"):
        run_live(bundle, link, tmp_path, LpBusSetup(configure=False))
    assert len(pd.read_csv(tmp_path / "live.csv", comment="#")) == SPLIT


def test_record_sets_a_power_cycled_sensor_up_again(lpbus_recording, tmp_path):
    from gyronet.deploy.stream.record import record_stream

    first, second = halves(lpbus_recording)
    for columns in (first, second):
        columns["time_s"] = np.arange(len(columns["time_s"])) / 100.0  # played at the rate the sensor is set to
    again = power_on("LPMS-BE1")
    link = tmp_path / "sensor"
    thread = started(play_in_thread(None, link, device=power_on("LPMS-BE1"), columns=first,
                                    replugs=[(again, second)]), link)
    summary = record_stream(str(link), tmp_path / "run.csv", lpbus=LpBusSetup(configure=True, rate_hz=100),
                            reconnect=FAST)
    thread.join(10)
    saved = load_recording(tmp_path / "run.csv")
    assert summary["n_samples"] == len(saved) == N_SAMPLES and summary["clock_restarts"] == 1
    assert again.rate_hz == 100 and not again.gyro_autocalibration
    layout = again.layout()
    np.testing.assert_array_equal(saved.columns["temp_c"][SPLIT:],
                                  [layout.quantize({c: float(second[c][i]) for c in layout.columns
                                                    if c in second})["temp_c"] for i in range(SPLIT)])
    assert np.all(np.diff(saved.columns["time_s"]) > 0)


def test_a_link_drop_without_a_power_cycle_is_set_up_again_with_nothing_to_change(bundle, lpbus_recording, tmp_path,
                                                                                    caplog):
    from gyronet.deploy.stream import FaultPlan

    recording = load_recording(lpbus_recording)
    device = power_on("LPMS-CU2")
    link = tmp_path / "sensor"
    thread = started(play_in_thread(None, link, device=device, columns=recording.columns,
                                    faults=FaultPlan(drop_port_at_s=(50.0,))), link)
    with caplog.at_level(logging.INFO, logger="gyronet.deploy.stream.lpbus_setup"):
        summary = run_live(bundle, link, tmp_path, LpBusSetup(configure=True, timeout_s=2.0))
    thread.join(10)
    assert "LPMS-CU2 set up again: it had kept its settings" in caplog.text
    assert summary["n_samples"] == N_SAMPLES and summary["faults"] == {"port_lost": 2}
    assert device.commands.count(6) == 2 and device.commands[-1] == 7


def test_record_refuses_another_sensor_after_a_replug_and_still_writes_its_summary(lpbus_recording, tmp_path):
    import json

    from gyronet.deploy.stream.record import record_stream

    first, second = halves(lpbus_recording)
    for columns in (first, second):
        columns["time_s"] = np.arange(len(columns["time_s"])) / 100.0
    link = tmp_path / "sensor"
    started(play_in_thread(None, link, device=power_on("LPMS-CU2"), columns=first,
                           replugs=[(power_on("LPMS-B2"), second)]), link)
    with pytest.raises(SensorError, match=r"sensor legacy LPMS-B2, firmware 2\.0\.5, not legacy LPMS-CU2"):
        record_stream(str(link), tmp_path / "run.csv", lpbus=LpBusSetup(configure=True, rate_hz=100),
                      reconnect=FAST, summary_path=tmp_path / "s.json")
    summary = json.loads((tmp_path / "s.json").read_text())
    assert summary["stopped"] == "refused" and "LPMS-B2" in summary["refused"]
    assert summary["n_samples"] == len(load_recording(tmp_path / "run.csv")) == SPLIT


def test_ctrl_c_without_a_stop_poll_still_writes_the_chunk_in_flight(tmp_path, monkeypatch):
    """record_stream called from Python (no ``stop``): SIGINT at the 10th row of a 25-sample read."""
    import os
    import signal

    from gyronet.deploy.stream import Sample
    from gyronet.deploy.stream import record

    values = {"gyro_x_dps": 0.1, "gyro_y_dps": 0.2, "gyro_z_dps": 0.3, "acc_x_g": 0.0, "acc_y_g": 0.0,
              "acc_z_g": 1.0, "temp_c": 30.0}

    def two_reads(port, parser, *, should_stop, **options):
        for read in range(2):
            if should_stop():
                return
            for i in range(25):
                if read == 0 and i == 10:
                    os.kill(os.getpid(), signal.SIGINT)
                yield Sample(0.01 * (25 * read + i), values)

    monkeypatch.setattr(record, "read_samples", two_reads)
    summary = record.record_stream("loop://", tmp_path / "run.csv", lpbus=LpBusSetup(configure=False))
    assert summary["stopped"] == "interrupted" and summary["n_samples"] == 25
    assert len(load_recording(tmp_path / "run.csv")) == 25


def test_record_keeps_the_length_of_an_unplug_as_the_break_in_time(lpbus_recording, tmp_path):
    """A clock restart after a 3 s unplug: time_s went on 1.01 s later (one interval and restart_gap_s), so a
    20-minute unplug during a ramp read as a jump of degrees in a second."""
    from gyronet.deploy.stream.record import record_stream

    first, second = halves(lpbus_recording)
    for columns in (first, second):
        columns["time_s"] = np.arange(len(columns["time_s"])) / 100.0
    link = tmp_path / "sensor"
    thread = started(play_in_thread(None, link, device=power_on("LPMS-BE1"), columns=first, port_down_s=3.0,
                                    replugs=[(power_on("LPMS-BE1"), second)]), link)
    summary = record_stream(str(link), tmp_path / "run.csv", lpbus=LpBusSetup(configure=True, rate_hz=100),
                            reconnect={**FAST, "give_up_s": 10.0})
    thread.join(10)
    time_s = load_recording(tmp_path / "run.csv").columns["time_s"]
    assert summary["clock_restarts"] == 1 and len(time_s) == N_SAMPLES
    assert 3.0 <= time_s[SPLIT] - time_s[SPLIT - 1] < 10.0
    np.testing.assert_allclose(np.diff(time_s[SPLIT:]), 0.01, atol=1e-6)


@pytest.mark.skipif(not hasattr(time, "CLOCK_BOOTTIME"), reason="Linux's boot-time clock")
def test_an_outage_is_timed_on_a_clock_that_counts_a_suspended_host(monkeypatch):
    """time.monotonic stops while a laptop sleeps: an unplug over a suspend was written short by the sleep."""
    from gyronet.deploy.stream import record

    clocks = {time.CLOCK_BOOTTIME: 5000.0, time.CLOCK_MONOTONIC: 200.0}
    monkeypatch.setattr(time, "clock_gettime", lambda clock: clocks[clock])
    monkeypatch.setattr(time, "monotonic", lambda: clocks[time.CLOCK_MONOTONIC])
    assert record._host_s() == 5000.0
