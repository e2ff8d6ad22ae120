"""Live Allan figures: bounded memory at 1 kHz, and N read from the binned history is right."""
import numpy as np
import pytest

from gyronet.stream.live import LiveAllan


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
