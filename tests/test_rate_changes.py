"""Issue 26 item 1: features follow real time. Jitter and clock drift cost nothing, a rate change inside a
recording is followed (resample=true) or refused in one line, and offline == live on the same samples."""
import subprocess
import sys

import numpy as np
import pandas as pd
import pytest
from hypothesis import given
from hypothesis import strategies as st

from gyronet.bundle.compensator import Compensator, RateChangeError
from gyronet.recordings.data import GYRO_COLUMNS, Recording, write_recording
from gyronet.model.features import PAPER_FEATURES, FeatureExtractor
from gyronet.bundle.offline import compensate_as_deployed
from gyronet.analysis.rate_table import residual_rms_dps
from gyronet.recordings.rate_watch import FAST, FAST_FACTOR, SPAN, VOTES, RateWatch
from gyronet.sim import simulate, timing

ROOT = __import__("pathlib").Path(__file__).resolve().parents[1]
STEP = 5  # the simulation runs at 10 Hz, five times the conftest bundle's 2 Hz


@pytest.fixture(scope="module")
def fast_sim():
    """Three hours of the cycle profile (held out from the bundle's paper run) at 10 Hz, with its truth."""
    return simulate("cycle", fs_hz=10.0, seed=4, sensor_seed=0, duration_s=3 * 3600.0)


@pytest.fixture(scope="module")
def full_rate(bundle, fast_sim):
    """The bundle on every 10 Hz sample (resample=true): the reference for any subset of its rows."""
    return compensate_as_deployed(Compensator.load(bundle), Recording(dict(fast_sim.recording), {}, "full"), True).rate_dps


def _ratio(bundle, fast_sim, full_rate, columns, rows, resample=False):
    """Residual of ``columns`` (simulation ``rows``) over the same rows' with full-rate features; or the refusal."""
    truth = {k: v[rows] for k, v in fast_sim.truth.items()}
    try:
        out = compensate_as_deployed(Compensator.load(bundle), Recording(dict(columns), {}, "damaged.csv"), resample)
    except RateChangeError as error:
        return str(error)
    reference = residual_rms_dps(truth["time_s"], full_rate[rows], truth)
    return residual_rms_dps(truth["time_s"], out.rate_dps, truth) / reference


def _two_rates(n_before=3000, n_after=3000, period_s=0.1, factor=2.0, jitter=0.0, seed=0):
    rng = np.random.default_rng(seed)
    time_s = np.concatenate([np.arange(n_before) * period_s, n_before * period_s + np.arange(n_after) * period_s / factor])
    return time_s + rng.uniform(-jitter, jitter, len(time_s)) * period_s / max(factor, 1.0)


@given(st.lists(st.integers(1, 400), min_size=1, max_size=40), st.sampled_from([0.5, 0.7, 1.5, 2.0, 4.0]))
def test_a_block_one_sample_at_a_time_and_any_chunking_find_the_same_changes(sizes, factor):
    time_s = _two_rates(600, 900, factor=factor, jitter=0.3, seed=len(sizes))
    whole = RateWatch(10.0).scan(time_s)
    one = RateWatch(10.0)
    assert [c for t in time_s.tolist() if (c := one.step(t)) is not None] == whole
    chunked, watch, start = [], RateWatch(10.0), 0
    while start < len(time_s):
        size = sizes[start % len(sizes)]
        chunked += watch.scan(time_s[start:start + size])
        start += size
    assert chunked == whole


@pytest.mark.parametrize("factor", [0.5, 0.7, 1.5, 2.0, 4.0])
def test_a_rate_change_is_found_soon_after_it_at_the_right_rate_and_refined_span_rows_later(factor):
    changes = RateWatch(10.0).scan(_two_rates(factor=factor, jitter=0.3))
    assert [c.refined for c in changes] == [False, True], changes
    change, refined = changes
    assert 2999 <= change.since_row <= 3000 + SPAN and change.row <= 3000 + SPAN + VOTES
    if factor * FAST_FACTOR * (1.0 - 0.3) > 1.0:  # every jittered interval under half the old period: at once
        assert change.row <= 3000 + 2 * FAST
    assert change.new_hz == pytest.approx(10.0 * factor, rel=0.08)
    assert refined.row == change.row + SPAN and refined.old_hz == change.new_hz
    assert refined.new_hz == pytest.approx(10.0 * factor, rel=0.02)


@pytest.mark.parametrize("factor", [0.5, 2.0, 4.0])
def test_the_refined_period_misses_by_no_more_than_the_stamp_jitter_over_span_intervals(factor):
    """Stamps off by up to j either way: SPAN intervals telescope to the period within 2 j / SPAN (0.6 / 8 before
    the refinement, when a rate twice as fast is adopted after FAST intervals)."""
    period_s, jitter_s = 0.1 / factor, 0.3 * 0.1 / max(factor, 1.0)
    for seed in range(40):
        changes = RateWatch(10.0).scan(_two_rates(factor=factor, jitter=0.3, seed=seed))
        assert changes[-1].refined, changes
        assert abs(1.0 / changes[-1].new_hz - period_s) <= 2 * jitter_s / SPAN + 1e-12, (seed, changes)


def test_a_sample_lost_soon_after_a_change_leaves_the_period_as_first_estimated():
    time_s = np.delete(_two_rates(factor=4.0, jitter=0.1), 3020)  # after the change is found (row 3008), before SPAN
    changes = RateWatch(10.0).scan(time_s)
    assert len(changes) == 1 and changes[0].new_hz == pytest.approx(40.0, rel=0.04), changes


@pytest.mark.parametrize("damage", ["stamp jitter 30 %", "loss 20 % and bursts", "drift 1 %", "200 ppm", "5 % slow"])
def test_jitter_loss_and_drift_are_not_a_rate_change(damage):
    rng = np.random.default_rng(1)
    time_s = np.arange(200_000) * 0.1
    if damage == "stamp jitter 30 %":
        time_s = timing.jitter_stamps(time_s, 0.3, rng)
    elif damage == "loss 20 % and bursts":
        keep = rng.random(len(time_s)) > 0.2
        for start in rng.choice(len(time_s) - 500, 20):
            keep[start:start + 300] = False
        time_s = time_s[keep]
    elif damage == "drift 1 %":
        time_s = timing.drift_stamps(time_s, end_fraction=0.01)
    elif damage == "200 ppm":
        time_s = timing.drift_stamps(time_s, offset_ppm=200.0)
    else:
        time_s = timing.jitter_stamps(time_s * 1.04, 0.2, rng)  # 4 % slow (inside the tolerance), jittered
    assert RateWatch(10.0).scan(time_s) == []


def test_the_extractor_follows_a_rate_change_exactly_like_one_sample_at_a_time():
    time_s = _two_rates(2000, 3000, factor=2.0, jitter=0.2)
    temp_c = 20.0 + 10.0 * np.sin(time_s / 300.0)
    columns = {"time_s": time_s, "temp_c": temp_c}
    batch = FeatureExtractor(PAPER_FEATURES, 10.0)
    whole = batch.process(columns)
    assert [c.refined for c in batch.rate_changes] == [False, True] and batch.dt_s == pytest.approx(0.05, rel=0.02)
    live = FeatureExtractor(PAPER_FEATURES, 10.0)
    rows = np.array([live.process_row(t, {"temp_c": c})[0] for t, c in zip(time_s.tolist(), temp_c.tolist())])
    np.testing.assert_allclose(rows, whole, rtol=0, atol=1e-9)
    # and dT/dt is right at the new rate (true rate: 10/300 cos(t/300) degC/s)
    late = time_s > time_s[2000] + 30.0
    true_rate = 10.0 / 300.0 * np.cos(time_s[late] / 300.0)
    assert np.abs(whole[late, 1] - true_rate).max() < 2e-3


def test_doubling_for_the_last_fifth_is_refused_or_followed(bundle, fast_sim, full_rate):
    """The issue's row 1 (the median stays at the bundle's rate): was 1.58x / 1.06x / 1.03x."""
    n = len(fast_sim.recording["time_s"])
    rows = timing.rate_change_rows(n, STEP, 2, 0.8)  # 2 Hz (the bundle's), then 5 Hz for the last fifth
    columns = {k: v[rows] for k, v in fast_sim.recording.items()}
    refused = _ratio(bundle, fast_sim, full_rate, columns, rows)
    assert isinstance(refused, str) and "\n" not in refused
    assert "damaged.csv: near row" in refused and "from 2 Hz to 5 Hz" in refused and "resample=true" in refused
    line_row = int(refused.split("near row ")[1].split(" ")[0]) - 1
    cut = np.flatnonzero(np.diff(rows) < STEP)[0] + 1  # the first row at 5 Hz
    assert cut - 1 <= line_row <= cut + SPAN
    followed = _ratio(bundle, fast_sim, full_rate, columns, rows, resample=True)
    assert np.all(followed <= 1.05), followed


def test_compensate_py_refuses_a_rate_change_in_one_line_with_the_file_line(bundle, fast_sim, tmp_path):
    n = len(fast_sim.recording["time_s"])
    rows = timing.rate_change_rows(n, STEP, 2, 0.9)
    path = tmp_path / "doubles.csv"
    write_recording(path, {k: v[rows] for k, v in fast_sim.recording.items()}, {})
    done = subprocess.run([sys.executable, "scripts/compensate.py", f"model={bundle}", f"input={path}",
                           f"output={tmp_path / 'out.csv'}", f"hydra.run.dir={tmp_path / 'run'}"],
                          cwd=ROOT, capture_output=True, text=True, env={**__import__("os").environ, "PYTHONPATH": str(ROOT)})
    assert done.returncode == 2, done.stderr[-2000:]
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "doubles.csv: near line" in lines[0] and "from 2 Hz to 5 Hz" in lines[0], lines
    assert not (tmp_path / "out.csv").exists()


def test_live_chunked_equals_offline_through_a_rate_change(bundle, fast_sim, tmp_path, monkeypatch):
    import gyronet.deploy.stream.live as live
    from gyronet.deploy.stream import Sample

    n = len(fast_sim.recording["time_s"])
    rows = timing.rate_change_rows(n, STEP, 2, 0.97)
    recording = Recording({k: v[rows] for k, v in fast_sim.recording.items()}, {}, "changes.csv")

    def scripted(*args, **kwargs):
        samples = [Sample(float(recording.time_s[row]), {c: float(recording.columns[c][row]) for c in ("temp_c", *GYRO_COLUMNS)})
                   for row in range(len(recording))]
        for start in range(0, len(samples), 7):
            yield samples[start:start + 7]

    monkeypatch.setattr(live, "read_chunks", scripted)
    live.run_stream(bundle, "/dev/null", tmp_path / "live.csv", allan_every_s=0, reconnect={"wait_at_start": True},
                    resample=True)
    expected = compensate_as_deployed(Compensator.load(bundle), recording, resample=True).rate_dps
    got = pd.read_csv(tmp_path / "live.csv", comment="#")[list(GYRO_COLUMNS)].to_numpy()
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-9)
    with pytest.raises(RateChangeError, match=r"from 2 Hz to 5 Hz.*resample=true"):
        live.run_stream(bundle, "/dev/null", tmp_path / "live2.csv", allan_every_s=0, reconnect={"wait_at_start": True})


def test_the_c_compensator_flags_the_rate_change_where_compensate_py_refuses_it(bundle, fast_sim, tmp_path):
    """The C compensator cannot follow a rate (its coefficients are the bundle's): it finds the change with the
    same stamps and flags GYRONET_RATE_CHANGED from the very sample compensate.py refuses at; before it, C == Python."""
    import shutil

    from gyronet.deploy.c_export import DRIVER, write_c

    cc = shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        pytest.skip("no C compiler (cc or gcc) on this machine")
    rows = timing.rate_change_rows(20_000, STEP, 2, 0.75)  # 2 Hz (the bundle's) for 2000 s, then 5 Hz
    columns = {k: v[rows] for k, v in fast_sim.recording.items()}
    columns["time_s"] = timing.jitter_stamps(columns["time_s"], 0.2, np.random.default_rng(3))
    with pytest.raises(RateChangeError) as refused:
        Compensator.load(bundle).process(columns)
    at = refused.value.change.row
    write_c(bundle, tmp_path / "c")
    flags = ["-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic", "-O2"]
    subprocess.run([cc, *flags, "-I", str(tmp_path / "c"), str(DRIVER), str(tmp_path / "c" / "gyronet_compensator.c"),
                    "-lm", "-o", str(tmp_path / "driver")], check=True)
    names = ["time_s", "temp_c", *GYRO_COLUMNS]
    np.savetxt(tmp_path / "in.csv", np.column_stack([columns[c] for c in names]), delimiter=",", fmt="%.17g",
               header=",".join(names), comments="")
    subprocess.run([str(tmp_path / "driver"), str(tmp_path / "in.csv"), str(tmp_path / "out.csv")], check=True,
                   capture_output=True)
    c_out = np.loadtxt(tmp_path / "out.csv", delimiter=",", skiprows=1, ndmin=2)
    changed = (c_out[:, 3].astype(int) & 4) != 0
    assert np.flatnonzero(changed)[0] == at and changed[at:].all()
    before = Compensator.load(bundle).process({k: v[:at] for k, v in columns.items()})
    assert np.abs(c_out[:at, :3] - before.rate_dps).max() < 1e-4


def test_training_with_a_kalman_stage_refuses_a_rate_change_in_one_line(fast_sim, tmp_path):
    from gyronet.training.dataset import DriftData
    from gyronet.errors import GyronetError
    from gyronet.model.rbf import RBFNet
    from gyronet.training.pipeline import kalman_stage

    n = len(fast_sim.recording["time_s"])
    rows = timing.rate_change_rows(n, STEP, 2, 0.8)
    path = tmp_path / "train.csv"
    write_recording(path, {k: v[rows] for k, v in fast_sim.recording.items()}, {})
    data = DriftData(str(path))
    model = RBFNet(data.n_features, 3, 4, rbf_inputs=[0], linear=True, temp_degree=3, clamp=True)
    with pytest.raises(GyronetError, match=r"train.csv: near line \d+ .*from 2 Hz to 5 Hz.*kalman=disabled"):
        kalman_stage({"enabled": True}, model, data)


def test_a_rate_change_error_crosses_a_process_boundary_intact():
    """joblib and submitit pickle a worker's error: one that cannot be rebuilt took a whole fleet or sweep down."""
    import pickle

    from gyronet.recordings.rate_watch import RateChange

    change = RateChange(33, 16.5, 1.0, 2.0, 30, 15.0, False)
    error = pickle.loads(pickle.dumps(RateChangeError("F.csv: the sampling rate changes", change)))
    assert isinstance(error, RateChangeError) and str(error) == "F.csv: the sampling rate changes"
    assert error.change == change


def test_stamps_that_stop_or_repeat_are_no_rate_and_scan_agrees_with_step():
    """A FIFO's batch stamped once divided by zero (ZeroDivisionError from Compensator.process); a clock that
    stops made the vectorised scan rebuild a window a row."""
    from gyronet.recordings.rate_watch import RateWatch

    time_s = np.arange(20000) * 0.01
    time_s[3000:3010] = time_s[3000]  # a batch stamped once
    time_s[8000:13000] = time_s[8000]  # a clock that stops for 5,000 rows
    time_s[15000:15002] = np.inf  # two stamps that are no time, in a row
    stepped = RateWatch(100.0)
    by_step = [c for t in time_s.tolist() if (c := stepped.step(t)) is not None]
    by_scan = RateWatch(100.0).scan(time_s)
    assert [tuple(map(str, c)) for c in by_scan] == [tuple(map(str, c)) for c in by_step]
    assert all(np.isfinite(c.new_hz) and c.new_hz > 0 for c in by_scan)
