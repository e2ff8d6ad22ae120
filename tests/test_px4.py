"""PX4's thermal calibrations (gyronet/model/px4.py): each rule on data whose answer is worked out here,
and the offline fit against PX4's own script's output on the same ULog (tests/data/px4_reference.json)."""
import importlib.util
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from gyronet.model.baselines import TempPolynomial
from gyronet.errors import GyronetError
from gyronet.model.px4 import Px4Cubic, Px4Onboard, median_filter, temperature_bins

DATA = Path(__file__).resolve().parent / "data"
REFERENCE = json.loads((DATA / "px4_reference.json").read_text())


def _tensor(values) -> torch.Tensor:
    return torch.as_tensor(np.asarray(values, dtype=np.float64))


def test_median_filter_is_a_31_sample_running_median_with_zero_padded_ends():
    rng = np.random.default_rng(0)
    values = rng.normal(1.0, 1.0, (120, 2))
    padded = np.vstack([np.zeros((15, 2)), values, np.zeros((15, 2))])
    expected = np.array([[sorted(padded[i:i + 31, j])[15] for j in range(2)] for i in range(120)])
    assert np.array_equal(median_filter(values), expected)


def test_bins_average_each_equal_temperature_interval_and_drop_empty_ones():
    # 0 .. 20 degC in 4 bins of 5 degC: [0, 5), [5, 10), [10, 15), [15, 20]; the top sample goes to the last
    temp = np.array([0.0, 1.0, 6.0, 7.0, 8.0, 19.0, 20.0], dtype=np.float32)
    values = np.array([[1.0], [3.0], [2.0], [4.0], [9.0], [5.0], [7.0]])
    temp_means, value_means = temperature_bins(temp, values, n_bins=4)
    assert np.allclose(temp_means, [0.5, 7.0, 19.5])
    assert np.allclose(value_means[:, 0], [2.0, 5.0, 6.0])


def _chamber(n_dwell: int = 400, quantum_c: float = 0.0625):
    """A ramp 0 -> 30 degC with a long dwell at 10 degC, the temperature quantised as drivers report it."""
    ramp = np.linspace(0.0, 30.0, 1201)
    temp = np.concatenate([ramp[:401], np.full(n_dwell, 10.0), ramp[401:]])
    return np.round(temp / quantum_c) * quantum_c


def test_px4_fit_weighs_each_temperature_bin_once_and_poly3_each_sample():
    temp = _chamber()
    drift = 0.01 + 0.002 * (temp - 15) - 1e-5 * (temp - 15) ** 3
    drift = np.where(temp == 10.0, drift + 0.02, drift)  # the dwell sits off the curve
    y = np.column_stack([drift, -drift, 2 * drift])
    px4, poly3 = Px4Cubic(1), TempPolynomial(1)
    px4.fit_closed_form(_tensor(temp[:, None]), _tensor(y))
    poly3.fit_closed_form(_tensor(temp[:, None]), _tensor(y))
    # expected, worked out independently: the quantum (1/16 degC) is wider than a bin (30/2000 degC), so
    # every bin holds one reported temperature; PX4 fits a cubic to the mean (of the median-filtered
    # samples) at each one, once each
    levels, filtered = np.unique(temp), median_filter(y)
    means = np.array([filtered[temp == level].mean(0) for level in levels])
    expected = np.polynomial.polynomial.polyfit(levels - 15.0, means, 3)
    assert float(px4.temp_ref_c) == 15.0 and float(px4.temp_min_c) == 0.0 and float(px4.temp_max_c) == 30.0
    np.testing.assert_allclose(px4.coef.numpy(), expected, rtol=1e-9, atol=1e-12)
    # poly3 counts the 400 dwell samples 400 times: pulled towards the dwell's offset at 10 degC
    at_dwell = _tensor([[10.0]])
    assert float(poly3(at_dwell)[0, 0] - px4(at_dwell)[0, 0]) > 0.005


def test_px4_no_resample_fits_the_median_filtered_samples():
    temp = _chamber(n_dwell=40)
    y = np.column_stack([0.001 * temp, np.zeros_like(temp), np.ones_like(temp)])
    y[700, 0] += 5.0  # one spike: the median filter removes it, poly3 does not
    model = Px4Cubic(1, resample=False)
    model.fit_closed_form(_tensor(temp[:, None]), _tensor(y))
    expected = np.polynomial.polynomial.polyfit(temp - 15.0, median_filter(y), 3)
    np.testing.assert_allclose(model.coef.numpy(), expected, rtol=1e-9, atol=1e-12)
    assert abs(float(model.coef[1, 0]) - 0.001) < 1e-4


def test_px4_correction_clamps_the_temperature_to_the_calibrated_range():
    model = Px4Cubic(1)
    model.temp_min_c.fill_(0.0), model.temp_max_c.fill_(30.0), model.temp_ref_c.fill_(15.0)
    model.coef.copy_(torch.tensor([[1.0, 0, 0], [0.1, 0, 0], [0.01, 0, 0], [0.001, 0, 0]], dtype=torch.float64))
    out = model(_tensor([[-10.0], [0.0], [20.0], [45.0]]))[:, 0].numpy()
    offset = [1 + 0.1 * d + 0.01 * d**2 + 0.001 * d**3 for d in (-15.0, -15.0, 5.0, 15.0)]
    np.testing.assert_allclose(out, offset)


def _onboard_rule(temp, time_s, t_min, t_max, rise, settle_s):
    """gyro.cpp's update_sensor_instance, one sample at a time, as the firmware runs it."""
    cold, low, high, used = False, None, None, []
    for i, (t, temp_c) in enumerate(zip(time_s, temp)):
        if temp_c < t_min:
            continue
        if not cold:
            if t > settle_s:
                if temp_c > t_max:
                    return "too hot"
                cold, low, high = True, temp_c, temp_c
            continue
        if temp_c <= high:
            continue
        high = temp_c
        used.append(i)
        if high - low > rise:
            return used, low, low + rise / 2
    return "not finished"


def _rising_run(start_c: float = 3.0, rng_seed: int = 1):
    rng = np.random.default_rng(rng_seed)
    time_s = np.arange(0.0, 2000.0, 1.0)
    true_c = np.clip(start_c + np.maximum(time_s - 20.0, 0) * 0.02, None, 40.0)
    temp = np.round((true_c + rng.normal(0, 0.05, len(time_s))) * 16) / 16
    return time_s, temp.astype(np.float32).astype(np.float64)


def test_onboard_rule_uses_only_new_highest_temperatures_from_the_cold_soak_point():
    time_s, temp = _rising_run(start_c=6.0)
    temp[:5] = 3.0  # below SYS_CAL_TMIN: skipped
    used, low, temp_ref = _onboard_rule(temp, time_s, 5.0, 10.0, 24.0, 10.0)
    model = Px4Onboard(2, time_index=1)
    mask, temp_min, ref = model.used_samples(temp, time_s)
    assert np.flatnonzero(mask).tolist() == used
    assert temp_min == low == temp[11] and ref == temp_ref == low + 12.0  # the first sample after 10 s
    drift = 0.02 - 0.001 * (temp - 18) + 2e-5 * (temp - 18) ** 3
    x = np.column_stack([temp, time_s / 3600.0])
    model.fit_closed_form(_tensor(x), _tensor(np.column_stack([drift, drift, drift])))
    assert float(model.temp_min_c) == low and float(model.temp_max_c) == temp[used[-1]] > low + 24.0
    assert float(model.temp_ref_c) == ref
    # the coefficients are stored as float parameters (rad/s): exact up to float32 rounding
    np.testing.assert_allclose(model.coef[:, 0].numpy(), [0.02 - 0.001 * (ref - 18) + 2e-5 * (ref - 18) ** 3,
                                                          -0.001 + 6e-5 * (ref - 18) ** 2, 6e-5 * (ref - 18), 2e-5],
                               rtol=1e-6, atol=1e-10)


def test_onboard_rule_refuses_a_warm_start_and_a_run_that_does_not_rise_enough():
    time_s, temp = _rising_run(start_c=12.0)
    assert _onboard_rule(temp, time_s, 5.0, 10.0, 24.0, 10.0) == "too hot"
    with pytest.raises(GyronetError, match=r"refuses to start at 12\.\d+ degC: above SYS_CAL_TMAX = 10 degC"):
        Px4Onboard(1).used_samples(temp, time_s)
    time_s, temp = _rising_run(start_c=6.0)
    assert _onboard_rule(temp, time_s, 5.0, 10.0, 40.0, 10.0) == "not finished"
    with pytest.raises(GyronetError, match="does not finish: the temperature rises .* SYS_CAL_TDEL = 40 degC"):
        Px4Onboard(1, temp_rise_c=40.0).used_samples(temp, time_s)


def _reference_module():
    spec = importlib.util.spec_from_file_location("px4_reference", DATA / "px4_reference.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize("case", sorted(REFERENCE["cases"]))
def test_px4_fit_equals_px4s_own_script_on_the_same_ulog(tmp_path, case):
    """PX4's process_sensor_caldata.py, run unmodified (px4_reference.json says how), against model=px4."""
    from gyronet.recordings.importers.ulog import import_ulog

    reference, fixture = _reference_module(), REFERENCE["cases"][case]
    path = reference.write_caldata_ulog(tmp_path / "caldata.ulg", fixture["generator"])
    assert reference.sha256(path) == fixture["ulog_sha256"], "the generator no longer writes the fixture's ULog"
    recording = import_ulog(path, accel=False)
    x, y = _tensor(recording.temp_c[:, None]), _tensor(recording.gyro_dps)
    grid = np.linspace(recording.temp_c.min() - 5, recording.temp_c.max() + 5, 1001)
    for name, resample in (("default", True), ("no_resample", False)):
        px4 = fixture[name]
        model = Px4Cubic(1, resample=resample)
        model.fit_closed_form(x, y)
        assert (float(model.temp_min_c), float(model.temp_max_c), float(model.temp_ref_c)) == (
            px4["TMIN"], px4["TMAX"], px4["TREF"])
        # PX4's curve in deg/s: calc_thermal_offsets_3D with TC_G0_* (rad/s)
        delta = np.clip(grid, px4["TMIN"], px4["TMAX"]) - px4["TREF"]
        expected = np.vander(delta, 4, increasing=True) @ (np.array(px4["coef_rad_s"]) * 180 / np.pi)
        ours = model(_tensor(grid[:, None])).numpy()
        assert np.abs(ours - expected).max() < 1e-6, name
    # and poly3 is neither: no median filter (the logs have spikes), every sample counted
    poly3 = TempPolynomial(1)
    poly3.fit_closed_form(x, y)
    assert np.abs(poly3(_tensor(grid[:, None])).numpy() - expected).max() > 1e-3


def test_px4_models_refuse_run_offsets_in_one_line():
    from gyronet.training.run_offsets import RunOffsets

    x = torch.linspace(0.0, 30.0, 200, dtype=torch.float64)[:, None]
    offsets = RunOffsets(np.repeat([0, 1], 100), 2)
    for model in (Px4Cubic(1), Px4Onboard(1)):
        with pytest.raises(GyronetError, match="cannot fit run offsets.*data.run_offsets=false"):
            offsets.fit_closed_form(model, x, torch.zeros(200, 3, dtype=torch.float64))
