"""What each flight stack's users get from an exported cubic (gyronet/deploy/as_flown.py): PX4's 1 Hz /
1 degC offset schedule on cases worked out by hand, and ArduPilot's difference form e(T) - e(T_cal)."""
import json

import numpy as np
import pytest
import torch

from gyronet.model.baselines import TempPolynomial
from gyronet.bundle.compensator import Compensated
from gyronet.recordings.data import AXES, load_recording, load_truth
from gyronet.training.dataset import DriftData, block_rmse
from gyronet.deploy.as_flown import (difference_error, is_px4_cubic, minimax_cubic, px4_calibrated_error,
                                     px4_firmware_output, px4_published_index, px4_schedule_error)
from gyronet.deploy.params import ardupilot_cubic, bundle_curve, export_params, fit_cubic, px4_cubic, read_params
from gyronet.errors import GyronetError
from gyronet.training.pipeline import train_run
from gyronet.analysis.table import table_rows


def test_schedule_on_a_ramp_crossing_the_threshold_worked_by_hand():
    # 2 Hz samples, 0.25 degC/s (exact in float32): the module runs at t = 0, 1, 2, ... and reads the
    # sample at t (index 2 t). t = 0 publishes (last temperature starts at -100); at t = 4 the rise is
    # exactly 1.0, not > 1, so the next publication is t = 5 (20 + 1.25), then t = 10 (22.5), t = 15
    time_s = np.arange(0, 16.0, 0.5)
    temp_c = 20.0 + 0.25 * time_s
    held = px4_published_index(time_s, temp_c)
    expected = np.zeros(len(time_s), dtype=int)
    expected[11:] = 10  # read at t = 5 (index 10): applies from the next sample, t = 5.5
    expected[21:] = 20  # t = 10
    expected[31:] = 30  # t = 15, from t = 15.5
    np.testing.assert_array_equal(held, expected)
    assert np.all(held <= np.arange(len(time_s)))  # causal


def test_schedule_reads_the_newest_sample_runs_through_a_gap_and_follows_cooling():
    # samples at 0, 0.7, 1.4, 2.1, then a gap to 6.3, 6.8; temperatures cool through the threshold
    time_s = np.array([0.0, 0.7, 1.4, 2.1, 6.3, 6.8, 7.6])
    temp_c = np.array([30.0, 29.5, 28.9, 28.5, 27.0, 26.5, 25.8])
    # runs at 0 (index 0: publish 30.0), 1 (index 1, 29.5: |-0.5|), 2 (index 2, 28.9: |-1.1| > 1: publish,
    # from index 3 on), 3, 4, 5, 6 (index 3 each time, then no new sample: nothing), 7 (index 5, 26.5:
    # |-2.4|: publish, from index 6 on)
    held = px4_published_index(time_s, temp_c)
    np.testing.assert_array_equal(held, [0, 0, 0, 2, 2, 2, 5])  # index 4 (6.3 s) is never read
    with pytest.raises(GyronetError, match="one length"):
        px4_published_index(time_s, temp_c[:-1])


def test_the_firmware_output_holds_the_drift_and_keeps_the_total():
    time_s = np.arange(0, 8.0, 0.5)
    temp_c = 10.0 + 0.5 * time_s
    drift = np.column_stack([temp_c, -temp_c, 2 * temp_c]) * 1e-3
    gyro = np.full((len(time_s), 3), 0.2)
    out = px4_firmware_output(time_s, temp_c, Compensated(gyro - drift, drift, np.zeros(len(time_s), bool)))
    # runs at 0 (10.0), 1 (10.5), 2 (11.0: 1.0, not > 1), 3 (11.5: publish), 4 (12.0), 5 (12.5: 1.0),
    # 6 (13.0: publish), 7 (13.5); each applies from the sample after the one read
    held = np.array([0] * 7 + [6] * 6 + [12] * 3)
    np.testing.assert_allclose(out.drift_dps, drift[held])
    np.testing.assert_allclose(out.rate_dps + out.drift_dps, gyro)


def test_the_held_offset_bound_is_what_a_slow_ramp_gives():
    grid = np.linspace(0.0, 40.0, 4001)
    curve = np.column_stack([1e-3 * (grid - 20) + 2e-6 * (grid - 20) ** 3, 0.01 * np.tanh(grid - 25), 0 * grid])
    cubic = fit_cubic(grid, curve).cubic
    bound = px4_schedule_error(grid, cubic(grid), curve, 1.0 + 1 / 60)
    # the same cubic run through the schedule on a 1 degC/min ramp up and down, 10 Hz
    time_s = np.arange(0, 4800.0, 0.1)
    temp_c = np.where(time_s < 2400, time_s / 60, 80 - time_s / 60)
    held = px4_published_index(time_s, temp_c)
    truth = np.column_stack([np.interp(temp_c, grid, c) for c in curve.T])
    as_run = np.abs(cubic(temp_c[held]) - truth).max(0)
    assert np.all(as_run <= bound + 1e-6)
    np.testing.assert_allclose(as_run[:2], bound[:2], rtol=0.03)
    per_sample = np.abs(cubic(grid) - curve).max(0)
    assert np.all(bound >= per_sample) and bound[0] > 1.5 * per_sample[0]


def test_the_held_bounds_by_brute_force_on_a_coarse_grid():
    # 0.5 degC spacing, a step of 1 degC: T' is T or a neighbour or the next but one, clamped at the ends
    grid = np.arange(0.0, 10.5, 0.5)
    curve = np.column_stack([np.sin(grid / 2), 0.1 * grid, grid**2 / 50])
    cubic = curve + np.column_stack([0.01 * np.cos(grid), 0 * grid, 0.02 * np.ones_like(grid)])
    errors = np.array([[cubic[min(max(i + k, 0), len(grid) - 1)] - curve[i] for k in range(-2, 3)]
                       for i in range(len(grid))])  # (T, T', axis)
    np.testing.assert_allclose(px4_schedule_error(grid, cubic, curve, 1.0), np.abs(errors).max((0, 1)))
    np.testing.assert_allclose(px4_calibrated_error(grid, cubic, curve, 1.0),
                               errors.max((0, 1)) - errors.min((0, 1)))
    # with no hold (a step of 0), the calibrated bound is the difference form's
    np.testing.assert_allclose(px4_calibrated_error(grid, cubic, curve, 0.0), difference_error(cubic - curve)[0])


def _knee_curve() -> tuple[np.ndarray, np.ndarray]:
    grid = np.linspace(-40.0, 60.0, 2001)
    return grid, np.column_stack([0.05 * np.tanh((grid - 10) / 4), 0.03 * np.tanh((grid + 20) / 8),
                                  1e-3 * grid + 0.02 * np.exp(-((grid - 40) / 5) ** 2)])


def test_the_minimax_cubic_equioscillates_and_beats_least_squares_on_the_difference_error():
    grid, curve = _knee_curve()
    least_squares, minimax = fit_cubic(grid, curve, "px4"), fit_cubic(grid, curve, "difference")
    ls_bound, _ = difference_error(least_squares.cubic(grid) - curve)
    mm_bound, _ = difference_error(minimax.cubic(grid) - curve)
    assert np.all(mm_bound < 0.95 * ls_bound)
    # the bound over T and T_cal, by brute force on a coarse subgrid of pairs
    sub = slice(None, None, 20)
    e = (minimax.cubic(grid) - curve)[sub]
    np.testing.assert_allclose(np.abs(e[:, None, :] - e[None, :, :]).max((0, 1)), mm_bound, rtol=0.01)
    # Chebyshev: the best uniform cubic touches its largest error at 5 points with alternating sign
    for axis in range(3):
        error = minimax.cubic(grid)[:, axis] - curve[:, axis]
        peak = np.abs(error).max()
        touching = np.flatnonzero(np.abs(error) > peak * (1 - 1e-4))
        signs = np.sign(error[touching])
        changes = 1 + np.count_nonzero(np.diff(signs))
        assert changes >= 5, (axis, changes)
    # the minimax is the least-squares cubic's bound's lower limit: no perturbation improves it
    rng = np.random.default_rng(0)
    delta = grid - minimax.cubic.temp_ref_c
    for _ in range(50):
        trial = minimax.cubic.coef_dps + rng.normal(0, 1e-4, (4, 3)) / 50.0 ** np.arange(4)[:, None]
        assert np.all(np.ptp(np.vander(delta, 4, increasing=True) @ trial - curve, 0) >= mm_bound * (1 - 1e-5))


def test_minimax_recovers_a_cubic_exactly():
    delta = np.linspace(-30, 30, 301)
    coef = np.array([[0.1, -0.2], [1e-3, 2e-3], [-2e-5, 1e-5], [3e-7, -1e-7]])
    np.testing.assert_allclose(minimax_cubic(delta, np.vander(delta, 4, increasing=True) @ coef), coef,
                               rtol=1e-6, atol=1e-12)


def test_ardupilot_sidecar_states_the_difference_bound_and_its_params_give_it(bundle, tmp_path):
    summary = export_params(bundle, tmp_path / "ap.params", "ardupilot")
    sidecar = json.loads((tmp_path / "ap.json").read_text())
    # the old keys keep working
    for key in ("format", "bundle", "params", "n_params", "model_class", "temp_min_c", "temp_max_c", "temp_ref_c",
                "coef_dps", "max_error_dps", "rms_error_dps", "grid"):
        assert key in sidecar, key
    assert sidecar["fit_form"] == "difference" and sidecar["stated_error_dps"] == sidecar["difference_max_error_dps"]
    assert sidecar["other_fit"]["fit_form"] == "px4"
    # ArduPilot's correction from the file read back (correct_sensor: both temperatures clamped), every
    # (T, T_cal) pair of a grid: the error against the bundle's own difference
    grid, target, curve, _ = bundle_curve(bundle)
    cubic = ardupilot_cubic(read_params(tmp_path / "ap.params"))
    temps = grid[::10]
    ours = cubic(temps) - curve(temps)
    measured = np.abs(ours[:, None, :] - ours[None, :, :]).max((0, 1))
    stated = np.array([summary["stated_error_dps"][a] for a in AXES])
    np.testing.assert_allclose(measured, stated, rtol=0.02, atol=1e-6)
    assert np.all(stated > 1e-4)  # a network is no cubic
    ls = np.array([sidecar["other_fit"]["difference_max_error_dps"][a] for a in AXES])
    assert np.all(stated <= ls * (1 + 1e-6)) and stated.sum() < ls.sum()
    # PX4's stated per-sample error would understate it: the bound is up to twice the largest |e|
    per_sample = np.array([summary["max_error_dps"][a] for a in AXES])
    np.testing.assert_allclose(stated, 2 * per_sample, rtol=1e-4)


def test_px4_sidecar_states_both_errors_and_the_history_as_the_firmware_runs(bundle, cycle_csv, tmp_path):
    summary = export_params(bundle, tmp_path / "tc.params", "px4", history=cycle_csv)
    sidecar = json.loads((tmp_path / "tc.json").read_text())
    assert sidecar["fit_form"] == "px4" and sidecar["px4_firmware"]["temp_step_c"] == pytest.approx(1 + 1 / 60)
    per_sample = np.array([summary["max_error_dps"][a] for a in AXES])
    firmware = np.array([summary["px4_firmware"]["max_error_dps"][a] for a in AXES])
    assert summary["stated_error_dps"] == summary["px4_firmware"]["max_error_dps"]
    assert np.all(firmware >= per_sample) and np.all(firmware > per_sample + 1e-4)
    # after PX4's gyro calibration: the difference form, with the offsets held
    calibrated = np.array([summary["px4_firmware"]["after_gyro_calibration_max_error_dps"][a] for a in AXES])
    assert np.all(calibrated >= np.array([summary["difference_max_error_dps"][a] for a in AXES]) - 1e-12)
    # on the cycle's temperatures: the .params read back, held as the firmware holds it
    recording = load_recording(cycle_csv)
    cubic = px4_cubic(read_params(tmp_path / "tc.params"))
    grid, target, curve, _ = bundle_curve(bundle)
    held = px4_published_index(recording.time_s, recording.temp_c)
    as_run = cubic(recording.temp_c[held]) - curve(recording.temp_c)
    history = sidecar["history"]
    np.testing.assert_allclose([history["as_run"]["max_error_dps"][a] for a in AXES], np.abs(as_run).max(0),
                               rtol=1e-4, atol=1e-7)
    # the bound at the step the history's reading actually made (its 1/16 degC quantum can pass 1 degC)
    step_c = max(history["temp_step_c"], sidecar["px4_firmware"]["temp_step_c"])
    bound = px4_schedule_error(grid, cubic(grid), target, step_c)
    assert np.all(np.abs(as_run).max(0) <= bound + 1e-6)
    with pytest.raises(GyronetError, match="fit must be one of px4, difference"):
        export_params(bundle, tmp_path / "x.params", "px4", fit="chebyshev")


def test_table_runs_px4_rows_as_the_firmware_and_leaves_gyronet_alone(paper_csv, cycle_csv, bundle, tmp_path):
    data = DriftData(str(paper_csv))
    train_run(data, TempPolynomial(data.n_features), None, tmp_path, {"progress": False})
    poly3 = tmp_path / "compensator"
    assert is_px4_cubic(json.loads((poly3 / "meta.json").read_text()))
    assert not is_px4_cubic(json.loads((bundle / "meta.json").read_text()))
    bundles = {"PX4-cubic": poly3, "gyronet": bundle}
    firmware, per_sample = table_rows(cycle_csv, bundles), table_rows(cycle_csv, bundles, px4_firmware_schedule=False)
    assert firmware["gyronet"] == per_sample["gyronet"]
    # independently: the poly3 drift held at the schedule's samples, against the truth in 60 s blocks
    recording, truth = load_recording(cycle_csv), load_truth(cycle_csv).columns
    model = torch.jit.load(str(poly3 / "model.pt"))
    temp = torch.as_tensor(recording.temp_c[:, None].repeat(data.n_features, 1))
    with torch.no_grad():
        drift = model(temp).numpy()
    true_drift = np.column_stack([truth[f"drift_{a}_dps"] for a in AXES])
    held = px4_published_index(recording.time_s, recording.temp_c)
    np.testing.assert_allclose(firmware["PX4-cubic"]["drift_error_dps"],
                               block_rmse(recording.time_s, drift[held] - true_drift, 60.0), rtol=1e-6)
    assert firmware["PX4-cubic"]["drift_error_dps"] != per_sample["PX4-cubic"]["drift_error_dps"]


def _refused(script: str, *args: str) -> str:
    import subprocess
    import sys

    from conftest import ROOT

    failed = subprocess.run([sys.executable, str(ROOT / "scripts" / script), *args], capture_output=True, text=True,
                            cwd=ROOT, timeout=300)
    assert failed.returncode == 2, (script, failed.stderr)
    lines = failed.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in failed.stderr, failed.stderr
    return lines[0]


def test_export_refuses_a_bad_fit_in_one_line(tmp_path):
    line = _refused("export.py", f"model={tmp_path}", f"output={tmp_path}/x.params", "fit=chebyshev",
                    f"hydra.run.dir={tmp_path}/run")
    assert "fit must be one of px4, difference" in line, line


@pytest.mark.slow
def test_table_refuses_a_bad_schedule_setting_in_one_line(tmp_path):
    line = _refused("table.py", f"input={tmp_path}/none.csv", "px4.firmware_schedule=sometimes",
                    f"hydra.run.dir={tmp_path}/run")
    assert "px4.firmware_schedule" in line, line
