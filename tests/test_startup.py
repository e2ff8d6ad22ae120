"""Start-up offsets: the run's turn-on bias from its first still seconds, offline and live alike."""
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from gyronet.bundle.compensator import Compensator
from gyronet.recordings.data import load_recording, load_truth
from gyronet.errors import GyronetError
from gyronet.sim import simulate, write_simulation
from gyronet.bundle.startup import StartupMotionError, StartupOffset

from conftest import FAST_FS_HZ, ROOT


@pytest.fixture(scope="module")
def biased_csv(tmp_path_factory):
    """The cycle history of the bundle's sensor, with a turn-on bias of its own (0.2 deg/s per axis std)."""
    path = tmp_path_factory.mktemp("sim") / "biased.csv"
    write_simulation(simulate("cycle", fs_hz=FAST_FS_HZ, seed=5, sensor_seed=0,
                              sensor={"turn_on_bias_dps": 0.2}), path)
    return path


def test_the_window_mean_is_removed_after_the_window_and_only_after():
    rng = np.random.default_rng(0)
    time_s = np.arange(1000.0)
    rate = rng.normal(0, 0.1, (1000, 3)) + [0.3, -0.2, 0.05]
    startup = StartupOffset(still_s=300)
    out = startup.process(time_s, rate)
    np.testing.assert_array_equal(out[:300], rate[:300])
    np.testing.assert_allclose(out[300:], rate[300:] - rate[:300].mean(0), atol=1e-12)
    assert startup.done


def test_a_window_whose_samples_span_under_half_of_it_is_named(caplog):
    rng = np.random.default_rng(0)
    time_s = np.concatenate([[0.0], np.arange(100.0, 400.0)])  # one sample, then a 100 s gap past a 60 s window
    with caplog.at_level("WARNING", logger="gyronet.bundle.startup"):
        StartupOffset(still_s=60).process(time_s, rng.normal(0, 0.1, (len(time_s), 3)))
    assert "span 1 s of its 60 s (1 samples" in caplog.text
    caplog.clear()
    with caplog.at_level("WARNING", logger="gyronet.bundle.startup"):
        StartupOffset(still_s=60).process(np.arange(100.0), rng.normal(0, 0.1, (100, 3)))
    assert not caplog.text


def test_the_offsets_noise_is_the_window_means_and_widens_only_what_follows():
    """White noise of 0.1 deg/s on a slow drift: the offset's error is 0.1 / sqrt(n), the bar grows by it."""
    rng = np.random.default_rng(2)
    time_s = np.arange(0.0, 2000.0, 0.5)
    rate = rng.normal(0, [0.1, 0.2, 0.05], (len(time_s), 3)) + 1e-4 * time_s[:, None]
    startup = StartupOffset(still_s=600)
    chunks = [startup.process(time_s[i:i + 333], rate[i:i + 333]) for i in range(0, len(time_s), 333)]
    assert np.vstack(chunks).shape == rate.shape
    np.testing.assert_allclose(np.sqrt(startup.noise_var_dps2), np.array([0.1, 0.2, 0.05]) / np.sqrt(1200), rtol=0.06)
    whole = StartupOffset(still_s=600)
    whole.process(time_s, rate)  # chunks or not, the same differences
    np.testing.assert_allclose(whole.noise_var_dps2, startup.noise_var_dps2, rtol=1e-12)
    sigma = np.full((len(time_s), 3), 0.003)
    wide = whole.widen(sigma)  # of the chunk it last had
    after = time_s >= 600
    np.testing.assert_array_equal(wide[~after], sigma[~after])
    np.testing.assert_allclose(wide[after], np.broadcast_to(np.sqrt(0.003 ** 2 + whole.noise_var_dps2), (after.sum(), 3)))
    last = (len(time_s) - 1) // 333 * 333  # the chunked one's last chunk: all past the window
    np.testing.assert_allclose(startup.widen(sigma[last:]), wide[last:])


def test_the_bar_widens_by_the_offsets_noise_unless_its_runs_were_scored_with_one(bundle, biased_csv):
    """Batch and row by row alike; a campaign bar calibrated with a start-up window has that noise already."""
    columns = {k: v[:2000] for k, v in load_recording(biased_csv).columns.items()}
    after = columns["time_s"] - columns["time_s"][0] >= 120

    def sigma(still_s: float, startup_s: float = 0.0, rows: bool = False) -> np.ndarray:
        comp = Compensator.load(bundle)
        comp.error_bar.calibration["startup_s"] = startup_s
        comp.use_startup(still_s=still_s)
        if not rows:
            return comp.process(columns).drift_sigma_dps
        out = comp.process({k: v[:300] for k, v in columns.items()}).drift_sigma_dps.tolist()
        comp.use_small_chunks()
        for i in range(300, len(columns["time_s"])):
            row = comp.process_row(float(columns["time_s"][i]), {k: float(v[i]) for k, v in columns.items() if k != "time_s"})
            out.append(row.drift_sigma_dps)
        return np.array(out)

    plain, widened = sigma(0.0), sigma(120.0)
    np.testing.assert_array_equal(widened[~after], plain[~after])
    assert np.all(widened[after] > plain[after])
    np.testing.assert_allclose(sigma(120.0, rows=True), widened, rtol=1e-12)
    np.testing.assert_array_equal(sigma(120.0, startup_s=120.0), plain)


def test_one_call_equals_one_call_per_sample_with_a_bundle(bundle, biased_csv):
    recording = load_recording(biased_csv)
    whole = Compensator.load(bundle)
    whole.use_startup(still_s=120)
    batch = whole.process(recording.columns).rate_dps
    live = Compensator.load(bundle)
    live.use_startup(still_s=120)
    rows = [live.process({k: v[i:i + 1] for k, v in recording.columns.items()}).rate_dps for i in range(600)]
    np.testing.assert_allclose(np.vstack(rows), batch[:600], rtol=0, atol=1e-12)
    live.reset()  # a new stream starts a new window
    assert not live.startup.done


def test_the_offset_removes_a_turn_on_bias(bundle, biased_csv):
    recording = load_recording(biased_csv)
    truth = load_truth(biased_csv).columns
    bias = np.column_stack([truth[f"turn_on_bias_{a}_dps"] for a in "xyz"])[0]
    assert np.max(np.abs(bias)) > 0.05
    comp = Compensator.load(bundle)
    plain = comp.process(recording.columns).rate_dps
    comp.use_startup(still_s=300)
    comp.reset()
    with_offset = comp.process(recording.columns).rate_dps
    after = recording.time_s >= recording.time_s[0] + 300
    true_rate = np.column_stack([truth[f"true_rate_{a}_dps"] for a in "xyz"])
    err_plain = np.abs((plain - true_rate)[after].mean(0))
    err_offset = np.abs((with_offset - true_rate)[after].mean(0))
    assert np.all(err_offset < 0.5 * err_plain), (err_plain, err_offset)
    np.testing.assert_allclose(comp.startup.offset_dps, bias, atol=0.05)


def test_motion_in_the_window_is_refused():
    rng = np.random.default_rng(1)
    time_s = np.arange(600.0)
    rate = rng.normal(0, 0.12, (600, 3))
    rate[100:105, 2] += 3.0  # someone turns the sensor for 5 s
    with pytest.raises(StartupMotionError, match="z rate departs"):
        StartupOffset(still_s=300).process(time_s, rate)
    # a still window at the same noise passes, and a slow 0.3 deg/s wobble below the bound too
    rate[100:105, 2] -= 3.0
    rate[200:210, 0] += 0.3
    StartupOffset(still_s=300).process(time_s, rate)


def test_a_short_record_and_bad_settings_are_user_errors():
    startup = StartupOffset(still_s=300)
    startup.process(np.arange(10.0), np.zeros((10, 3)))
    with pytest.raises(GyronetError, match="shorter than startup.still_s"):
        startup.require_done("f.csv")
    for bad in (-1.0, float("nan")):
        with pytest.raises(GyronetError, match="still_s"):
            StartupOffset(still_s=bad)


def _compensate(bundle, csv, out, *overrides):
    return subprocess.run([sys.executable, "scripts/compensate.py", f"model={bundle}", f"input={csv}", f"output={out}",
                           f"hydra.run.dir={Path(out).parent / 'hydra'}", *overrides], cwd=ROOT, capture_output=True,
                          text=True)


def test_compensate_script_takes_startup_and_refuses_motion_in_one_line(bundle, biased_csv, tmp_path):
    out = tmp_path / "o.csv"
    proc = _compensate(bundle, biased_csv, out, "startup.still_s=300")
    assert proc.returncode == 0, proc.stderr
    recording = load_recording(biased_csv)
    comp = Compensator.load(bundle)
    comp.use_startup(still_s=300)
    expected = comp.process(recording.columns).rate_dps
    written = load_recording(out, required=("time_s", "gyro_x_dps")).gyro_dps
    np.testing.assert_allclose(written, expected, rtol=1e-11, atol=1e-12)
    assert "\n# startup_still_s=300\n" in out.read_text()[:500]  # for allan.py's still_s
    # the same file with a turn in its first minute
    moved = dict(recording.columns)
    moved["gyro_y_dps"] = moved["gyro_y_dps"].copy()
    moved["gyro_y_dps"][20:30] += 20.0
    from gyronet.recordings.data import write_recording

    moved_csv = tmp_path / "moved.csv"
    write_recording(moved_csv, moved, recording.meta)
    proc = _compensate(bundle, moved_csv, out, "startup.still_s=300")
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and f"{moved_csv}: motion in the start-up window" in lines[0], proc.stderr


def test_live_stream_with_startup_equals_offline(bundle, biased_csv, tmp_path):
    """stream.py's loop (in-process, over a pty) with startup.still_s gives the offline numbers."""
    import pandas as pd

    from gyronet.recordings.data import GYRO_COLUMNS, write_recording
    from gyronet.deploy.stream import FaultPlan, plan_stream
    from gyronet.deploy.stream.live import run_stream
    from gyronet.deploy.stream.pty_sensor import play_in_thread

    recording = load_recording(biased_csv).slice(slice(0, 300))
    short = write_recording(tmp_path / "short.csv", recording.columns, recording.meta)
    plan = plan_stream(recording.columns, "csv", FaultPlan(seed=1))
    link = tmp_path / "sensor"
    thread = play_in_thread(plan, link)
    run_stream(bundle, str(link), tmp_path / "live.csv", protocol="csv", allan_every_s=0,
               reconnect={"backoff_s": 0.05, "max_backoff_s": 0.2, "give_up_s": 0.5},
               startup={"still_s": 60, "motion_dps": 0.5})
    thread.join(10)
    live = pd.read_csv(tmp_path / "live.csv", comment="#")
    assert "\n# startup_still_s=60\n" in (tmp_path / "live.csv").read_text()[:500]
    comp = Compensator.load(bundle)
    comp.use_startup(still_s=60)
    offline = comp.process(load_recording(short).columns).rate_dps
    assert len(live) == len(offline)
    np.testing.assert_allclose(live[list(GYRO_COLUMNS)].to_numpy(), offline, rtol=0, atol=1e-9)


def test_the_output_names_the_true_rate_left_in_it(bundle, biased_csv, tmp_path):
    """Without a start-up offset the input's Earth rate stays in the output; the offset takes the window's rate,
    Earth's included, unless told its static_rate_dps: an output labelled with a rate it lacks read as drift."""
    from gyronet.bundle.offline import compensate_file

    assert "# static_rate_dps=" in biased_csv.read_text()[:400]
    lines = {}
    for name, startup in (("plain", None), ("offset", {"still_s": 600}),
                          ("told", {"still_s": 600, "static_rate_dps": [0.0, 0.01, 0.0]})):
        compensate_file(bundle, biased_csv, tmp_path / f"{name}.csv", startup=startup)
        head = (tmp_path / f"{name}.csv").read_text()[:400]
        lines[name] = [line for line in head.splitlines() if line.startswith("# static_rate_dps=")]
    assert lines["plain"] and not lines["offset"] and lines["told"] == ["# static_rate_dps=0.0,0.01,0.0"]


@pytest.mark.parametrize("options, message", [
    ({"still_s": 600, "static_rate_dps": [0, 0.003]}, r"static_rate_dps needs 3 numbers \(x, y, z, deg/s\), got \[0, 0.003\]"),
    ({"still_s": 600, "static_rate_dps": 0.003}, "static_rate_dps needs 3 numbers"),
    ({"still_s": "10min"}, "startup.still_s must be a number, got '10min'"),
    ({"still_s": 600, "motion_dps": None}, "startup.motion_dps must be a number, got None"),
])
def test_a_bad_startup_option_is_one_line(bundle, options, message):
    """compensate.py and stream.py pass these straight through: each was a ValueError or TypeError traceback."""
    with pytest.raises(GyronetError, match=message):
        Compensator.load(bundle).use_startup(**options)
