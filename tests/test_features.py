"""Causal features: dT/dt on a quantised ramp, batch equals live, gaps restart the filters."""
import numpy as np
import pytest

from gyronet.model.features import PAPER_FEATURES, FeatureExtractor, feature_name

FS_HZ = 10.0


def _ramp(rate_c_per_s=1 / 60, lsb_c=0.0625, noise_c=0.02, duration_s=3000.0, start_s=500.0, seed=0):
    time_s = np.arange(0, duration_s, 1 / FS_HZ)
    true_c = 20 + rate_c_per_s * np.clip(time_s - start_s, 0, None)
    noisy = true_c + noise_c * np.random.default_rng(seed).standard_normal(len(time_s))
    return time_s, np.round(noisy / lsb_c) * lsb_c, true_c


@pytest.mark.parametrize("tau_s, max_std_c_per_s", [(5.0, 6e-4), (30.0, 6e-5)])
@pytest.mark.parametrize("rate_c_per_min", [-1.0, 0.25, 2.0])
def test_rate_on_a_quantised_ramp_is_unbiased_and_quiet(rate_c_per_min, tau_s, max_std_c_per_s):
    time_s, temp_c, _ = _ramp(rate_c_per_min / 60)
    specs = [{"kind": "temp"}, {"kind": "rate", "tau_s": tau_s}]
    rate = FeatureExtractor(specs, FS_HZ).process({"time_s": time_s, "temp_c": temp_c})[:, 1]
    settled = time_s > 1500  # 1000 s after the ramp starts
    true_rate = rate_c_per_min / 60
    # no lag on a ramp: a type-2 tracker, not a differentiated low-pass
    assert abs(rate[settled].mean() - true_rate) < 0.002 * abs(true_rate) + 2e-6
    # the reading steps by 1/16 degC every few seconds; the estimate must not
    assert rate[settled].std() < max_std_c_per_s


@pytest.mark.parametrize("tau_s", [2.5, 5.0])
def test_rate_is_twice_its_time_constant_late_where_the_ramp_curves(tau_s):
    """Why data.rate_tau_s is short: under a constant d2T/dt2 the type-2 tracker's dT/dt lags by 2 tau."""
    time_s = np.arange(0, 3000, 1 / FS_HZ)
    accel_c_per_s2 = 1e-5
    temp_c = 20 + 0.5 * accel_c_per_s2 * time_s ** 2
    rate = FeatureExtractor([{"kind": "temp"}, {"kind": "rate", "tau_s": tau_s}], FS_HZ).process(
        {"time_s": time_s, "temp_c": temp_c})[:, 1]
    settled = time_s > 20 * tau_s
    delay_s = (accel_c_per_s2 * time_s[settled] - rate[settled]) / accel_c_per_s2
    np.testing.assert_allclose(delay_s, 2 * tau_s, rtol=0.01)


def test_rate_is_zero_on_a_dwell_and_product_is_t_times_rate():
    time_s, temp_c, _ = _ramp(0.0)
    features = FeatureExtractor(PAPER_FEATURES, FS_HZ).process({"time_s": time_s, "temp_c": temp_c})
    assert abs(features[time_s > 100, 1].mean()) < 1e-5
    assert np.abs(features[:, 1]).max() < 2e-3
    np.testing.assert_allclose(features[:, 2], features[:, 0] * features[:, 1])


def test_product_multiplies_t_by_its_own_rate_whatever_rate_comes_first():
    """A supply voltage's rate listed first gave T * dVdd/dt under the name temp_x_rate_c2_per_s."""
    time_s, temp_c, _ = _ramp(duration_s=400.0, start_s=100.0)
    columns = {"time_s": time_s, "temp_c": temp_c, "vdd_v": 3.3 + 0.01 * np.sin(time_s / 50)}
    specs = [{"kind": "temp"}, {"kind": "rate", "source": "vdd_v"}, {"kind": "rate", "tau_s": 5.0, "lag_s": 30.0},
             {"kind": "rate", "tau_s": 5.0}, {"kind": "product"}]
    batch = FeatureExtractor(specs, FS_HZ).process(columns)
    np.testing.assert_allclose(batch[:, 4], batch[:, 0] * batch[:, 3])
    live = FeatureExtractor(specs, FS_HZ)
    rows = [live.process({k: v[i:i + 1] for k, v in columns.items()}) for i in range(len(time_s))]
    np.testing.assert_allclose(np.vstack(rows), batch, rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match="the temperature's 'rate' feature"):
        FeatureExtractor(specs[:3] + specs[4:], FS_HZ).process(columns)


def test_live_one_sample_at_a_time_equals_batch():
    time_s, temp_c, _ = _ramp(duration_s=400.0, start_s=100.0)
    vdd = 3.3 + 0.01 * np.sin(time_s / 50)
    specs = [*PAPER_FEATURES, {"kind": "lag", "tau_s": 600.0}, {"kind": "column", "source": "vdd_v", "tau_s": 20.0},
             {"kind": "hysteresis", "width": 0.5}, {"kind": "time", "tau_s": 900.0}, {"kind": "power", "exponent": 2}]
    columns = {"time_s": time_s, "temp_c": temp_c, "vdd_v": vdd}
    batch = FeatureExtractor(specs, FS_HZ).process(columns)
    live = FeatureExtractor(specs, FS_HZ)
    rows = [live.process({k: v[i:i + 1] for k, v in columns.items()}) for i in range(len(time_s))]
    np.testing.assert_allclose(np.vstack(rows), batch, rtol=0, atol=1e-12)


def test_a_gap_restarts_the_rate_from_the_mean_slope_over_the_gap():
    time_s, temp_c, true_c = _ramp(1 / 60, lsb_c=1e-6, noise_c=0.0, start_s=0.0)
    keep = (time_s < 1000) | (time_s > 1600)  # a 10-minute break in the record
    rate = FeatureExtractor(PAPER_FEATURES, FS_HZ).process({"time_s": time_s[keep], "temp_c": temp_c[keep]})[:, 1]
    after_gap = np.flatnonzero(time_s[keep] > 1600)[:5]
    np.testing.assert_allclose(rate[after_gap], 1 / 60, rtol=1e-3)


def test_lag_follows_a_first_order_response():
    time_s = np.arange(0, 2000, 0.1)
    step = np.where(time_s >= 100, 1.0, 0.0)
    out = FeatureExtractor([{"kind": "temp"}, {"kind": "lag", "tau_s": 300.0}], FS_HZ).process(
        {"time_s": time_s, "temp_c": step})[:, 1]
    at = np.searchsorted(time_s, 400.0)  # one time constant after the step
    assert out[at] == pytest.approx(1 - np.exp(-1), abs=2e-3)


def test_hysteresis_separates_heating_from_cooling():
    time_s = np.arange(0, 400, 0.1)
    temp = 10 * np.sin(2 * np.pi * time_s / 200)
    out = FeatureExtractor([{"kind": "temp"}, {"kind": "hysteresis", "width": 1.0}], FS_HZ).process(
        {"time_s": time_s, "temp_c": temp})[:, 1]
    heating = np.gradient(temp) > 0
    at_zero = np.abs(temp) < 0.2
    assert np.all(out[at_zero & heating & (time_s > 50)] > 0.9)
    assert np.all(out[at_zero & ~heating & (time_s > 50)] < -0.9)


def test_names_are_unique_and_descriptive():
    names = [feature_name(s) for s in PAPER_FEATURES]
    assert names == ["temp_c", "temp_rate_c_per_s", "temp_x_rate_c2_per_s"]
    with pytest.raises(ValueError, match="duplicate"):
        FeatureExtractor([{"kind": "temp"}, {"kind": "temp"}], FS_HZ)
