"""Equivalent explanations, run-level effects and what to record next (issue 12).

Fast tests check the statistics on synthetic arrays (ties, pseudo-runs, the design advice); the
slow ones run the diagnosis on simulated campaigns: clean runs with turn-on biases (the answer is
``run_offset`` alone) and two orientations with g-sensitivity (``run_offset`` with the orientation
columns as its alternatives, and the report asks for the run that would separate them).
"""
import json
from pathlib import Path

import numpy as np
import pytest

from gyronet.analysis.diagnose import screen
from gyronet.analysis.diagnose.advice import (advice_lines, alternatives_advice, orientation_label, record_advice,
                                             runs_advice)
from gyronet.analysis.diagnose.choose import complexity, tie_groups
from gyronet.analysis.diagnose.runlevel import RunCandidate, dealt_labels, run_candidates, screen_runs
from gyronet.model.rbf import RBFNet
from gyronet.sim import first_order_lag, simulate, write_simulation


# ------------------------------------------------------------------------------------------ ties

def _tied(seed: int):
    """A basis, a target that follows ``signal``, and three candidates: the signal as measured, the
    same signal through a short lag (a derived copy), and an unrelated smooth series."""
    rng = np.random.default_rng(seed)
    n = 800
    t = np.linspace(0, 1, n)
    basis = np.column_stack([np.sin(2 * np.pi * k * t) for k in (1, 2)])
    signal = first_order_lag(rng.standard_normal(n), 1.0, 20.0) * 5
    target = np.outer(signal, [0.3, -0.2, 0.1]) + 0.05 * rng.standard_normal((n, 3))
    lagged = first_order_lag(signal, 1.0, 0.5)
    other = first_order_lag(rng.standard_normal(n), 1.0, 20.0) * 5
    specs = [{"kind": "lag", "source": "humidity_pct", "tau_s": 60.0},  # a lag of some column: derived
             {"kind": "column", "source": "board_temp_c", "tau_s": 0.0},  # measured, as it is
             {"kind": "column", "source": "vdd_v", "tau_s": 0.0}]
    candidates = np.column_stack([lagged, signal, other])
    fold = (np.arange(n) // 20) % 5
    return basis, target, candidates, fold, specs


def test_equivalent_candidates_are_grouped_and_the_simplest_is_chosen():
    basis, target, candidates, fold, specs = _tied(0)
    result = screen(basis, target, candidates, fold, np.zeros(len(target), int), ["lag", "raw", "other"], specs,
                    n_shifts=99)
    passing = result.passing(0.01, 0.1)
    assert set(passing.tolist()) >= {0, 1}
    groups = tie_groups(result, passing)
    # the measured column and its lagged copy explain the same: one group, the column first,
    # whichever scored a hair higher; the unrelated column is not in it
    assert groups[0][:2] == [1, 0]
    assert 2 not in groups[0]
    # the noise is measured, not assumed: far apart scores are not within it
    assert result.tie_noise(1, np.array([2]))[0] < result.score[1] - result.score[2]


def test_complexity_orders_measured_before_derived_and_no_lag_before_a_lag():
    order = sorted([{"kind": "lag", "source": "temp_c", "tau_s": 1200.0},
                    {"kind": "column", "source": "board_temp_c", "tau_s": 300.0},
                    {"kind": "time"},
                    {"kind": "hysteresis", "source": "temp_c", "width": 2.0},
                    {"kind": "column", "source": "board_temp_c", "tau_s": 0.0}], key=complexity)
    assert order[0] == {"kind": "column", "source": "board_temp_c", "tau_s": 0.0}
    assert order[1] == {"kind": "time"}
    # of one free parameter, a recording column through a lag before what is derived from the temperature
    assert order[2] == {"kind": "column", "source": "board_temp_c", "tau_s": 300.0}
    assert order[3]["kind"] == "hysteresis" and order[-1] == {"kind": "lag", "source": "temp_c", "tau_s": 1200.0}


# ------------------------------------------------------------------------------------- run level

def test_a_deal_of_pieces_keeps_every_run_s_size_and_each_piece_whole():
    run = np.repeat([0, 1, 2], 120)
    position = np.tile(np.linspace(0, 1, 120), 3)
    labels = dealt_labels(run, position, 12, np.random.default_rng(0))
    assert (np.bincount(labels) == 120).all()
    piece = run * 12 + np.minimum((position * 12).astype(int), 11)
    assert all(len(set(labels[piece == k])) == 1 for k in range(36))
    assert (labels != run).any()


def _campaign(seed: int, offsets: np.ndarray, n_runs: int = 3, n: int = 300):
    rng = np.random.default_rng(seed)
    run = np.repeat(np.arange(n_runs), n)
    position = np.tile(np.linspace(0, 1, n), n_runs)
    basis = np.column_stack([np.sin(2 * np.pi * position * k + run) for k in (1, 2)])
    # a slow wander within each run that no candidate explains, and white noise
    # (stationary from the first row: the lag's start-up transient would be an offset per run)
    wander = np.concatenate([first_order_lag(rng.standard_normal(n + 300), 1.0, 5.0)[300:] for _ in range(n_runs)])
    wander /= wander.std()
    target = np.outer(wander, [1.0, 0.5, 0.2]) + 0.1 * rng.standard_normal((n * n_runs, 3)) + offsets[run]
    fold = np.concatenate([(np.arange(n) // 15) % 5 for _ in range(n_runs)])
    return basis, target, fold, run, position


def test_a_per_run_offset_passes_and_a_wander_within_runs_does_not():
    candidates = run_candidates({}, {}, 3)
    basis, target, fold, run, position = _campaign(0, np.array([[0.5, 0, 0], [-0.4, 0.3, 0], [0, -0.3, 0]]))
    found = screen_runs(basis, None, target, fold, run, position, candidates, n_shifts=99)
    assert found.passing(0.05, 0.1).tolist() == [0]
    hits = 0
    for seed in range(20):
        basis, target, fold, run, position = _campaign(100 + seed, np.zeros((3, 3)))
        hits += int(screen_runs(basis, None, target, fold, run, position, candidates, n_shifts=49,
                                seed=seed).p_value.min() <= 0.05)
    assert hits <= 4  # binomial(20, 0.05): P(X > 4) < 2 %


def test_run_level_columns_are_those_constant_within_runs():
    means = {"acc_z_g": np.array([-1.0, 0.0]), "mag_x_ut": np.array([20.0, 22.0]), "acc_x_g": np.array([0.0, 1e-4])}
    spread = {"acc_z_g": np.array([1e-3, 1e-3]), "mag_x_ut": np.array([3.0, 3.0]), "acc_x_g": np.array([1e-3, 1e-3])}
    found = run_candidates(means, spread, 2)
    assert [c.spec["kind"] for c in found] == ["run_offset", "column"]
    assert found[1].spec["source"] == "acc_z_g" and isinstance(found[1], RunCandidate)


# ---------------------------------------------------------------------------------------- advice

def test_the_design_of_the_runs_decides_what_to_record_next():
    two = " ".join(a.record for a in runs_advice(["z_down", "y_down"]))
    assert "the same orientation twice" in two and "a third orientation" in two
    same = runs_advice(["z_up", "z_up", "z_up"])
    assert len(same) == 1 and "another orientation" in same[0].record
    # an orientation recorded twice separates the offset from the orientation: no such advice
    assert not [a for a in runs_advice(["z_down", "z_down", "y_down"]) if "twice" in a.record]
    assert "a second run" in runs_advice(["z_up"])[0].record
    assert orientation_label(np.array([0.01, -0.99, 0.02])) == "y_down"


def test_every_report_ends_with_what_to_record_next():
    time_s = np.arange(0, 3600.0 * 4, 1.0)
    cooling = 20 - time_s / 1200.0
    items = record_advice(time_s, cooling, 1.0, [])
    records = " ".join(a.record for a in items)
    assert "heating as well" in records and "wider range" in records and "accelerometer" in records
    assert "another thermal history" in records  # time and temperature confounded
    assert "board thermistor" in records  # no column to test a second thermal path with
    for logged in (["vdd_v"], ["depth_m", "acc_x_g"], ["board_temp_c"]):  # one there already: not asked for
        assert "board thermistor" not in " ".join(a.record for a in record_advice(time_s, cooling, 1.0, logged))
    # a record that shows everything still gets one item
    lines = advice_lines([])
    assert lines[0] == "## What to record next" and any("another run" in line for line in lines)
    # ties first only where an item decides one; else the order is the cost alone, and the report says so
    assert advice_lines(items)[2].startswith("Cheapest first. **Next: ")
    tie = alternatives_advice([{"kind": "lag", "source": "temp_c", "alternatives": [{"kind": "time", "source": "t"}]}])
    assert advice_lines(items + tie)[2].startswith("What would decide between equivalent explanations first")
    # a column against its own lag: a step of that column held past the lag, not "do not move together"
    own = alternatives_advice([{"kind": "column", "source": "vdd_v", "params": {"tau_s": 0.0},
                                "alternatives": [{"kind": "column", "source": "vdd_v", "params": {"tau_s": 16.0}}]}])
    assert own[0].record == "a run where vdd_v steps and then holds for longer than 16 s, so that its lags part"
    assert "(column of vdd_v (tau_s 16 s))" in own[0].cannot_show


# ------------------------------------------------------------------------------ simulated campaigns

FS_HZ = 0.5


def _runs(tmp_path: Path, orientations, sensor: dict, seed: int = 10) -> list[str]:
    paths = []
    for i, orientation in enumerate(orientations):
        sim = simulate("random", fs_hz=FS_HZ, seed=seed + i, sensor_seed=3, duration_s=5 * 3600, sensor=sensor,
                       orientation=orientation)
        paths.append(str(tmp_path / f"run{i}.csv"))
        write_simulation(sim, paths[-1])
    return paths


def _diagnose_runs(paths, out: Path) -> dict:
    from gyronet.analysis.diagnose import diagnose

    model = lambda n: RBFNet(n, 3, 12, rbf_inputs=[0], linear=True, temp_degree=3, clamp=True)  # noqa: E731
    # 99 shifts and deals (p down to 0.01 = alpha), as the slow tests of test_diagnose.py
    return diagnose({"paths": paths, "rate_tau_s": 5.0}, model, out, train_cfg={"progress": False, "max_epochs": 800},
                    options={"n_shifts": 99}, plots=False)


@pytest.mark.slow
def test_clean_runs_with_turn_on_biases_give_a_run_offset_alone(tmp_path):
    paths = _runs(tmp_path, [None, None, None], {"turn_on_bias_dps": 0.03})
    diagnosis = _diagnose_runs(paths, tmp_path / "out")
    assert [e["kind"] for e in diagnosis["effects"]] == ["run_offset"]
    assert json.loads((tmp_path / "out" / "diagnosis.json").read_text()) == diagnosis
    meta = json.loads((tmp_path / "out" / "compensator" / "meta.json").read_text())
    assert set(meta["run_offsets_dps"]) == {"run0", "run1", "run2"}
    report = (tmp_path / "out" / "report.md").read_text()
    assert "## What to record next" in report and "another orientation" in report


@pytest.mark.slow
def test_two_orientations_cannot_separate_orientation_from_run_offset(tmp_path):
    paths = _runs(tmp_path, ["z_down", "y_down"], {"turn_on_bias_dps": 0.01, "g_sensitivity_dps_per_g": 0.05},
                  seed=20)
    diagnosis = _diagnose_runs(paths, tmp_path / "out")
    first = diagnosis["effects"][0]
    assert first["kind"] == "run_offset"
    assert {(a["kind"], a["source"]) for a in first["alternatives"]} == {("column", "acc_z_g"), ("column", "acc_y_g")}
    assert all(a["score"] == pytest.approx(first_score, rel=1e-6) for a in first["alternatives"]
               for first_score in [first["alternatives"][0]["score"]])
    report = (tmp_path / "out" / "report.md").read_text()
    assert "cannot separate them" in report
    assert "the same orientation twice" in report and "a third orientation (e.g. x_down)" in report


def test_a_campaign_too_short_for_the_test_says_no_effect_can_be_shown(tmp_path):
    """With n deals the smallest p is 1 / (n + 1): above alpha, "no effect found" would claim what was not tested."""
    from gyronet.analysis.diagnose.runs_report import write_runs_report

    rmse = {"val_rmse_dps": {"x": 0.01, "y": 0.01, "z": 0.01}}
    diagnosis = {"baseline": rmse, "final": rmse, "effects": []}
    runs = [{"name": "a", "orientation": "z_down"}, {"name": "b", "orientation": "z_down"}]
    for deals, says in ((97, "No effect can be shown"), (999, "No effect found")):
        details = {"runs": runs, "options": {"alpha": 0.01},
                   "rounds": [{"n_shifts": deals, "null_max_quantile": 0.7, "candidates": [], "tried": []}]}
        write_runs_report(tmp_path, diagnosis, details, ["z_down", "z_down"], [])
        assert says in (tmp_path / "report.md").read_text()


def test_a_report_names_an_effect_s_parameters_in_words(tmp_path):
    """report.md printed Python dicts: "`run_offset` of `run` {'n_free': 0}"."""
    from gyronet.analysis.diagnose.runs_report import write_runs_report

    rmse = {"val_rmse_dps": {"x": 0.01, "y": 0.01, "z": 0.01}}
    effect = {"kind": "run_offset", "source": "run", "params": {"n_free": 0}, "axes": ["x"], "evidence": "E.",
              "alternatives": [{"kind": "column", "source": "acc_y_g", "params": {"tau_s": 0.0}, "score": 1.39},
                               {"kind": "column", "source": "depth_m", "params": {"tau_s": 389.0}, "score": 1.38}]}
    details = {"runs": [{"name": "a", "orientation": "z_down"}, {"name": "b", "orientation": "y_down"}],
               "options": {"alpha": 0.01}, "rounds": []}
    diagnosis = {"baseline": rmse, "final": rmse, "effects": [effect]}
    write_runs_report(tmp_path, diagnosis, details, ["z_down", "y_down"], [])
    report = (tmp_path / "report.md").read_text()
    assert "### 1. `run_offset` of `run`, axes x" in report and "{" not in report
    assert "`column` of `acc_y_g` (score 1.39); `column` of `depth_m` (tau_s 389) (score 1.38)" in report


def test_a_campaign_report_shows_its_figures(tmp_path):
    """diagnose.md promises the residual before and after as figures; a campaign wrote none."""
    from gyronet.analysis.diagnose import diagnose

    paths = []
    for i in range(2):
        sim = simulate("random", fs_hz=FS_HZ, seed=40 + i, sensor_seed=3, duration_s=2 * 3600,
                       sensor={"turn_on_bias_dps": 0.03})
        paths.append(str(tmp_path / f"run{i}.csv"))
        write_simulation(sim, paths[-1])
    model = lambda n: RBFNet(n, 3, 6, rbf_inputs=[0], linear=True, temp_degree=3, clamp=True)  # noqa: E731
    diagnose({"paths": paths, "rate_tau_s": 2.5}, model, tmp_path / "out",
             train_cfg={"progress": False, "max_epochs": 60}, options={"n_shifts": 19, "max_effects": 1})
    report = (tmp_path / "out" / "report.md").read_text()
    assert "## Figures" in report
    assert "in the dT/dt tracker's 2.5 s" in report  # the model's tracker, not the advice's 5 s default
    for name in ("residual_by_run.png", "residual_vs_temperature.png"):
        assert f"![{name}]({name})" in report
        assert (tmp_path / "out" / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
