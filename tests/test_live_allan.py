"""Live Allan figures: bounded memory at 1 kHz, and N read from the binned history is right."""
import numpy as np
import pytest

from gyronet.deploy.stream.live import LiveAllan


def test_a_1khz_stream_keeps_ten_values_a_second_and_reads_n():
    fs_hz, duration_s, arw = 1000.0, 300.0, 3.0  # N in deg/sqrt(h)
    sigma_dps = arw / 60 * np.sqrt(fs_hz)
    rng = np.random.default_rng(0)
    allan = LiveAllan(None, every_s=100.0, fs_hz=fs_hz)
    for k in range(int(duration_s * fs_hz)):
        allan.add(k / fs_hz, rng.normal(0.0, sigma_dps, 3))
    assert len(allan.time_s) <= duration_s / 0.1 + 1
    allan.finish()
    for axis in "xyz":
        assert allan.last[axis]["arw_deg_rthr"] == pytest.approx(arw, rel=0.1)


def test_history_is_capped():
    allan = LiveAllan(None, every_s=1e9, fs_hz=10.0, max_history_s=100.0)
    for k in range(5000):
        allan.add(k / 10.0, np.zeros(3))
    assert len(allan.time_s) <= 1000 and allan.time_s[-1] > 499


@pytest.mark.parametrize("fs_hz", [10.0, 15.0, 400.0])
def test_bins_stay_contiguous_when_a_bin_holds_one_or_few_samples(fs_hz):
    # at 10 Hz a 0.1 s bin holds one sample: float rounding at the bin edges once left bins
    # empty, and the Allan report then used only the longest gap-free stretch
    n = int(3600 * fs_hz)
    allan = LiveAllan(None, every_s=1e9, fs_hz=fs_hz)
    for k in range(n):
        allan.add(1000.0 + k / fs_hz, np.zeros(3))
    allan.finish()
    steps = np.diff(allan.time_s)
    assert np.allclose(steps, allan.bin_s) and len(allan.time_s) == pytest.approx(3600 / allan.bin_s, abs=1)


def white_stream(fs_hz: float, duration_s: float, arw: float, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    n = int(duration_s * fs_hz)
    return np.arange(n) / fs_hz, rng.normal(0.0, arw / 60 * np.sqrt(fs_hz), (n, 3))


def test_frame_loss_is_bridged_not_cut_to_the_longest_stretch():
    # 1 % of the frames lost at 10 Hz (one sample a bin): the report used 131 of 593 bins
    fs_hz, arw = 10.0, 3.0
    time_s, rate = white_stream(fs_hz, 3600.0, arw, seed=1)
    kept = np.random.default_rng(2).random(len(time_s)) >= 0.01
    allan = LiveAllan(None, every_s=1e9, fs_hz=fs_hz)
    for t, r in zip(time_s[kept], rate[kept]):
        allan.add(t, r)
    allan.finish()
    n_bins = 3600.0 / allan.bin_s
    assert allan.bins["used"] == pytest.approx(n_bins, abs=2)
    assert allan.bins["filled"] == pytest.approx((~kept).sum(), rel=0.1) and allan.bins["filled"] < 0.02 * n_bins
    for axis in "xyz":
        assert allan.last[axis]["arw_deg_rthr"] == pytest.approx(arw, rel=0.1)


def test_long_gaps_and_restarted_clocks_stay_breaks():
    fs_hz = 10.0
    time_s, rate = white_stream(fs_hz, 600.0, 3.0, seed=3)
    allan = LiveAllan(None, every_s=1e9, fs_hz=fs_hz, max_fill_s=2.0)
    gone = (time_s >= 100.0) & (time_s < 130.0)  # the port down for 30 s: not bridged
    for t, r in zip(time_s[~gone], rate[~gone]):
        allan.add(t, r)
    allan.new_segment(0.0)  # the sensor replugged, its clock at 0 again: the next 200 s continue after a break
    for t, r in zip(time_s[:2000], rate[:2000]):
        allan.add(t, r)
    allan.finish()
    steps = np.diff(allan.time_s)
    assert steps.min() > 0  # the history's own time axis stays increasing across the restart
    assert allan.bins["filled"] == 0 and allan.bins["used"] == pytest.approx(470 / allan.bin_s, abs=2)
    bridged_time_s, bridged_rate, n_filled = allan.bridged()
    assert np.allclose(np.diff(bridged_time_s), allan.bin_s) and n_filled == 0


@pytest.mark.parametrize("fs_hz", [2.0, 10.0, 1000.0])
def test_add_many_in_chunks_gives_the_bins_and_reports_of_add_one_by_one(fs_hz):
    """The chunked live loop adds a read's samples at once: same bins (to rounding), reports at the same steps."""
    rng = np.random.default_rng(1)
    time_s = (np.arange(int(400 * fs_hz)) / fs_hz + 3.0)[rng.random(int(400 * fs_hz)) > 0.02]  # lost frames
    rate_dps = rng.normal(0.0, 0.1, (len(time_s), 3))
    restart = len(time_s) // 2
    time_s[restart:] -= 100.0  # a restarted sensor clock
    monitors = [LiveAllan(None, 60.0, fs_hz, max_history_s=100.0) for _ in range(2)]  # the cap is reached
    reports = [[], []]
    for monitor, seen in zip(monitors, reports):
        def report(step, figure=False, monitor=monitor, seen=seen, original=monitor.report):
            seen.append((step, monitor.rate_dps.copy()))
            original(step, figure)
        monitor.report = report
    one, many = monitors
    for i in range(len(time_s)):
        if i == restart:
            one.new_segment(time_s[i])
        one.add(time_s[i], rate_dps[i])
    start = 0
    for size in rng.integers(1, 3000, size=len(time_s)):
        stop = min(start + int(size), len(time_s))
        if start < restart <= stop:
            many.add_many(time_s[start:restart], rate_dps[start:restart])
            many.new_segment(time_s[restart])
            start = restart
        many.add_many(time_s[start:stop], rate_dps[start:stop])
        if stop == len(time_s):
            break
        start = stop
    one.finish()
    many.finish()
    assert [step for step, _ in reports[0]] == [step for step, _ in reports[1]] and len(reports[0]) >= 5
    for (_, a), (_, b) in zip(*reports):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-15)
    np.testing.assert_array_equal(one.time_s, many.time_s)
    assert one.bins == many.bins


def test_a_background_report_uses_the_history_as_it_was_due_and_holds_nothing_up():
    """The worker reads the history when the report fell due, even after the cap halved it meanwhile."""
    import threading

    fs_hz = 10.0
    rng = np.random.default_rng(2)
    time_s = np.arange(int(300 * fs_hz)) / fs_hz
    rate_dps = rng.normal(0.0, 0.1, (len(time_s), 3))
    now, later = (LiveAllan(None, 60.0, fs_hz, max_history_s=100.0, background=flag) for flag in (False, True))
    due = [[], []]
    release = threading.Event()
    for monitor, seen in zip((now, later), due):
        def report(step, figure=False, history=None, monitor=monitor, seen=seen, original=monitor.report):
            if monitor.background and not figure:
                assert threading.current_thread() is not threading.main_thread()
                release.wait(10.0)  # held until the history has moved on (and was halved)
            original(step, figure, history)
            seen.append((step, dict(monitor.last), dict(monitor.bins)))
        monitor.report = report
    for monitor in (now, later):
        for i in range(len(time_s)):
            monitor.add(time_s[i], rate_dps[i])
            if monitor is later and i == 1199:  # the first report (at 60 s) is held; the cap (1000 bins) passed
                assert len(due[1]) == 0 and later._worker.is_alive()
                release.set()
            if monitor is later and i >= 1199:
                later._worker.join()  # the next report never finds this one running
    now.finish()
    later.finish()
    assert [step for step, *_ in due[0]] == [60, 120, 180, 240, 300] and later.n_skipped == 0
    assert due[1][0] == due[0][0]
    assert [d[0] for d in due[1]] == [d[0] for d in due[0]]
