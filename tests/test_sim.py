"""The simulator: chamber profiles, die temperature, drift, noise figures, effects, files, script."""
import re
import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hydra import compose, initialize_config_dir

from gyronet.recordings.data import load_recording, load_truth, truth_path
from gyronet.errors import GyronetError
from gyronet.sim import (EFFECTS, chamber_profile, draw_sensor, earth_rate_dps, first_order_lag, play_operator,
                         simulate, write_simulation)

ROOT = Path(__file__).resolve().parents[1]
AXES = ("x", "y", "z")
ALL_EFFECTS = {name: {} for name in EFFECTS}
QUIET = {"bias_instability_deg_hr": 0.0, "rrw_deg_hr_rthr": 0.0}

try:  # the project's overlapping ADEV; allantools until it exists
    from gyronet.allan import oadev as _project_oadev

    def oadev(rate: np.ndarray, fs_hz: float, taus_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        taus, adev, _ = _project_oadev(rate, fs_hz, taus_s)
        return taus, adev
except ImportError:  # pragma: no cover
    import allantools

    def oadev(rate: np.ndarray, fs_hz: float, taus_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        taus, adev, _, _ = allantools.oadev(rate, rate=fs_hz, data_type="freq", taus=taus_s)
        return taus, adev


def gyro(sim, source: str = "recording", prefix: str = "gyro") -> np.ndarray:
    table = getattr(sim, source)
    return np.column_stack([table[f"{prefix}_{a}_dps"] for a in AXES])


def fit_allan(taus_s: np.ndarray, adev_dps: np.ndarray, terms: str) -> dict[str, float]:
    """Least squares of sigma^2 = N^2/tau + (0.664 B)^2 + K^2 tau/3 (relative errors), in the
    units of IEEE Std 952: N deg/sqrt(h), B deg/h, K deg/h/sqrt(h)."""
    basis = {"N": 1.0 / taus_s, "B": np.full_like(taus_s, 0.664**2), "K": taus_s / 3.0}
    design = np.column_stack([basis[t] for t in terms]) / adev_dps[:, None] ** 2
    coef, *_ = np.linalg.lstsq(design, np.ones_like(taus_s), rcond=None)
    to_ieee = {"N": 60.0, "B": 3600.0, "K": 216000.0}
    return {t: float(np.sqrt(max(c, 0.0))) * to_ieee[t] for t, c in zip(terms, coef)}


# --- chamber profiles --------------------------------------------------------------------------

def test_paper_profile_is_the_papers_staircase():
    time_s, chamber_c = chamber_profile("paper", fs_hz=0.5)
    duration_h = (time_s[-1] + 2.0) / 3600  # 11 dwells of 1 h and 10 ramps of 10 min
    assert duration_h == pytest.approx(11 + 100 / 60) and round(duration_h, 2) == 12.67
    assert chamber_c.max() == pytest.approx(60.0) and chamber_c.min() == pytest.approx(-40.0)
    for k, setpoint in enumerate(range(60, -41, -10)):  # the middle of each 1 h dwell
        mid_dwell_s = k * (3600 + 600) + 1800
        assert chamber_c[int(mid_dwell_s * 0.5)] == pytest.approx(setpoint, abs=1e-9)
    mid_ramp = int((3600 + 300) * 0.5)
    rate_c_per_min = np.gradient(chamber_c, time_s)[mid_ramp] * 60
    assert rate_c_per_min == pytest.approx(-1.0, rel=1e-6)
    assert np.all(np.diff(chamber_c) <= 1e-12)  # only ever cools


def test_cycle_profile_visits_the_same_temperatures_cooling_and_heating():
    time_s, chamber_c = chamber_profile("cycle", fs_hz=0.1)
    assert chamber_c[0] == pytest.approx(25) and chamber_c[-1] == pytest.approx(25)
    assert chamber_c.min() == pytest.approx(-40) and chamber_c.max() == pytest.approx(60)
    rate = np.gradient(chamber_c, time_s)
    at_zero = np.abs(chamber_c) < 1e-9
    before_zero = np.flatnonzero(at_zero)
    # dwells at 0 degC are entered once cooling (first leg) and once heating (second leg)
    entries = before_zero[np.flatnonzero(np.diff(before_zero, prepend=-10) > 1)]
    assert [np.sign(rate[i - 30]) for i in entries] == [-1.0, 1.0]
    assert np.abs(rate).max() * 60 == pytest.approx(1.0, rel=1e-6)


def test_random_profile_respects_its_ranges_and_seed():
    one = chamber_profile("random", 0.2, np.random.default_rng(1), duration_s=8 * 3600)
    same = chamber_profile("random", 0.2, np.random.default_rng(1), duration_s=8 * 3600)
    other = chamber_profile("random", 0.2, np.random.default_rng(2), duration_s=8 * 3600)
    time_s, chamber_c = one
    assert len(time_s) == 8 * 3600 * 0.2
    assert np.array_equal(chamber_c, same[1]) and not np.allclose(chamber_c, other[1])
    assert -40 <= chamber_c.min() and chamber_c.max() <= 60 and np.ptp(chamber_c) > 20
    assert np.abs(np.gradient(chamber_c, time_s)).max() * 60 <= 2.0 + 1e-9


def test_constant_profile_and_bad_options():
    time_s, chamber_c = chamber_profile("constant", 10.0, duration_s=5.0, temp_c=-12.5)
    assert len(time_s) == 50 and np.all(chamber_c == -12.5)
    with pytest.raises(GyronetError, match="unknown profile"):
        chamber_profile("sauna", 1.0)
    with pytest.raises(GyronetError, match="unknown option"):
        chamber_profile("paper", 1.0, banana=3)
    with pytest.raises(GyronetError, match="needs a random generator"):
        chamber_profile("random", 1.0, None)


# --- sensor: die temperature, temp_c, drift ----------------------------------------------------

def test_die_lags_the_chamber_with_the_sensors_time_constant():
    sim = simulate("paper", fs_hz=1.0, sensor={"self_heating_c": 0.0, "thermal_tau_s": 300.0})
    die_c, chamber_c = sim.truth["die_temp_c"], sim.truth["chamber_temp_c"]
    # tau dT_die/dt = T_chamber - T_die
    residual = 300.0 * np.gradient(die_c) - (chamber_c - die_c)
    assert np.abs(residual).max() < 0.01
    assert (die_c - chamber_c).max() > 1.5  # a few degC behind on a 1 degC/min ramp
    assert 200 <= draw_sensor(0).thermal_tau_s <= 500


def test_self_heating_rises_with_the_warmup_time_constant():
    sim = simulate("constant", fs_hz=1.0, duration_s=6 * 3600, temperature={"noise_c": 0.0})
    warm = sim.truth["die_temp_c"] - sim.truth["chamber_temp_c"]
    model = sim.sensor
    assert 1.5 <= model.self_heating_c <= 4.0
    assert warm[0] == 0.0
    assert warm[int(model.warmup_tau_s)] == pytest.approx(model.self_heating_c * (1 - np.exp(-1)), rel=1e-3)
    assert warm[-1] == pytest.approx(model.self_heating_c, rel=1e-4)


@pytest.mark.parametrize("lsb_c", [0.0625, 0.1])
def test_temp_c_is_the_quantised_die_temperature(lsb_c):
    sim = simulate("paper", fs_hz=0.2, temperature={"lsb_c": lsb_c, "noise_c": 0.02})
    temp_c = sim.recording["temp_c"]
    steps = temp_c / lsb_c
    assert np.allclose(steps, np.round(steps), atol=1e-9)
    error = temp_c - sim.truth["die_temp_c"]
    assert np.abs(error).max() <= lsb_c / 2 + 5 * 0.02
    assert abs(error.mean()) < 0.01 and len(np.unique(temp_c)) > 100


@pytest.mark.parametrize("sensor_seed", range(6))
def test_static_drift_swings_1_to_4_dps_differently_per_axis_and_is_not_a_cubic(sensor_seed):
    model = draw_sensor(sensor_seed)
    temp_c = np.linspace(-40, 60, 501)
    bias = model.static_bias_dps(temp_c)
    swing = np.ptp(bias, axis=0)
    assert np.all((swing >= 1.0) & (swing <= 4.0))
    centred = bias - bias.mean(axis=0)
    for i, j in ((0, 1), (0, 2), (1, 2)):
        assert np.abs(centred[:, i] - centred[:, j]).max() > 0.1
    for axis in range(3):
        cubic = np.polyval(np.polyfit(temp_c, bias[:, axis], 3), temp_c)
        assert np.abs(bias[:, axis] - cubic).max() > 0.02  # well above the 60 s noise floor


@pytest.mark.parametrize("sensor_seed", range(6))
def test_rate_terms_are_0p05_to_0p3_dps_at_1_degc_per_min(sensor_seed):
    model = draw_sensor(sensor_seed)
    per_min = 1.0 / 60.0
    for temp_c in (-40.0, 10.0, 60.0):
        ramp = model.drift_dps(np.array([temp_c]), np.array([-per_min]))
        settled = model.drift_dps(np.array([temp_c]), np.array([0.0]))
        size = np.abs(ramp - settled)[0]
        assert np.all((size >= 0.05) & (size <= 0.3)), (temp_c, size)
    assert np.all(np.abs(model.rate_gain_deg_per_c) * per_min >= 0.05)


def test_truth_drift_is_the_documented_formula_on_the_die_temperature():
    sim = simulate("paper", fs_hz=0.2, seed=3, sensor_seed=4)
    die_c, time_s = sim.truth["die_temp_c"], sim.truth["time_s"]
    expected = sim.sensor.drift_dps(die_c, np.gradient(die_c, time_s))
    assert np.allclose(gyro(sim, "truth", "drift"), expected, atol=1e-12)
    swing = np.ptp(gyro(sim, "truth", "drift"), axis=0)
    assert np.all((swing > 1.0) & (swing < 4.5))


def test_sensor_overrides():
    model = draw_sensor(2, swing_dps=[1.0, 2.0, 3.0], rate_gain_deg_per_c=0.0, thermal_tau_s=250)
    assert model.swing_dps() == pytest.approx([1.0, 2.0, 3.0], rel=1e-9)
    assert np.all(model.rate_gain_deg_per_c == 0) and model.thermal_tau_s == 250
    with pytest.raises(GyronetError, match="unknown sensor option"):
        draw_sensor(2, tau=3)


# --- identity, determinism, Earth rate ---------------------------------------------------------

STEPS = [{"start_s": 600.0, "duration_s": 30.0, "rate_dps": [10.0, 0.0, -5.0]}]


def test_gyro_is_true_rate_plus_drift_plus_noise():
    sim = simulate("cycle", fs_hz=0.5, duration_s=4 * 3600, effects=ALL_EFFECTS, rate_steps=STEPS)
    total = gyro(sim, "truth", "true_rate") + gyro(sim, "truth", "drift") + gyro(sim, "truth", "noise")
    assert np.abs(gyro(sim) - total).max() < 1e-12
    lsb = 0.00875
    assert np.allclose(gyro(sim) / lsb, np.round(gyro(sim) / lsb), atol=1e-6)  # output quantised
    effects = sum(np.column_stack([sim.truth[f"effect_{e}_{a}_dps"] for a in AXES]) for e in EFFECTS)
    die_c = sim.truth["die_temp_c"]
    base = sim.sensor.drift_dps(die_c, np.gradient(die_c, sim.truth["time_s"]))
    assert np.abs(gyro(sim, "truth", "drift") - base - effects).max() < 1e-12


def test_rate_steps_and_earth_rate_are_the_true_rate():
    sim = simulate("constant", fs_hz=10.0, duration_s=900, rate_steps=STEPS,
                   earth={"latitude_deg": 30.0})
    true_rate = gyro(sim, "truth", "true_rate")
    earth = earth_rate_dps(30.0, (0, 0, 0))
    on = (sim.truth["time_s"] >= 600) & (sim.truth["time_s"] < 630)
    assert on.sum() == 300
    assert np.allclose(true_rate[~on], earth) and np.allclose(true_rate[on], earth + [10, 0, -5])
    assert earth == pytest.approx([0, 15.041 / 3600 * np.cos(np.pi / 6), 15.041 / 3600 * 0.5])
    tilted = earth_rate_dps(30.0, (20.0, -35.0, 110.0))
    assert np.linalg.norm(tilted) == pytest.approx(15.041 / 3600)
    acc = np.column_stack([sim.recording[f"acc_{a}_g"] for a in AXES]).mean(axis=0)
    assert acc == pytest.approx([0, 0, 1], abs=2e-4)


def test_same_seeds_same_record_and_the_sensor_ignores_the_history_seed():
    first = simulate("random", 0.2, seed=5, sensor_seed=9, duration_s=4 * 3600, effects=ALL_EFFECTS)
    again = simulate("random", 0.2, seed=5, sensor_seed=9, duration_s=4 * 3600, effects=ALL_EFFECTS)
    for name, values in first.recording.items():
        assert np.array_equal(values, again.recording[name]), name
    other_history = simulate("random", 0.2, seed=6, sensor_seed=9, duration_s=4 * 3600)
    assert not np.allclose(other_history.truth["chamber_temp_c"], first.truth["chamber_temp_c"])
    assert other_history.sensor.to_dict() == first.sensor.to_dict()
    other_sensor = simulate("random", 0.2, seed=5, sensor_seed=10, duration_s=4 * 3600)
    assert np.array_equal(other_sensor.truth["chamber_temp_c"], first.truth["chamber_temp_c"])
    assert other_sensor.sensor.to_dict() != first.sensor.to_dict()


def test_noise_depends_on_seed_only():
    quiet = {"lsb_dps": 0.0}
    one = simulate("constant", 10.0, seed=1, sensor_seed=1, duration_s=60, noise=quiet)
    two = simulate("constant", 10.0, seed=1, sensor_seed=2, duration_s=60, noise=quiet)
    three = simulate("constant", 10.0, seed=2, sensor_seed=1, duration_s=60, noise=quiet)
    assert np.allclose(gyro(one, "truth", "noise"), gyro(two, "truth", "noise"), atol=1e-12)
    assert not np.allclose(gyro(one, "truth", "noise"), gyro(three, "truth", "noise"))


def test_noise_seed_moves_the_noise_and_nothing_else():
    """Two sensors in one chamber run: the same history and temperature curve, each its own noise."""
    base = simulate("random", 1.0, seed=3, sensor_seed=4, duration_s=3600)
    same = simulate("random", 1.0, seed=3, sensor_seed=4, duration_s=3600, noise_seed=3)
    other = simulate("random", 1.0, seed=3, sensor_seed=4, duration_s=3600, noise_seed=7)
    assert all(np.array_equal(v, same.recording[k]) for k, v in base.recording.items())
    assert "noise_seed" not in same.meta and other.meta["noise_seed"] == "7"
    for column in ("chamber_temp_c", "die_temp_c", "drift_x_dps", "true_rate_z_dps"):
        assert np.array_equal(base.truth[column], other.truth[column]), column
    assert not np.allclose(gyro(base, "truth", "noise"), gyro(other, "truth", "noise"))
    assert not np.array_equal(base.recording["temp_c"], other.recording["temp_c"])


# --- optional effects --------------------------------------------------------------------------

@pytest.fixture(scope="module")
def base_cycle():
    return simulate("cycle", fs_hz=0.1, seed=1, sensor_seed=1)


def test_effects_are_off_by_default(base_cycle):
    assert base_cycle.meta["effects"] == "none"
    assert not [c for c in base_cycle.truth if c.startswith("effect_")]
    assert "vdd_v" not in base_cycle.recording
    off = simulate("cycle", fs_hz=0.1, seed=1, sensor_seed=1, effects={"aux": {"enabled": False}})
    assert np.array_equal(gyro(off), gyro(base_cycle)) and "vdd_v" not in off.recording


@pytest.mark.parametrize("name", sorted(EFFECTS))
def test_each_effect_adds_its_own_visible_drift(base_cycle, name):
    sim = simulate("cycle", fs_hz=0.1, seed=1, sensor_seed=1, effects={name: {}})
    effect = np.column_stack([sim.truth[f"effect_{name}_{a}_dps"] for a in AXES])
    added = gyro(sim, "truth", "drift") - gyro(base_cycle, "truth", "drift")
    assert np.abs(added - effect).max() < 1e-12
    assert np.all(np.ptp(effect, axis=0) > 0.02)  # well above the 60 s noise floor
    assert np.all(np.ptp(effect, axis=0) < 0.3)
    assert sim.meta["effects"] == name
    # the noise is unchanged by switching an effect on
    assert np.abs(gyro(sim, "truth", "noise") - gyro(base_cycle, "truth", "noise")).max() < 0.00875


def test_effect_sizes_are_configurable_per_axis():
    sim = simulate("cycle", fs_hz=0.1, effects={"lag2": {"gain_dps_per_c": [0.0, 0.01, 0.02]}})
    swing = np.ptp(np.column_stack([sim.truth[f"effect_lag2_{a}_dps"] for a in AXES]), axis=0)
    assert swing[0] == 0 and swing[2] == pytest.approx(2 * swing[1])


def test_aux_writes_its_column_and_the_drift_follows_it():
    effects = {"aux": {"gain_dps_per_v": [0.05, 0.0, 0.03]},
               "hum": {"kind": "aux", "column": "humidity_pct", "nominal": 40.0, "wander": 5.0,
                       "step": 0.0, "read_noise": 0.1, "lsb": 0.1, "gain_dps_per_unit": 0.002}}
    sim = simulate("paper", fs_hz=0.1, seed=4, effects=effects)
    vdd, humidity = sim.recording["vdd_v"], sim.recording["humidity_pct"]
    assert abs(np.median(vdd) - 3.3) < 0.2 and np.ptp(vdd) > 0.02
    assert abs(np.median(humidity) - 40) < 15
    assert np.all(sim.truth["effect_aux_y_dps"] == 0)
    assert np.corrcoef(vdd, sim.truth["effect_aux_x_dps"])[0, 1] > 0.95
    assert np.corrcoef(humidity, sim.truth["effect_hum_z_dps"])[0, 1] > 0.95


def test_hysteresis_is_plus_gain_heating_and_minus_gain_cooling(base_cycle):
    sim = simulate("cycle", fs_hz=0.1, seed=1, sensor_seed=1, effects={"hysteresis": {"gain_dps": 0.05}})
    rate = np.gradient(sim.truth["die_temp_c"], sim.truth["time_s"])
    effect = sim.truth["effect_hysteresis_x_dps"]
    assert effect.max() == pytest.approx(0.05) and effect.min() == pytest.approx(-0.05)
    # after each reversal the play takes 2 width_c = 4 degC to reach the other branch
    assert np.mean(np.isclose(effect[rate > 0.01], 0.05)) > 0.7
    assert np.mean(np.isclose(effect[rate < -0.01], -0.05)) > 0.7
    assert np.allclose(play_operator(np.array([0.0, 3.0, 2.0, -1.0, 5.0]), 1.0), [0, 2, 2, 0, 4])


def test_a_board_die_gradient_follows_the_recorded_board_column():
    sim = simulate("cycle", fs_hz=0.1, seed=1, sensor_seed=1, effects={"board": {"tau_s": 600.0}})
    board_c, die_c = sim.recording["board_temp_c"], sim.truth["die_temp_c"]
    # the drift is gain * (lag(B, 600 s) - T): rebuilt from the recorded column within its read noise
    gradient_c = first_order_lag(board_c, 0.1, 600.0) - die_c
    assert np.abs(sim.truth["effect_board_x_dps"] - 0.008 * gradient_c).max() < 0.008 * 0.05
    assert np.allclose(sim.truth["effect_board_y_dps"] / sim.truth["effect_board_x_dps"], -0.75)
    # the board is slower than the die: on the cycle's ramps they part by degrees
    assert np.ptp(gradient_c) > 3.0 and np.std(board_c - sim.recording["temp_c"]) > 1.0


def test_lag2_warmup_ageing_shapes():
    six_hours_at_minus_40 = 45600 + 5 * 3600
    sim = simulate("paper", fs_hz=0.1, duration_s=six_hours_at_minus_40,
                   effects={"lag2": {"tau_s": 1800.0}, "warmup": {"tau_s": 900.0},
                            "ageing": {"rate_dps_per_h": [0.01, 0.0, -0.01]}})
    time_h = sim.truth["time_s"] / 3600
    lag2 = sim.truth["effect_lag2_x_dps"]
    assert abs(lag2[-1]) < 1e-3 * np.ptp(lag2)  # zero once the temperature has settled
    assert sim.truth["effect_warmup_x_dps"][0] == pytest.approx(0.08)
    assert sim.truth["effect_warmup_x_dps"][90] == pytest.approx(0.08 * np.exp(-1))
    assert np.allclose(sim.truth["effect_ageing_z_dps"], -0.01 * time_h)


def test_bad_effects_are_clear_errors():
    with pytest.raises(GyronetError, match="unknown effect 'sauna'"):
        simulate("constant", 1.0, duration_s=60, effects={"sauna": {}})
    with pytest.raises(GyronetError, match="unknown option"):
        simulate("constant", 1.0, duration_s=60, effects={"aux": {"gain": 1.0}})
    with pytest.raises(GyronetError, match="three"):
        simulate("constant", 1.0, duration_s=60, effects={"ageing": {"rate_dps_per_h": [1, 2]}})


# --- noise: the Allan figures the simulator was asked for --------------------------------------

CONSTANT = dict(profile="constant", sensor={"self_heating_c": 0.0}, accel={"enabled": False})


def test_angle_random_walk_matches_the_request():
    sim = simulate(fs_hz=10.0, duration_s=3600, noise=QUIET, **CONSTANT)  # default N, 8.75 mdps LSB
    taus, adev = oadev(gyro(sim), 10.0, np.logspace(-1, 1.5, 12))
    for axis, asked in enumerate([3.03, 4.55, 5.89]):
        assert fit_allan(taus, adev[:, axis], "N")["N"] == pytest.approx(asked, rel=0.05)


def test_bias_instability_is_the_allan_plateau_over_0p664():
    # N low so that the flicker plateau shows from about 10 s; 28 h at 1 Hz
    asked = [2.9, 3.9, 1.6]
    sim = simulate(fs_hz=1.0, duration_s=100_000, seed=3, **CONSTANT,
                   noise={"arw_deg_rthr": 0.03, "bias_instability_deg_hr": asked,
                          "rrw_deg_hr_rthr": 0.0, "lsb_dps": 0.0})
    taus, adev = oadev(gyro(sim), 1.0, np.logspace(1, 3.3, 12))
    for axis in range(3):
        fit = fit_allan(taus, adev[:, axis], "NB")
        assert fit["B"] == pytest.approx(asked[axis], rel=0.2)


def test_rate_random_walk_matches_the_request():
    asked = [5.0, 10.0, 20.0]
    sim = simulate(fs_hz=1.0, duration_s=200_000, seed=4, **CONSTANT,
                   noise={"arw_deg_rthr": 0.01, "bias_instability_deg_hr": 0.0,
                          "rrw_deg_hr_rthr": asked, "lsb_dps": 0.0})
    taus, adev = oadev(gyro(sim), 1.0, np.logspace(0, 3.3, 14))
    for axis in range(3):
        assert fit_allan(taus, adev[:, axis], "NK")["K"] == pytest.approx(asked[axis], rel=0.25)


def test_default_noise_matches_the_papers_raw_figures_at_short_tau():
    sim = simulate(fs_hz=10.0, duration_s=1800, **CONSTANT)
    taus, adev = oadev(gyro(sim), 10.0, [1.0])
    assert adev[0] * 60 == pytest.approx([3.03, 4.55, 5.89], rel=0.06)


# --- files and script --------------------------------------------------------------------------

def test_write_simulation_round_trip(tmp_path):
    sim = simulate("cycle", fs_hz=0.2, duration_s=3 * 3600, seed=2, effects={"aux": {}, "lag2": {}})
    recording_path, written_truth = write_simulation(sim, tmp_path / "run.csv")
    assert written_truth == truth_path(recording_path) == tmp_path / "run.truth.csv"
    recording, truth = load_recording(recording_path), load_truth(recording_path)
    assert {k: recording.meta[k] for k in ("fs_hz", "sensor", "seed", "sensor_seed", "profile")} == \
        {"fs_hz": "0.2", "sensor": "gyronet-sim", "seed": "2", "sensor_seed": "0", "profile": "cycle"}
    assert list(recording.columns) == list(sim.recording) and "vdd_v" in recording.aux_columns
    assert list(truth.columns) == list(sim.truth)
    for name, values in {**sim.recording, **sim.truth}.items():
        loaded = recording.columns.get(name, truth.columns.get(name))
        assert np.abs(loaded - values).max() <= 5e-9 * max(1.0, np.abs(values).max()), name
    total = sum(np.column_stack([truth.columns[f"{p}_{a}_dps"] for a in AXES])
                for p in ("true_rate", "drift", "noise"))
    assert np.abs(recording.gyro_dps - total).max() < 1e-8
    # the fast writer and gyronet.recordings.data.write_recording give the same numbers
    write_simulation(sim, tmp_path / "slow.csv", fast=False)
    slow = load_recording(tmp_path / "slow.csv")
    for name, values in recording.columns.items():
        assert np.abs(slow.columns[name] - values).max() <= 1e-8 * max(1.0, np.abs(values).max()), name


def _run_script(*overrides: str, cwd: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    return subprocess.run([sys.executable, str(ROOT / "scripts" / "simulate.py"), *overrides,
                           f"hydra.run.dir={cwd / 'hydra'}"], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=120)


def test_script_writes_recording_and_truth(tmp_path):
    out = tmp_path / "data" / "F.csv"
    done = _run_script(f"output={out}", "profile=constant", "duration_s=120", "seed=7",
                       "sim/effects=[aux,ageing]", "noise.arw_deg_rthr=[1,2,3]",
                       "+effects.aux.gain_dps_per_v=[0.05,0,0.03]", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    recording, truth = load_recording(out), load_truth(out)
    assert len(recording) == 1200 and recording.meta["seed"] == "7"
    assert recording.meta["effects"] == "aux,ageing" and recording.meta["arw_deg_rthr"] == "1/2/3"
    assert "vdd_v" in recording.columns and np.all(truth.columns["effect_aux_y_dps"] == 0)


def _script_main():
    spec = importlib.util.spec_from_file_location("simulate_script", ROOT / "scripts" / "simulate.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.main.__wrapped__  # under @hydra.main: the @exit_on_error task


@pytest.mark.parametrize("overrides, message", [
    (["profile=constant"], "error: no output file: add output=F.csv"),
    (["output=unused.csv", "profile=constant", "+effects.aux.gain=1"],
     "error: effect 'aux': unknown option(s) gain"),
    (["output=unused.csv", "profile=sauna"], "error: unknown profile 'sauna'"),
])
def test_script_errors_are_one_line(overrides, message, capsys):
    with initialize_config_dir(str(ROOT / "conf"), version_base="1.3"):
        cfg = compose("simulate", overrides=overrides)
    with pytest.raises(SystemExit) as stop:
        _script_main()(cfg)
    assert stop.value.code == 2
    assert capsys.readouterr().err.strip().startswith(message)


@pytest.mark.slow
def test_paper_profile_at_10_hz_end_to_end(tmp_path):
    sim = simulate()
    assert len(sim.recording["time_s"]) == 456_000
    recording_path, _ = write_simulation(sim, tmp_path / "paper.csv")
    recording, truth = load_recording(recording_path), load_truth(recording_path)
    total = sum(np.column_stack([truth.columns[f"{p}_{a}_dps"] for a in AXES])
                for p in ("true_rate", "drift", "noise"))
    assert np.abs(recording.gyro_dps - total).max() < 1e-8


# --- run-level settings: turn-on bias, orientation and g-sensitivity, decimation, sample loss ---

def _fingerprint(sim) -> dict:
    """Per column: mean, spread and three samples; robust to last-bit changes of numpy's kernels."""
    out = {}
    for part, table in (("recording", sim.recording), ("truth", sim.truth)):
        for name in sorted(table):
            v = np.asarray(table[name], dtype=np.float64)
            out[f"{part}.{name}"] = [float(v.mean()), float(v.std()), float(v[0]), float(v[len(v) // 3]), float(v[-1])]
    return out


def _same(a: dict, b: dict) -> bool:
    return a.keys() == b.keys() and all(np.allclose(a[k], b[k], rtol=1e-9, atol=1e-12) for k in a)


# recorded by the simulator as it was before the run-level settings existed (tests/data; a bit-for-bit
# digest moved with numpy's build from one machine to the next): with them off, nothing moves
_FINGERPRINTS = json.loads((Path(__file__).parent / "data" / "sim_fingerprints.json").read_text())
RUN_OFF = {"sensor": {"turn_on_bias_dps": 0.0, "g_sensitivity_dps_per_g": 0.0}, "orientation": None,
           "decimate": 1, "loss": {"fraction": 0.0, "bursts_per_h": 0.0, "burst_s": 10.0}}


def test_run_settings_off_leave_the_simulation_unchanged():
    cycle = simulate("cycle", fs_hz=0.5, seed=3, sensor_seed=2)
    assert _same(_fingerprint(cycle), _FINGERPRINTS["cycle"])
    off = simulate("cycle", fs_hz=0.5, seed=3, sensor_seed=2, **RUN_OFF)
    assert all(np.array_equal(cycle.recording[k], off.recording[k]) for k in cycle.recording)
    assert all(np.array_equal(cycle.truth[k], off.truth[k]) for k in cycle.truth) and cycle.meta == off.meta
    paper = simulate("paper", fs_hz=1.0, seed=1, sensor_seed=4, effects={"aux": {}, "lag2": {}})
    assert _same(_fingerprint(paper), _FINGERPRINTS["paper_aux_lag2"])
    assert paper.run == {}


def test_turn_on_bias_is_a_constant_per_run_seed_apart_from_the_temperature_curve():
    runs = [simulate("cycle", fs_hz=0.05, seed=s, sensor_seed=3, duration_s=4 * 3600,
                     sensor={"turn_on_bias_dps": [0.02, 0.05, 0.0]}) for s in range(40)]
    biases = np.array([r.run["turn_on_bias_dps"] for r in runs])
    assert np.allclose(biases[:, 2], 0.0)
    # the standard deviation over runs is the setting (40 draws: within 35 %)
    assert np.std(biases[:, :2], axis=0) == pytest.approx([0.02, 0.05], rel=0.35)
    again = simulate("cycle", fs_hz=0.05, seed=7, sensor_seed=3, duration_s=4 * 3600,
                     sensor={"turn_on_bias_dps": [0.02, 0.05, 0.0]})
    assert again.run == runs[7].run  # from the run's seed: reproducible
    plain = simulate("cycle", fs_hz=0.05, seed=7, sensor_seed=3, duration_s=4 * 3600)
    column = gyro(again, "truth", "turn_on_bias")
    assert np.all(column == biases[7])
    # part of the drift, on top of the unchanged temperature curve and noise; the identity holds
    assert np.allclose(gyro(again, "truth", "drift"), gyro(plain, "truth", "drift") + biases[7], atol=1e-12)
    assert again.sensor.to_dict() == plain.sensor.to_dict()
    assert np.array_equal(gyro(again, "truth", "true_rate"), gyro(plain, "truth", "true_rate"))
    total = sum(gyro(again, "truth", p) for p in ("true_rate", "drift", "noise"))
    assert np.abs(gyro(again) - total).max() < 1e-12
    with pytest.raises(GyronetError, match="turn_on_bias_dps must be >= 0"):
        simulate("constant", 1.0, duration_s=60, sensor={"turn_on_bias_dps": -1.0})


def test_run_bump_is_new_each_run_and_sits_in_the_runs_temperatures():
    kwargs = dict(fs_hz=0.05, sensor_seed=3, duration_s=6 * 3600, sensor={"run_bump_dps": [0.1, 0.0, 0.05]})
    runs = [simulate("random", seed=s, **kwargs) for s in range(30)]
    bumps = np.array([gyro(r, "truth", "run_bump") for r in runs])
    peaks = np.array([b[np.argmax(np.abs(b), axis=0), range(3)] for b in bumps])
    assert np.allclose(peaks[:, 1], 0.0)
    assert np.std(peaks[:, [0, 2]], axis=0) == pytest.approx([0.1, 0.05], rel=0.4)  # its peak is near the amplitude
    assert len(np.unique(np.round(peaks[:, 0], 9))) == 30  # a bump of each run's own
    run = runs[4]
    die = run.truth["die_temp_c"]
    centre = die[np.argmax(np.abs(bumps[4][:, 0]))]
    assert np.percentile(die, 5) - 0.5 <= centre <= np.percentile(die, 95) + 0.5
    plain = simulate("random", seed=4, **{**kwargs, "sensor": {}})
    assert np.allclose(gyro(run, "truth", "drift"), gyro(plain, "truth", "drift") + bumps[4], atol=1e-12)
    # the same noise, but for the output quantisation's share (one step at most)
    assert np.abs(gyro(run, "truth", "noise") - gyro(plain, "truth", "noise")).max() <= 0.00875 + 1e-12
    with pytest.raises(GyronetError, match="run_bump_dps must be >= 0"):
        simulate("constant", 1.0, duration_s=60, sensor={"run_bump_dps": -1.0})


def test_run_settle_is_new_each_run_and_gone_within_hours():
    kwargs = dict(fs_hz=0.1, sensor_seed=3, duration_s=8 * 3600, sensor={"run_settle_dps": [0.05, 0.0, 0.02]})
    runs = [simulate("random", seed=s, **kwargs) for s in range(30)]
    settles = np.array([gyro(r, "truth", "run_settle") for r in runs])
    assert np.allclose(settles[:, :, 1], 0.0)
    assert np.std(settles[:, 0, [0, 2]], axis=0) == pytest.approx([0.05, 0.02], rel=0.4)  # at power-up
    assert np.all(np.abs(settles[:, -1]) <= 1e-3 * np.abs(settles[:, 0]) + 1e-15)  # 8 h is 12 tau or more
    assert len(np.unique(np.sign(settles[:, 0, 0]))) == 2  # either sign, run by run, as the real tag's y
    plain = simulate("random", seed=4, **{**kwargs, "sensor": {}})
    assert np.allclose(gyro(runs[4], "truth", "drift"), gyro(plain, "truth", "drift") + settles[4], atol=1e-12)
    with pytest.raises(GyronetError, match="run_settle_dps must be >= 0"):
        simulate("constant", 1.0, duration_s=60, sensor={"run_settle_dps": -1.0})


@pytest.mark.parametrize("name, axis, sign", [("z_up", 2, 1), ("z_down", 2, -1), ("y_up", 1, 1),
                                              ("y_down", 1, -1), ("x_up", 0, 1), ("x_down", 0, -1)])
def test_named_orientation_turns_gravity_and_the_earth_rate(name, axis, sign):
    sim = simulate("constant", 1.0, duration_s=600, orientation=name, earth={"latitude_deg": 30.0},
                   accel={"noise_g": 0.0})
    acc = np.column_stack([sim.recording[f"acc_{a}_g"] for a in AXES])
    expected = np.zeros(3)
    expected[axis] = sign
    assert np.allclose(acc, expected, atol=1e-12)
    earth = gyro(sim, "truth", "true_rate")[0]
    assert np.linalg.norm(earth) == pytest.approx(15.041 / 3600)
    # the Up component of the Earth rate, Omega sin(lat), lies along the Up-pointing axis
    assert earth[axis] * sign == pytest.approx(15.041 / 3600 * 0.5)
    assert sim.meta["orientation"] == name and "g_sensitivity_x_dps" not in sim.truth


def test_g_sensitivity_is_the_sensors_matrix_times_the_runs_gravity():
    common = {"profile": "constant", "fs_hz": 1.0, "duration_s": 600, "sensor_seed": 5,
              "sensor": {"g_sensitivity_dps_per_g": 0.03}}
    z_down = simulate(seed=1, orientation="z_down", **common)
    y_down = simulate(seed=2, orientation="y_down", **common)
    matrix = np.array(z_down.run["g_sensitivity_dps_per_g"])
    assert matrix.shape == (3, 3) and np.array_equal(matrix, y_down.run["g_sensitivity_dps_per_g"])
    assert 0.005 < np.std(matrix) < 0.06
    assert np.allclose(gyro(z_down, "truth", "g_sensitivity"), matrix @ [0, 0, -1])
    assert np.allclose(gyro(y_down, "truth", "g_sensitivity"), matrix @ [0, -1, 0])
    # the runs differ by the constant G (f_1 - f_2) on top of the same temperature curve
    plain = simulate(seed=1, orientation="z_down", **{**common, "sensor": {}})
    assert np.allclose(gyro(z_down, "truth", "drift") - gyro(plain, "truth", "drift"), matrix @ [0, 0, -1])
    assert np.abs(gyro(z_down) - sum(gyro(z_down, "truth", p) for p in ("true_rate", "drift", "noise"))).max() < 1e-12
    identity = {**common, "sensor": {"g_sensitivity_dps_per_g": np.eye(3).tolist()}}
    given = simulate(seed=1, orientation="x_up", **identity)
    assert np.allclose(gyro(given, "truth", "g_sensitivity"), [1, 0, 0])
    # without a named orientation, the earth spec's orientation is the one that counts
    level = simulate(seed=1, **common)
    assert np.allclose(gyro(level, "truth", "g_sensitivity"), matrix @ [0, 0, 1])
    with pytest.raises(GyronetError, match="unknown orientation"):
        simulate(seed=1, orientation="upside", **common)
    with pytest.raises(GyronetError, match="give one of them"):
        simulate(seed=1, orientation="z_down", earth={"orientation_deg": [10, 0, 0]}, **common)


def test_decimation_averages_every_column_like_a_resampled_recording(tmp_path):
    fast = simulate("cycle", fs_hz=2.0, seed=4, duration_s=2 * 3600 + 1.0, sensor={"turn_on_bias_dps": 0.01})
    slow = simulate("cycle", fs_hz=2.0, seed=4, duration_s=2 * 3600 + 1.0, sensor={"turn_on_bias_dps": 0.01},
                    decimate=4)
    assert len(fast.recording["time_s"]) == 14402 and len(slow.recording["time_s"]) == 3600
    assert slow.meta["fs_hz"] == "0.5" and slow.meta["decimated_from_hz"] == "2"
    for table in ("recording", "truth"):
        for name, values in getattr(fast, table).items():
            expected = values[:14400].reshape(-1, 4).mean(axis=1)
            assert np.allclose(getattr(slow, table)[name], expected, rtol=0, atol=1e-12), name
    assert np.allclose(np.diff(slow.recording["time_s"]), 2.0)
    total = sum(gyro(slow, "truth", p) for p in ("true_rate", "drift", "noise"))
    assert np.abs(gyro(slow) - total).max() < 1e-12
    # white noise averaged over 4 samples: 1/2 the per-sample deviation, the same ARW
    assert np.std(gyro(slow, "truth", "noise"), axis=0) / np.std(gyro(fast, "truth", "noise"), axis=0) \
        == pytest.approx([0.5] * 3, rel=0.1)
    write_simulation(slow, tmp_path / "slow.csv")
    assert load_recording(tmp_path / "slow.csv").fs_hz == pytest.approx(0.5)
    with pytest.raises(GyronetError, match="decimate must be"):
        simulate("constant", 1.0, duration_s=60, decimate=0)


def test_sample_loss_drops_the_same_rows_from_recording_and_truth(tmp_path):
    common = {"profile": "constant", "fs_hz": 1.0, "duration_s": 20 * 3600, "seed": 3}
    whole = simulate(**common)
    lossy = simulate(loss={"fraction": 0.02, "bursts_per_h": 1.0, "burst_s": 60.0}, **common)
    time_s = lossy.recording["time_s"]
    assert np.array_equal(time_s, lossy.truth["time_s"])
    assert time_s[0] == whole.recording["time_s"][0] and time_s[-1] == whole.recording["time_s"][-1]
    kept = np.isin(whole.recording["time_s"], time_s)
    for table in ("recording", "truth"):
        for name, values in getattr(lossy, table).items():
            assert np.array_equal(values, getattr(whole, table)[name][kept]), name
    lost = 1 - kept.mean()
    # 2 % single rows, plus about 20 bursts of 60 s (1.7 %)
    assert 0.025 < lost < 0.06
    gaps = np.diff(time_s)
    assert gaps.max() > 20 and np.sum(gaps > 10) >= 8
    assert np.isclose(np.mean(gaps == 2.0), 0.02 * 0.98, atol=0.005)  # single lost rows
    write_simulation(lossy, tmp_path / "lossy.csv")
    loaded = load_recording(tmp_path / "lossy.csv")  # gaps are allowed: a break in the record
    assert len(loaded) == len(time_s) and loaded.fs_hz == pytest.approx(1.0)
    assert np.abs(load_truth(tmp_path / "lossy.csv").columns["drift_x_dps"] - lossy.truth["drift_x_dps"]).max() < 1e-8
    with pytest.raises(GyronetError, match="unknown loss option"):
        simulate("constant", 1.0, duration_s=60, loss={"rate": 0.1})
    with pytest.raises(GyronetError, match="loss needs"):
        simulate("constant", 1.0, duration_s=60, loss={"fraction": 1.5})


def test_script_passes_the_run_settings_through(tmp_path):
    out = tmp_path / "run.csv"
    done = _run_script(f"output={out}", "profile=constant", "duration_s=200", "fs_hz=10", "decimate=10",
                       "orientation=y_down", "+sensor.turn_on_bias_dps=0.05",
                       "+sensor.g_sensitivity_dps_per_g=0.02", "loss.fraction=0.05", cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    recording, truth = load_recording(out), load_truth(out)
    assert recording.meta["orientation"] == "y_down" and recording.meta["fs_hz"] == "1"
    assert 150 < len(recording) < 200 and np.allclose(recording.columns["acc_y_g"].mean(), -1, atol=0.01)
    assert "turn_on_bias_x_dps" in truth.columns and "g_sensitivity_z_dps" in truth.columns
    assert "run" in truth.meta and "run" not in recording.meta


@pytest.mark.parametrize("kind, options, refused", [
    ("paper", {"rate_c_per_min": 0}, "rate_c_per_min must be more than 0"),  # ZeroDivisionError
    ("paper", {"rate_c_per_min": -1}, "rate_c_per_min must be more than 0"),  # ramps back in time, exit 0
    ("cycle", {"rate_c_per_min": -1}, "rate_c_per_min must be more than 0"),
    ("paper", {"step_c": 0}, "step_c must be more than 0"),
    ("cycle", {"step_c": -5}, "step_c must be at least 0"),
    ("paper", {"dwell_s": -5}, "dwell_s must be at least 0"),
    ("random", {"dwell_s": -5}, "dwell_s must be at least 0"),  # TypeError
    ("random", {"rate_c_per_min": [2.0, 0.5]}, "low <= high"),
    ("random", {"dwell_s": "abc"}, "dwell_s must be a number or a [low, high] range"),
    ("paper", {"corner_s": -1}, "corner_s must be at least 0"),
])
def test_profile_options_that_would_give_a_wrong_history_are_refused(kind, options, refused):
    with pytest.raises(GyronetError, match=re.escape(refused)):
        chamber_profile(kind, 1.0, np.random.default_rng(0), **options)


def test_a_random_profile_takes_one_number_as_a_fixed_dwell():
    time_s, _ = chamber_profile("random", 1.0, np.random.default_rng(0), duration_s=7200, dwell_s=300)
    assert len(time_s) == 7200


def test_negative_seeds_and_a_sample_count_beyond_memory_are_one_line():
    with pytest.raises(GyronetError, match="seed must be 0 or more, got -1"):
        simulate("constant", fs_hz=1.0, duration_s=100, seed=-1)
    with pytest.raises(GyronetError, match="sensor_seed must be 0 or more, got -1"):
        simulate("constant", fs_hz=1.0, duration_s=100, sensor_seed=-1)
    with pytest.raises(GyronetError, match="4.56e[+]13 samples, more than the simulator's"):  # a 447 GiB MemoryError
        chamber_profile("paper", 1e9)
    with pytest.raises(GyronetError, match="inf samples, more than the simulator's"):  # an OverflowError
        chamber_profile("paper", 1e308)
    for duration_s in (float("inf"), float("nan"), -1.0):
        with pytest.raises(GyronetError, match="duration_s must be a positive, finite number of seconds"):
            chamber_profile("random", 1.0, np.random.default_rng(0), duration_s=duration_s)
