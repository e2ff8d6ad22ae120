"""gyronet.allan against allantools, the NBS14 reference values, simulated noise of known size and
a real ADIS16405 record; scripts/allan.py end to end."""
import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from gyronet.allan import (allan_report, continuous_segments, format_table, log_taus, noise_parameters, oadev,
                           plot_allan, report_to_json)
from gyronet.recordings.data import write_recording
from gyronet.errors import GyronetError

allantools = pytest.importorskip("allantools")

ROOT = Path(__file__).resolve().parents[1]
ADIS_DIR = ROOT.parent / "shared" / "data" / "real" / "smac-adis16405"

# NIST SP 1065 (2008), section 12.2, and allantools' tests/nbs14: the 10-point NBS14 set as
# fractional frequency, and the 1000-point set from its Park-Miller generator.
NBS14_FREQ = [892.0, 809.0, 823.0, 798.0, 671.0, 644.0, 883.0, 903.0, 677.0]
NBS14_ADEV_1_2 = (91.22945, 115.8082)   # non-overlapping ADEV, tau = 1, 2
NBS14_OADEV_1_2 = (91.22945, 85.95287)  # overlapping ADEV, tau = 1, 2
NBS14_1000_OADEV = (2.922319e-01, 9.159953e-02, 3.241343e-02)  # tau = 1, 10, 100


def nbs14_1000() -> np.ndarray:
    values = [1234567890]
    for _ in range(999):
        values.append(16807 * values[-1] % 2147483647)
    assert values[1:4] == [395529916, 1209410747, 633705974]  # printed in the handbook
    return np.array(values) / 2147483647.0


def white_rate(n: int, fs_hz: float, arw_deg_rthr: float, rng) -> np.ndarray:
    """White rate noise of angle random walk N: per-sample sigma = N [deg/sqrt(s)] sqrt(fs)."""
    return rng.standard_normal(n) * arw_deg_rthr / 60.0 * math.sqrt(fs_hz)


def random_walk_rate(n: int, fs_hz: float, rrw_deg_hr_rthr: float, rng) -> np.ndarray:
    """Rate random walk K: steps of K [deg/s/sqrt(s)] sqrt(dt)."""
    return np.cumsum(rng.standard_normal(n)) * rrw_deg_hr_rthr / 216000.0 / math.sqrt(fs_hz)


def flicker_rate(n: int, fs_hz: float, bias_instability_deg_hr: float, rng) -> np.ndarray:
    """Flicker rate noise with IEEE 952's two-sided PSD B^2 / (2 pi f), i.e. one-sided B^2 / (pi f)."""
    spectrum = np.fft.rfft(rng.standard_normal(n))
    freq_hz = np.fft.rfftfreq(n, 1.0 / fs_hz)
    psd = np.zeros_like(freq_hz)
    psd[1:] = (bias_instability_deg_hr / 3600.0) ** 2 / (math.pi * freq_hz[1:])
    # unit white noise has the one-sided PSD 2 / fs
    return np.fft.irfft(spectrum * np.sqrt(psd * fs_hz / 2.0), n)


# --- the estimator ----------------------------------------------------------------------------

@pytest.mark.parametrize("fs_hz", [1.0, 7.3, 100.0, 400.0])
@pytest.mark.parametrize("n_axes", [0, 3])
def test_oadev_equals_allantools(fs_hz, n_axes):
    rng = np.random.default_rng(int(fs_hz * 10) + n_axes)
    n = 6001
    shape = (n,) if n_axes == 0 else (n, n_axes)
    # white plus a random walk plus a large offset, so the mean removal matters
    rate = 40.0 + rng.standard_normal(shape) + 0.02 * np.cumsum(rng.standard_normal(shape), axis=0)
    m, taus_s = log_taus(n, fs_hz)
    ours_taus, ours, n_terms = oadev(rate, fs_hz, taus_s)
    columns = rate.reshape(n, -1)
    assert ours.shape == ((len(m),) if n_axes == 0 else (len(m), n_axes))
    for axis in range(columns.shape[1]):
        taus, ref, _, ref_n = allantools.oadev(columns[:, axis], rate=fs_hz, data_type="freq", taus=taus_s)
        np.testing.assert_allclose(ours_taus, taus, rtol=1e-12)
        np.testing.assert_array_equal(n_terms, ref_n)
        np.testing.assert_allclose(ours.reshape(len(m), -1)[:, axis], ref, rtol=1e-9)


def test_oadev_arbitrary_taus_round_like_allantools():
    rng = np.random.default_rng(5)
    rate = rng.standard_normal(999)
    taus_s = [0.004, 0.011, 0.0149, 0.5, 2.0, 4.98, 7.0]  # 0.004 s and 7 s fit no tau at 100 Hz
    ours_taus, ours, _ = oadev(rate, 100.0, taus_s)
    taus, ref, _, _ = allantools.oadev(rate, rate=100.0, data_type="freq", taus=taus_s)
    np.testing.assert_allclose(ours_taus, taus)
    np.testing.assert_allclose(ours, ref, rtol=1e-9)
    assert ours_taus[0] == pytest.approx(0.01) and ours_taus[-1] == pytest.approx(4.98)


def test_chunking_does_not_change_the_result():
    rng = np.random.default_rng(6)
    rate = rng.standard_normal((3000, 2))
    m = np.array([1, 2, 3, 7, 40, 300, 1499])
    _, whole, _ = oadev(rate, 10.0, m=m)
    for chunk_size in (1, 7, 64, 2000):  # chunks shorter and longer than m: both code paths
        np.testing.assert_allclose(oadev(rate, 10.0, m=m, chunk_size=chunk_size)[1], whole, rtol=1e-12)


def test_nbs14_10_point():
    """91.22945 / 115.8082 are the non-overlapping ADEV; overlapping gives 85.95287 at tau = 2."""
    taus_s, dev, n_terms = oadev(NBS14_FREQ, 1.0, [1, 2])
    np.testing.assert_allclose(taus_s, [1.0, 2.0])
    np.testing.assert_allclose(dev, NBS14_OADEV_1_2, rtol=1e-4)
    np.testing.assert_array_equal(n_terms, [8, 6])
    # the non-overlapping statistic from its definition: averages over adjacent m-blocks
    freq = np.asarray(NBS14_FREQ)
    for m, expected in zip((1, 2), NBS14_ADEV_1_2):
        means = freq[:len(freq) // m * m].reshape(-1, m).mean(axis=1)
        assert math.sqrt(0.5 * np.mean(np.diff(means) ** 2)) == pytest.approx(expected, rel=1e-4)
    assert dev[1] != pytest.approx(NBS14_ADEV_1_2[1], rel=0.1)


def test_nbs14_1000_point():
    _, dev, _ = oadev(nbs14_1000(), 1.0, [1, 10, 100])
    np.testing.assert_allclose(dev, NBS14_1000_OADEV, rtol=1e-4)


def test_log_taus():
    m, taus_s = log_taus(100_000, 50.0, per_decade=10)
    assert m[0] == 1 and m[-1] == (100_000 - 1) // 2
    assert np.all(np.diff(m) > 0) and m.dtype.kind == "i"
    np.testing.assert_allclose(taus_s, m / 50.0)
    decades = math.log10(m[-1])
    assert 8 * decades < len(m) <= 10 * decades + 1  # duplicates at small m dropped
    assert log_taus(3, 1.0)[0].tolist() == [1]
    with pytest.raises(ValueError):
        log_taus(2, 1.0)


def test_oadev_rejects_bad_input():
    with pytest.raises(ValueError, match="NaN"):
        oadev(np.array([1.0, np.nan, 2.0, 3.0]), 1.0)
    with pytest.raises(ValueError, match="no tau"):
        oadev(np.ones(10), 1.0, [100.0])
    with pytest.raises(ValueError, match="shape"):
        oadev(np.ones((4, 2, 2)), 1.0)


# --- noise terms on simulated noise of known size ----------------------------------------------

def test_white_noise_falls_as_inverse_root_tau_and_gives_arw():
    fs_hz, arw = 100.0, 0.5
    rate = white_rate(400_000, fs_hz, arw, np.random.default_rng(10))
    taus_s, dev, _ = oadev(rate, fs_hz)
    fit = (taus_s >= 0.05) & (taus_s <= 40.0)
    slope = np.polyfit(np.log10(taus_s[fit]), np.log10(dev[fit]), 1)[0]
    assert slope == pytest.approx(-0.5, abs=0.02)
    np.testing.assert_allclose(dev[fit], arw / 60.0 / np.sqrt(taus_s[fit]), rtol=0.1)
    terms = noise_parameters(taus_s, dev, max_tau_s=len(rate) / fs_hz / 10)
    assert terms["arw_deg_rthr"] == pytest.approx(arw, rel=0.03)
    assert math.isnan(terms["rrw_deg_hr_rthr"])  # no +1/2 region: no number made up


def test_rate_random_walk_recovered():
    fs_hz, arw, rrw = 1.0, 0.5, 200.0
    rng = np.random.default_rng(11)
    n = 200_000
    rate = white_rate(n, fs_hz, arw, rng) + random_walk_rate(n, fs_hz, rrw, rng)
    taus_s, dev, _ = oadev(rate, fs_hz)
    terms = noise_parameters(taus_s, dev, max_tau_s=n / fs_hz / 10)
    assert terms["rrw_deg_hr_rthr"] == pytest.approx(rrw, rel=0.15)
    assert terms["rrw_slope"] == pytest.approx(0.5, abs=0.15)
    assert terms["arw_deg_rthr"] == pytest.approx(arw, rel=0.05)


def test_flicker_gives_bias_instability():
    """The flat level is 0.664 B; B from the minimum of a noisy flat curve reads low, never high."""
    fs_hz, bias = 1.0, 10.0
    rng = np.random.default_rng(12)
    n = 1 << 19
    rate = flicker_rate(n, fs_hz, bias, rng) + white_rate(n, fs_hz, 0.05, rng)
    taus_s, dev, _ = oadev(rate, fs_hz)
    flat = (taus_s >= 5.0) & (taus_s <= 5000.0)
    assert np.polyfit(np.log10(taus_s[flat]), np.log10(dev[flat]), 1)[0] == pytest.approx(0.0, abs=0.03)
    assert np.median(dev[flat]) / 0.664 * 3600.0 == pytest.approx(bias, rel=0.05)
    terms = noise_parameters(taus_s, dev, max_tau_s=n / fs_hz / 10)
    assert 0.6 * bias < terms["bias_instability_deg_hr"] < 1.05 * bias


def test_noise_parameters_on_ideal_lines():
    """Exact IEEE 952 lines: N = 0.3 deg/rt-h, B = 5 deg/h, K = 40 deg/h/rt-h come back exactly."""
    taus_s = np.logspace(-2, 5, 141)
    white = 0.3 / 60.0 / np.sqrt(taus_s)
    walk = 40.0 / 216000.0 * np.sqrt(taus_s / 3.0)
    flat = 0.664 * 5.0 / 3600.0
    dev = np.maximum(np.maximum(white, walk), flat)
    terms = noise_parameters(taus_s, dev)
    assert terms["arw_deg_rthr"] == pytest.approx(0.3, rel=1e-9)
    assert terms["bias_instability_deg_hr"] == pytest.approx(5.0, rel=1e-9)
    assert terms["rrw_deg_hr_rthr"] == pytest.approx(40.0, rel=1e-9)
    assert terms["arw_tau_s"] < terms["bias_instability_tau_s"] < terms["rrw_tau_s"]
    only_white = noise_parameters(taus_s, white)
    assert math.isnan(only_white["rrw_deg_hr_rthr"])
    assert only_white["bias_instability_tau_s"] == pytest.approx(taus_s[-1])
    # read where the curve still falls, B is an upper bound, and says so in the JSON and the log's table
    assert only_white["bias_instability_upper_bound"] and not terms["bias_instability_upper_bound"]
    table = format_table({"x": {**only_white, "taus_s": taus_s}, "y": {**terms, "taus_s": taus_s}})
    assert table.splitlines()[1].split()[2].startswith("<=") and not table.splitlines()[2].split()[2].startswith("<=")
    assert math.isnan(noise_parameters(taus_s, walk)["arw_deg_rthr"])


def test_arw_is_read_in_the_broad_white_region_not_a_chance_window_at_long_tau():
    """A filtered output: the -1/2 region bent a little (slope -0.48) over two decades, then a hump, then
    0.7 decade at exactly -1/2 five times higher (a drift residual). N is the white region's."""
    log_tau = np.linspace(-1.0, 4.0, 201)
    slopes = np.select([log_tau < 0, log_tau < 2, log_tau < 2.5, log_tau < 3.2], [0.3, -0.48, 0.8, -0.5], -0.1)
    log_dev = np.concatenate([[0.0], np.cumsum(slopes[1:] * np.diff(log_tau))])
    log_dev += math.log10(0.3 / 60.0) - np.interp(0.0, log_tau, log_dev)  # the white line: N = 0.3 at 1 s
    terms = noise_parameters(10.0 ** log_tau, 10.0 ** log_dev)
    assert terms["arw_deg_rthr"] == pytest.approx(0.3, rel=0.1)
    assert terms["arw_slope"] == pytest.approx(-0.48, abs=0.01)
    assert 1.0 < terms["arw_tau_s"] < 100.0  # read in the white region, and says where


# --- the report, gaps, JSON and the plot -------------------------------------------------------

def _three_axis_record(n=20_000, fs_hz=50.0, seed=20):
    rng = np.random.default_rng(seed)
    time_s = np.arange(n) / fs_hz
    rate = np.column_stack([white_rate(n, fs_hz, arw, rng) for arw in (0.2, 0.4, 0.8)])
    return time_s, rate


def test_allan_report_keys_and_values():
    time_s, rate = _three_axis_record()
    report = allan_report(time_s, rate)
    assert report["fs_hz"] == 50.0 and report["segments"]["count"] == 1
    for axis, arw in zip("xyz", (0.2, 0.4, 0.8)):
        row = report[axis]
        for key in ("taus_s", "adev_dps", "arw_deg_rthr", "bias_instability_deg_hr", "rrw_deg_hr_rthr"):
            assert key in row
        assert len(row["taus_s"]) == len(row["adev_dps"]) > 20
        assert row["arw_deg_rthr"] == pytest.approx(arw, rel=0.1)


def test_gaps_are_not_glued():
    time_s, rate = _three_axis_record(n=30_000)
    time_s = time_s.copy()
    time_s[10_000:] += 500.0  # a 500 s break after 10 000 samples
    time_s[25_000:] += 3.0    # and a short one
    assert continuous_segments(time_s, 50.0) == [(0, 10_000), (10_000, 25_000), (25_000, 30_000)]
    report = allan_report(time_s, rate)
    segments = report["segments"]
    assert segments["count"] == 3 and segments["n_samples_used"] == 15_000
    assert segments["used_time_s"] == [pytest.approx(time_s[10_000]), pytest.approx(time_s[24_999])]
    assert segments["largest_gap_s"] == pytest.approx(500.02)
    assert max(report["x"]["taus_s"]) <= 15_000 / 50.0 / 2
    expected = oadev(rate[10_000:25_000], 50.0, m=log_taus(15_000, 50.0)[0])[1]
    np.testing.assert_allclose(report["y"]["adev_dps"], expected[:, 1])


def test_allan_report_too_short():
    with pytest.raises(GyronetError):
        allan_report(np.arange(2.0), np.zeros((2, 3)))


def test_report_to_json_writes_nan_as_null():
    time_s, rate = _three_axis_record(n=3_000)
    text = report_to_json(allan_report(time_s, rate))
    loaded = json.loads(text)  # strict JSON: no NaN tokens
    assert "NaN" not in text and loaded["x"]["rrw_deg_hr_rthr"] is None


def test_plot_allan_single_and_labelled(tmp_path):
    from matplotlib.figure import Figure

    time_s, rate = _three_axis_record(n=5_000)
    raw = allan_report(time_s, rate)
    compensated = allan_report(time_s, rate * 0.5)
    fig = plot_allan(raw, path=tmp_path / "a.png", title="one")
    assert isinstance(fig, Figure) and len(fig.axes) == 3
    assert (tmp_path / "a.png").stat().st_size > 10_000
    both = plot_allan({"raw": raw, "compensated": compensated})
    legend = [t.get_text() for t in both.axes[0].get_legend().get_texts()]
    assert legend[0].startswith("raw: N=") and legend[1].startswith("compensated: N=")


def test_plot_marks_where_n_and_k_were_read():
    """A square on the -1/2 line at ``arw_tau_s``, a triangle on the +1/2 line at ``rrw_tau_s``."""
    taus_s = np.logspace(-2, 5, 141)
    white, walk = 0.3 / 60.0 / np.sqrt(taus_s), 40.0 / 216000.0 * np.sqrt(taus_s / 3.0)
    dev = np.maximum(np.maximum(white, walk), 0.664 * 5.0 / 3600.0)
    terms = noise_parameters(taus_s, dev)
    fig = plot_allan({"x": {"taus_s": taus_s.tolist(), "adev_dps": dev.tolist(), **terms}})
    marks = {line.get_marker(): (line.get_xdata()[0], line.get_ydata()[0]) for line in fig.axes[0].get_lines()
             if line.get_marker() in ("s", "^")}
    assert marks["s"] == pytest.approx((terms["arw_tau_s"], np.interp(terms["arw_tau_s"], taus_s, dev)), rel=1e-6)
    assert marks["^"] == pytest.approx((terms["rrw_tau_s"], np.interp(terms["rrw_tau_s"], taus_s, dev)), rel=1e-6)


# --- real data -------------------------------------------------------------------------------

@pytest.mark.skipif(not ADIS_DIR.is_dir(), reason="shared ADIS16405 data not present")
@pytest.mark.parametrize("run", [1, pytest.param(2, marks=pytest.mark.slow)])
def test_real_adis16405(run):
    """PROVENANCE.md: ARW about 2.3-2.6 deg/rt-h, B about 26-50 deg/h (datasheet 2.0 and 25).

    About 2 s per run, so run 1 is in the quick suite and run 2 only with ``-m slow``.
    """
    import pandas as pd

    frame = pd.read_csv(ADIS_DIR / f"adis16405_run{run}_100Hz.csv.gz")
    report = allan_report(frame["t_s"].to_numpy(), frame[["gyro_x_dps", "gyro_y_dps", "gyro_z_dps"]].to_numpy())
    assert report["fs_hz"] == pytest.approx(100.0)
    for axis in "xyz":
        assert 2.1 < report[axis]["arw_deg_rthr"] < 2.8
        assert 20.0 < report[axis]["bias_instability_deg_hr"] < 60.0


# --- scripts/allan.py ------------------------------------------------------------------------

def _run_script(*overrides: str, cwd: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    return subprocess.run([sys.executable, str(ROOT / "scripts" / "allan.py"), *overrides,
                           f"hydra.run.dir={cwd / 'hydra'}"], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=300)


def test_script_end_to_end(tmp_path):
    time_s, rate = _three_axis_record(n=6_000)
    write_recording(tmp_path / "rec.csv", {"time_s": time_s, **{f"gyro_{a}_dps": rate[:, i]
                                                                for i, a in enumerate("xyz")}}, {"fs_hz": 50})
    proc = _run_script("input=rec.csv", "output=out/allan.json", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    report = json.loads((tmp_path / "out" / "allan.json").read_text())
    for axis in "xyz":
        assert {"taus_s", "adev_dps", "arw_deg_rthr", "bias_instability_deg_hr",
                "rrw_deg_hr_rthr"} <= set(report[axis])
    assert report["x"]["arw_deg_rthr"] == pytest.approx(0.2, rel=0.15)
    assert (tmp_path / "out" / "allan.png").read_bytes()[:4] == b"\x89PNG"
    assert "Traceback" not in proc.stderr


@pytest.mark.parametrize("content", ["time_s,gyro_x_dps,gyro_y_dps,gyro_z_dps\n0,1,2,3\n0.1,oops,2,3\n",
                                     "time_s,gyro_x_dps,gyro_y_dps\n0,1,2\n0.1,1,2\n",
                                     "\x00\x01binary"])
def test_script_bad_input_one_line(tmp_path, content):
    (tmp_path / "bad.csv").write_text(content)
    proc = _run_script("input=bad.csv", "output=a.json", cwd=tmp_path)
    assert proc.returncode != 0
    assert "Traceback" not in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1 and "bad.csv" in proc.stderr
    assert not (tmp_path / "a.json").exists()


def test_script_refuses_an_output_named_as_its_plot(tmp_path):
    """output=a.png wrote the JSON there and replaced it with the plot: "wrote a.png and a.png"."""
    time_s, rate = _three_axis_record(n=600)
    write_recording(tmp_path / "rec.csv", {"time_s": time_s, **{f"gyro_{a}_dps": rate[:, i]
                                                                for i, a in enumerate("xyz")}})
    proc = _run_script("input=rec.csv", "output=a.png", cwd=tmp_path)
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert proc.stderr.strip().splitlines() == ["error: output=a.png: output names the JSON report, and its plot goes "
                                                "beside it with the suffix .png, which would replace it: name the "
                                                "report A.json (the plot is then A.png)"]
    assert not (tmp_path / "a.png").exists()


def test_script_refuses_a_record_whose_rate_changes(tmp_path):
    """1 h at 100 Hz then 2 h at 50 Hz read N 22 % high with no word (a review): an Allan curve needs one rate."""
    time_s = np.concatenate([np.arange(6000) / 100.0, 60.0 + np.arange(1, 3000) / 50.0])
    rate = np.random.default_rng(0).normal(0.0, 0.3, (len(time_s), 3))
    write_recording(tmp_path / "rec.csv", {"time_s": time_s, **{f"gyro_{a}_dps": rate[:, i]
                                                                for i, a in enumerate("xyz")}})
    proc = _run_script("input=rec.csv", "output=a.json", cwd=tmp_path)
    assert proc.returncode != 0 and "Traceback" not in proc.stderr
    assert "the sampling rate changes from 100 Hz to 50 Hz; an Allan curve needs one rate" in proc.stderr


def test_a_record_too_short_for_any_term_says_so(caplog):
    with caplog.at_level("WARNING", logger="gyronet.allan"):
        report = allan_report(np.arange(5) / 10.0, np.random.default_rng(0).normal(size=(5, 3)))
    assert "5 samples (0.5 s) are too few to read N, B or K" in caplog.text
    assert report["x"]["bias_instability_upper_bound"] is False  # every key there, n/a or not
