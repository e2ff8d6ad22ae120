"""Kalman stage: identification against known AR(1) parameters, the filter's covariance, its
estimates against their predicted sigma, the measured step response, causal equality of batch and
per-sample runs, persistence and bad input."""
import json
import math

import numpy as np
import pytest
from scipy import signal
from scipy.linalg import solve_discrete_are

from gyronet.errors import GyronetError
from gyronet.model.kalman import (AxisModel, KalmanInputError, KalmanModel, KalmanStage, allan_cost, identify,
                            q_rate_for_time_constant, step_response)

FS_HZ = 10.0


def _ar1(n, phi, sigma_dps, rng):
    """Stationary AR(1) with per-sample coefficient phi and standard deviation sigma."""
    w = rng.standard_normal(n) * sigma_dps * math.sqrt(1.0 - phi ** 2)
    return signal.lfilter([1.0], [1.0, -phi], w, zi=[phi * sigma_dps * rng.standard_normal()])[0]


def _model(phi=0.995, q_drift=2.5e-5, r=0.01, n_axes=3):
    axis = AxisModel((phi,), (0.0,), q_drift, r)
    return KalmanModel(FS_HZ, (axis,) * n_axes)


@pytest.fixture(scope="module")
def noisy_ar1():
    """Three axes: AR(1) drift (phi 0.95 / 0.99 / 0.998) + white noise, and the true values."""
    rng = np.random.default_rng(7)
    phis, sigmas, r = (0.95, 0.99, 0.998), (0.05, 0.03, 0.02), 0.1 ** 2
    n = 40_000
    data = np.column_stack([_ar1(n, p, s, rng) + math.sqrt(r) * rng.standard_normal(n)
                            for p, s in zip(phis, sigmas)])
    return data, phis, sigmas, r


def test_ar1_is_identified_within_its_standard_error(noisy_ar1):
    data, phis, sigmas, r = noisy_ar1
    model = identify(data + 0.3, FS_HZ)  # a constant offset is rate, not drift
    for axis, phi, sigma in zip(model.axes, phis, sigmas):
        assert axis.order == 1
        assert 0 < axis.ar_se[0] < 0.02
        assert abs(axis.ar[0] - phi) < 3 * axis.ar_se[0]
        assert abs(axis.r_dps2 - r) < 3 * axis.r_se_dps2
        q = sigma ** 2 * (1 - phi ** 2)
        assert abs(axis.q_drift_dps2 - q) < 3 * axis.q_drift_se_dps2
        assert axis.mean_dps == pytest.approx(0.3, abs=0.05)


def test_plain_least_squares_would_be_biased_by_the_white_noise(noisy_ar1):
    """Why identify() does not regress d_k on d_{k-1}: the noise pulls phi towards 0."""
    data, phis, _, _ = noisy_ar1
    model = identify(data, FS_HZ)
    x = data[:, 1] - data[:, 1].mean()
    phi_ls = float(x[1:] @ x[:-1] / (x[:-1] @ x[:-1]))
    assert abs(phi_ls - phis[1]) > 20 * model.axes[1].ar_se[0]


def test_bic_picks_the_order_of_an_ar2():
    rng = np.random.default_rng(3)
    ar = [1.5, -0.6]  # complex poles of modulus sqrt(0.6) = 0.77: stationary
    d = signal.lfilter([1.0], [1.0, -ar[0], -ar[1]], 0.01 * rng.standard_normal(60_000))
    model = identify((d + 0.05 * rng.standard_normal(len(d)))[:, None], FS_HZ, max_order=3)
    axis = model.axes[0]
    assert axis.order == 2
    assert np.all(np.abs(np.subtract(axis.ar, ar)) < 3 * np.asarray(axis.ar_se))


def test_identify_refuses_bad_input():
    with pytest.raises(ValueError, match="sample 5, axis 1"):
        bad = np.zeros((100, 3))
        bad[5, 1] = np.nan
        identify(bad, FS_HZ)
    with pytest.raises(ValueError, match="shape"):
        identify(np.zeros(100), FS_HZ)


def test_covariance_stays_symmetric_and_settles_to_the_riccati_solution():
    stage = KalmanStage(_model(), q_rate_dps2_per_s=1e-3, gain_tol=0.0)  # never switch: watch P
    kf, previous, changes = stage.kf, None, []
    for _ in range(3000):
        kf.predict()
        kf.update(np.zeros((3, 1)))
        P = kf.P
        assert np.max(np.abs(P - P.T)) <= 1e-12 * np.max(np.abs(P))
        assert np.all(np.linalg.eigvalsh(0.5 * (P + P.T)) > 0)
        if previous is not None:
            changes.append(np.max(np.abs(P - previous)))
        previous = P.copy()
    assert changes[-1] < 1e-12 * np.max(np.abs(P)) < changes[10]
    # the steady posterior: P = P- - P- H^T (H P- H^T + R)^-1 H P-, P- from the DARE
    prior = solve_discrete_are(kf.F.T, kf.H.T, kf.Q, kf.R)
    gain = prior @ kf.H.T @ np.linalg.inv(kf.H @ prior @ kf.H.T + kf.R)
    np.testing.assert_allclose(P, prior - gain @ kf.H @ prior, rtol=1e-6, atol=1e-14)


def test_constant_rate_is_recovered_within_its_predicted_sigma():
    rng = np.random.default_rng(11)
    model = _model(phi=0.99, q_drift=4e-5, r=0.04)
    n, rate_dps = 20_000, np.array([0.7, -0.2, 0.0])
    drift = np.column_stack([_ar1(n, 0.99, math.sqrt(4e-5 / (1 - 0.99 ** 2)), rng) for _ in range(3)])
    measured = rate_dps + drift + 0.2 * rng.standard_normal((n, 3))
    stage = KalmanStage(model, mode="rate", q_rate_dps2_per_s=1e-6)
    error = stage.process(measured)[n // 2:] - rate_dps
    sigma = stage.rate_sigma_dps()
    assert np.all(np.abs(error[-1]) < 3 * sigma)
    assert np.all(np.mean(np.abs(error) < 2 * sigma, axis=0) > 0.9)
    assert np.all(np.std(error, axis=0) < 1.1 * sigma)
    # and the filter did something: the raw measurement is far noisier than its estimate
    assert np.all(np.std(measured[n // 2:] - rate_dps, axis=0) > 3 * np.std(error, axis=0))


def test_step_response_is_measured_and_bandwidth_follows_q_rate():
    model = _model()
    slow = step_response(KalmanStage(model, q_rate_dps2_per_s=1e-3), FS_HZ, 2.0, 120.0)
    fast = step_response(KalmanStage(model, q_rate_dps2_per_s=1e-2), FS_HZ, 2.0, 120.0)
    for result in (slow, fast):
        for axis in "xyz":
            figures = result[axis]
            assert 0 < figures["delay_s"] < 60
            assert figures["delay_s"] < figures["settling_5pct_s"] <= figures["settling_2pct_s"] < 120
            assert figures["final_ratio"] == pytest.approx(1.0, abs=0.02)
    assert fast["x"]["delay_s"] < slow["x"]["delay_s"]
    assert fast["x"]["settling_2pct_s"] < slow["x"]["settling_2pct_s"]


def test_time_constant_helper_matches_the_measured_step():
    model = _model(q_drift=1e-9)  # a drift far too small to matter: the rate alone
    for tau_s in (0.5, 3.0):
        q = q_rate_for_time_constant(model.axes[0].r_dps2, FS_HZ, tau_s)
        measured = step_response(KalmanStage(model, q_rate_dps2_per_s=q), FS_HZ, 1.0, 10 * tau_s)
        assert measured["x"]["time_constant_s"] == pytest.approx(tau_s, abs=1.5 / FS_HZ)


def test_bias_mode_passes_a_step_at_once_and_rate_mode_takes_it_for_drift_with_a_tiny_q():
    model = _model()
    bias = step_response(KalmanStage(model, mode="bias", q_rate_dps2_per_s=1e-2), FS_HZ, 1.0, 60.0)
    assert bias["x"]["first_sample_ratio"] > 0.99
    model = _model(phi=0.98, q_drift=1e-4)  # a drift correlation time of 5 s: a short pre-roll
    rate = step_response(KalmanStage(model, mode="rate", q_rate_dps2_per_s=1e-6), FS_HZ, 1.0, 60.0)
    smooth = step_response(KalmanStage(model, mode="smooth", q_rate_dps2_per_s=1e-6), FS_HZ, 1.0, 60.0)
    assert math.isnan(rate["x"]["delay_s"]) and rate["x"]["final_ratio"] < 0.5
    assert smooth["x"]["delay_s"] < 5.0


def _chunks(data, sizes):
    start = 0
    for size in sizes:
        yield data[start:start + size]
        start += size
    if start < len(data):
        yield data[start:]


def test_batch_and_per_sample_give_the_same_numbers():
    rng = np.random.default_rng(5)
    data = 0.1 * rng.standard_normal((3000, 3)) + np.linspace(0, 1, 3000)[:, None]
    stage = KalmanStage(_model(), q_rate_dps2_per_s=1e-2)
    batch = stage.process(data)
    assert stage.steady_since is not None and 1 < stage.steady_since < 2000
    for sizes in ([1] * 3000, [7, 1, 300, 1, 1, 20, 2], [stage.steady_since, 1, 1, 15, 16]):
        stage.reset()
        pieces = np.vstack([stage.process(chunk) for chunk in _chunks(data, sizes)])
        np.testing.assert_allclose(pieces, batch, rtol=0, atol=1e-12)


def test_steady_state_switch_stays_close_to_the_time_varying_filter():
    rng = np.random.default_rng(9)
    data = 0.1 * rng.standard_normal((6000, 3))
    for mode in ("rate", "smooth", "bias"):
        switched = KalmanStage(_model(phi=0.999, q_drift=1e-6), mode=mode, q_rate_dps2_per_s=1e-4)
        exact = KalmanStage(_model(phi=0.999, q_drift=1e-6), mode=mode, q_rate_dps2_per_s=1e-4, gain_tol=0.0)
        out = switched.process(data)
        assert switched.steady and not exact.steady
        np.testing.assert_allclose(out, exact.process(data), rtol=0, atol=1e-6)


def test_to_dict_from_dict_round_trip_gives_identical_outputs(tmp_path, noisy_ar1):
    stage = KalmanStage(identify(noisy_ar1[0][:5000], FS_HZ), mode="rate", q_rate_dps2_per_s=[1e-2, 2e-2, 3e-2])
    text = json.dumps(stage.to_dict(), allow_nan=False)  # strict JSON
    copy = KalmanStage.from_dict(json.loads(text))
    loaded = KalmanStage.load(stage.save(tmp_path / "kalman.json"))
    data = noisy_ar1[0][5000:8000]
    expected = stage.process(data)
    np.testing.assert_array_equal(copy.process(data), expected)
    np.testing.assert_array_equal(loaded.process(data), expected)
    assert copy.to_dict() == stage.to_dict()


def test_nan_is_refused_with_the_sample_named_and_the_state_kept():
    rng = np.random.default_rng(1)
    data = 0.1 * rng.standard_normal((50, 3))
    stage, clean = KalmanStage(_model()), KalmanStage(_model())
    stage.process(data[:20])
    bad = data[20:].copy()
    bad[4, 2] = np.nan
    with pytest.raises(ValueError, match=r"sample 24 \(axis z\)"):
        stage.process(bad)
    with pytest.raises(KalmanInputError, match="shape"):
        stage.process(data[0])
    clean.process(data[:20])
    np.testing.assert_array_equal(stage.process(data[20:]), clean.process(data[20:]))


def test_bad_options_are_refused():
    with pytest.raises(GyronetError, match="mode"):
        KalmanStage(_model(), mode="lowpass")
    with pytest.raises(GyronetError, match="q_rate"):
        KalmanStage(_model(), q_rate_dps2_per_s=0.0)
    with pytest.raises(ValueError, match="Hz"):
        step_response(KalmanStage(_model()), 100.0, 1.0, 1.0)


def test_allan_cost_reports_both_sides_and_the_low_pass_lowers_the_sample_noise():
    rng = np.random.default_rng(2)
    white = 0.1 * rng.standard_normal((20_000, 3))
    cost = allan_cost(KalmanStage(_model(q_drift=1e-9)), white, FS_HZ, skip_s=10.0)
    for axis in "xyz":
        without, with_filter = cost[axis]["without"], cost[axis]["with"]
        # white rate noise: N = sigma / sqrt(fs) in deg/sqrt(s), * 60 for deg/sqrt(h)
        assert without["arw_deg_rthr"] == pytest.approx(0.1 / math.sqrt(FS_HZ) * 60, rel=0.15)
        assert with_filter["std_dps"] < 0.6 * without["std_dps"]
        # a unit-DC-gain low-pass leaves the long taus, where B is read here, as they were
        assert with_filter["bias_instability_deg_hr"] == pytest.approx(without["bias_instability_deg_hr"], rel=0.02)
    assert cost["n_samples"] == 20_000 - 100


def test_white_noise_gets_no_drift_state_and_the_modes_reduce_accordingly():
    rng = np.random.default_rng(4)
    white = 0.2 * rng.standard_normal((30_000, 3))
    model = identify(white, FS_HZ, max_order=2)
    for axis in model.axes:
        assert axis.order == 0 and axis.q_drift_dps2 == 0.0
        assert min(axis.bic, key=axis.bic.get) == "0"
        assert abs(axis.r_dps2 - 0.04) < 3 * axis.r_se_dps2
    outputs = {mode: KalmanStage(model, mode=mode).process(white) for mode in ("rate", "smooth", "bias")}
    np.testing.assert_array_equal(outputs["rate"], outputs["smooth"])
    np.testing.assert_allclose(outputs["bias"], white, rtol=0, atol=1e-12)
