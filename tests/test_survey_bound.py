"""form-bound: least squares in the simulator's own drift formula spans a survey sensor's drift exactly."""
import numpy as np
import pytest

from gyronet.analysis.survey.bound import form_bound_rate_dps, form_columns, score_form_bound
from gyronet.analysis.survey.scoring import turn_on_bias
from gyronet.errors import GyronetError
from gyronet.recordings.data import AXES, Recording
from gyronet.sim import simulate

QUIET = {"arw_deg_rthr": 0.0, "bias_instability_deg_hr": 0.0, "rrw_deg_hr_rthr": 0.0, "lsb_dps": 0.0}


def record(profile: str, seed: int, noise=None, sensor_seed: int = 5):
    sim = simulate(profile, 1.0, seed=seed, sensor_seed=sensor_seed, sensor={"distribution": "survey"},
                   noise=noise, duration_s=None if profile == "cycle" else 20000)
    return Recording(sim.recording, sim.meta), sim.truth, sim.sensor.to_dict()


def test_without_noise_the_fit_leaves_only_the_two_runs_turn_on_bias_difference():
    """Every term of the formula is spanned: both knees, each axis's lag, the dT/dt terms, the coupling."""
    train, train_truth, sensor = record("cycle", 1, QUIET)
    check, check_truth, _ = record("random", 2, QUIET)
    assert np.count_nonzero(sensor["coupling"]) == 6 and min(sensor["axis_lag_s"]) > 0 and any(sensor["knee2_dps"])
    rate = form_bound_rate_dps([(train, train_truth)], check, check_truth, sensor)
    true_rate = np.column_stack([check_truth[f"true_rate_{a}_dps"] for a in AXES])
    difference = turn_on_bias(check_truth) - turn_on_bias(train_truth)
    np.testing.assert_allclose(rate - true_rate, np.broadcast_to(difference, rate.shape), atol=1e-7)
    # one term short (the second knee's), and the fit misses by mdps: the test can tell
    no_knee2 = {**sensor, "knee2_dps": [0.0, 0.0, 0.0]}
    short = form_bound_rate_dps([(train, train_truth)], check, check_truth, no_knee2)
    assert np.abs(short - true_rate - difference).max() > 1e-3


def test_scored_with_noise_it_is_near_the_floor_and_each_run_keeps_its_constant():
    runs = [record("cycle", seed)[:2] for seed in (1, 3)]  # two power-ups: a constant each, their mean kept
    check, check_truth, sensor = record("random", 2)
    trained_bias = np.mean([turn_on_bias(truth) for _, truth in runs], axis=0)
    scores = score_form_bound(runs, check, check_truth, sensor, 600.0, turn_on_bias(check_truth) - trained_bias)
    assert max(scores["turn_on_removed"]) == pytest.approx(1.0, abs=0.1)
    assert max(scores["deployed"]) < 1.3 and min(scores["as_is"]) > max(scores["turn_on_removed"])


def test_a_record_with_lost_rows_is_refused_in_one_line():
    """The axis lags are filtered sample by sample: over a gap they would be wrong, and the bound with them."""
    _, truth, sensor = record("random", 2)
    gapped = {k: np.delete(v, slice(1000, 1100)) for k, v in truth.items()}
    with pytest.raises(GyronetError, match="form-bound needs records without lost rows"):
        form_columns(gapped, sensor)
