"""The survey: the wider sensor distribution draws what it says, and scripts/survey.py writes its table.

The figures are the lead's full run's business (docs/results/survey.md); here two sensors on tiny 1 Hz
histories with a few training steps check the command end to end, in this process (``runpy``, as
``python scripts/survey.py`` runs it), its resume, and its one-line errors.
"""
import dataclasses
import json
import re
import runpy
import sys
from pathlib import Path

import numpy as np
import pytest

from gyronet.errors import GyronetError
from gyronet.sim import draw_sensor, simulate
from gyronet.sim.sensor import SURVEY_FIELDS, SensorModel
from gyronet.sim.survey_sensor import SURVEY_RANGES
from gyronet.analysis.survey import summarize, to_markdown
from gyronet.figures.plots import survey_figure
from gyronet.analysis.survey.scoring import turn_on_bias
from gyronet.analysis.survey.table import error_bar_arrays
from gyronet.recordings.data import load_truth

from conftest import ROOT

SEEDS = range(40)
AXES = ("x", "y", "z")


def inside(values, name: str) -> bool:
    low, high = SURVEY_RANGES[name]
    return bool(np.all((np.asarray(values) >= low) & (np.asarray(values) <= high)))


def test_the_survey_distribution_draws_its_ranges_and_is_wider_than_the_default():
    sensors = [draw_sensor(s, distribution="survey") for s in SEEDS]
    for seed, m in zip(SEEDS, sensors):
        base = draw_sensor(seed)
        assert inside(m.knee_width_c, "knee_width_c")
        on = np.flatnonzero(m.knee2_dps)
        assert len(on) == 1, "a second knee on exactly one axis"
        axis = on[0]
        swing = dataclasses.replace(m, coupling=np.zeros((3, 3))).swing_dps()
        np.testing.assert_allclose(swing, base.swing_dps(), rtol=1e-9)  # today's swing, before the coupling
        share = abs(m.knee2_dps[axis]) / swing[axis]
        assert 0.03 < share < 0.2  # 6-14 % drawn, then the axis rescaled by a few %
        assert inside(m.knee2_width_c[axis], "knee2_width_c") and inside(m.knee2_c[axis], "knee2_c")
        assert abs(m.knee2_c[axis] - m.knee_c[axis]) >= SURVEY_RANGES["knee2_min_separation_c"][0]
        assert inside(np.abs(m.rate_gain_deg_per_c), "rate_gain_abs_deg_per_c")
        assert inside(np.abs(m.rate_temp_gain_deg_per_c) / np.abs(m.rate_gain_deg_per_c), "rate_temp_gain_share")
        assert inside(m.axis_lag_s, "axis_lag_s") and inside(m.turn_on_bias_std_dps, "turn_on_bias_std_dps")
        assert np.all(np.diag(m.coupling) == 0) and inside(np.abs(m.coupling), "coupling_abs")
        np.testing.assert_array_equal(m.offset_dps, base.offset_dps)  # the same sensor, made harder
    # wider than today's: knees under 4 degC wide and dT/dt gains over 12 deg/degC both occur
    assert min(m.knee_width_c.min() for m in sensors) < 3.0
    assert max(np.abs(m.rate_gain_deg_per_c).max() for m in sensors) > 18.0
    with pytest.raises(GyronetError, match="unknown sensor distribution 'wide'"):
        draw_sensor(0, distribution="wide")


def test_the_default_distribution_is_unchanged():
    for seed in (0, 3):
        m = draw_sensor(seed)
        assert not set(SURVEY_FIELDS) & set(m.to_dict()), "old sensors' truth metadata keeps its keys"
        for name in SURVEY_FIELDS:
            value = getattr(m, name)
            assert np.array_equal(value, SensorModel.__dataclass_fields__[name].default_factory())
        sim = simulate(profile="cycle", fs_hz=1, seed=1, sensor_seed=seed, duration_s=3000)
        assert "turn_on_bias_x_dps" not in sim.truth and "sensor_distribution" not in sim.meta


def test_second_knee_coupling_and_axis_lag_enter_the_drift_as_written():
    m = draw_sensor(5, distribution="survey")
    temp_c = np.linspace(-40, 60, 201)
    rate = np.full_like(temp_c, 1 / 60)
    plain = dataclasses.replace(m, coupling=np.zeros((3, 3)), axis_lag_s=np.zeros(3))
    uncoupled = plain.drift_dps(temp_c, rate)
    # drift += C (drift - offset)
    np.testing.assert_allclose(m.drift_dps(temp_c, rate), uncoupled + (uncoupled - m.offset_dps) @ m.coupling.T)
    no_knee2 = dataclasses.replace(plain, knee2_dps=np.zeros(3))
    axis = int(np.flatnonzero(m.knee2_dps)[0])
    expected = m.knee2_dps[axis] * np.tanh((temp_c - m.knee2_c[axis]) / m.knee2_width_c[axis])
    np.testing.assert_allclose(uncoupled[:, axis] - no_knee2.drift_dps(temp_c, rate)[:, axis], expected, atol=1e-12)
    # an axis lag: on a ramp the axis sees an older, lower temperature
    time_s = np.arange(4000.0)
    ramp_c = 20 + time_s / 60
    lagged = dataclasses.replace(plain, axis_lag_s=np.array([30.0, 0.0, 0.0]))
    drift = lagged.history_drift_dps(time_s, ramp_c, 1.0)
    late = slice(1000, None)
    np.testing.assert_allclose(drift[late, 1], plain.history_drift_dps(time_s, ramp_c, 1.0)[late, 1])
    decay = np.exp(-1 / 30.0)
    seen_c = 20 + (time_s - decay / (1 - decay)) / 60  # the sampled 30 s lag, settled on a ramp: 29.5 s behind
    np.testing.assert_allclose(drift[late, 0], plain.drift_dps(seen_c, np.full_like(seen_c, 1 / 60))[late, 0],
                               atol=1e-9)


def test_a_survey_sensor_gets_a_new_turn_on_bias_each_run_and_the_truth_adds_up():
    runs = [simulate(profile="constant", fs_hz=1, seed=seed, sensor_seed=2, duration_s=600,
                     sensor={"distribution": "survey"}) for seed in (1, 2)]
    biases = [np.array(sim.run["turn_on_bias_dps"]) for sim in runs]
    assert not np.allclose(biases[0], biases[1])
    # another sensor with the same run seed does not share the draw (its z-scores are its own)
    other = simulate(profile="constant", fs_hz=1, seed=1, sensor_seed=3, duration_s=600, sensor={"distribution": "survey"})
    z_scores = [np.array(s.run["turn_on_bias_dps"]) / s.sensor.turn_on_bias_std_dps for s in (runs[0], other)]
    assert not np.allclose(z_scores[0], z_scores[1])
    sim = runs[0]
    assert sim.meta["sensor_distribution"] == "survey"
    for a in AXES:
        total = sim.truth[f"true_rate_{a}_dps"] + sim.truth[f"drift_{a}_dps"] + sim.truth[f"noise_{a}_dps"]
        np.testing.assert_allclose(sim.recording[f"gyro_{a}_dps"], total, atol=1e-12)


def test_each_survey_sensor_has_its_own_noise_on_the_shared_history(tmp_path):
    """One noise draw for all would make the start-up offset's noise one constant shared by the survey."""
    from gyronet.analysis.survey.sensor_run import History, SurveySpec, simulate_history
    from gyronet.recordings.data import load_truth

    spec = SurveySpec(methods={}, fs_hz=1.0)
    history = History("random", 2, duration_s=1800)
    truths = []
    for sensor_seed in (0, 1):
        (tmp_path / str(sensor_seed)).mkdir()
        truths.append(load_truth(simulate_history(tmp_path / str(sensor_seed), "check", sensor_seed, history, spec)).columns)
    assert np.array_equal(truths[0]["chamber_temp_c"], truths[1]["chamber_temp_c"])
    assert not np.allclose(truths[0]["noise_x_dps"], truths[1]["noise_x_dps"])


def test_a_history_s_own_simulate_settings_change_that_record_alone(tmp_path):
    """A training record quieter than the one scored: the noise is merged per key over the survey's, the drift kept."""
    from gyronet.analysis.survey.sensor_run import History, SurveySpec, simulate_history
    from gyronet.recordings.data import load_recording, load_truth

    spec = SurveySpec(methods={}, fs_hz=1.0, simulate={"noise": {"lsb_dps": 0.0, "arw_deg_rthr": 3.0}})
    plain = History("random", 2, duration_s=1800)
    quiet = History("random", 2, duration_s=1800, simulate={"noise": {"arw_deg_rthr": 1.5}})
    truths, steps = {}, {}
    for name, history in (("plain", plain), ("quiet", quiet)):
        (tmp_path / name).mkdir()
        path = simulate_history(tmp_path / name, "train", 0, history, spec)
        truths[name] = load_truth(path).columns
        steps[name] = load_recording(path).gyro_dps[:, 0] / 0.00875  # in the default quantisation's steps
    np.testing.assert_array_equal(truths["quiet"]["drift_x_dps"], truths["plain"]["drift_x_dps"])
    ratio = np.std(np.diff(truths["quiet"]["noise_x_dps"])) / np.std(np.diff(truths["plain"]["noise_x_dps"]))
    assert 0.45 < ratio < 0.55  # half the white noise
    for name in steps:  # the survey's lsb_dps=0 kept under the record's own noise setting: not on the default grid
        assert np.abs(steps[name] - np.round(steps[name])).max() > 0.1, name
    assert spec.fingerprint() != SurveySpec(methods={}, fs_hz=1.0, simulate=spec.simulate, train_history=quiet).fingerprint()


def test_a_perfect_drift_model_deployed_with_a_start_up_offset_scores_the_floor():
    """The deployed floor has the window's noise in it: else a perfect model would score above 1."""
    from gyronet.analysis.survey.scoring import deployed_floor_truth
    from gyronet.training.evaluate import residual_report

    sim = simulate("random", 1.0, seed=2, sensor_seed=5, duration_s=7200, sensor={"distribution": "survey"})
    truth, time_s = sim.truth, sim.recording["time_s"]
    keep = time_s >= time_s[0] + 600
    rate = np.column_stack([sim.recording[f"gyro_{a}_dps"] - truth[f"drift_{a}_dps"] for a in AXES])
    true_rate = np.column_stack([truth[f"true_rate_{a}_dps"] for a in AXES])
    deployed = rate - (rate - true_rate)[~keep].mean(0)  # the offset of a still window, the true rate removed
    kept = {k: v[keep] for k, v in truth.items()}
    on_deployed_floor = residual_report(time_s[keep], deployed[keep], deployed_floor_truth(truth, keep))
    on_plain_floor = residual_report(time_s[keep], deployed[keep], kept)
    assert [on_deployed_floor["ratio_to_floor"][a] for a in AXES] == pytest.approx([1, 1, 1], abs=1e-12)
    assert all(on_plain_floor["ratio_to_floor"][a] != pytest.approx(1, abs=1e-4) for a in AXES)


TINY = ["n_sensors=2", "jobs=1", "fs_hz=1", "startup_s=300", "progress=false",
        'train_overrides=["train.max_epochs=40","train.patience=20"]',
        "+train_history.profile_options.dwell_s=300", "+train_history.profile_options.rate_c_per_min=4",
        "check_history.duration_s=7200"]


def run_survey(monkeypatch, *args: str) -> int:
    """``python scripts/survey.py ARGS`` in this process: its exit status."""
    monkeypatch.setattr(sys, "argv", ["scripts/survey.py", *args])
    monkeypatch.delenv("HYDRA_FULL_ERROR", raising=False)
    try:
        runpy.run_path(str(ROOT / "scripts" / "survey.py"), run_name="__main__")
    except SystemExit as stop:
        return stop.code if isinstance(stop.code, int) else 1
    return 0


def test_the_survey_command_writes_its_table_and_resumes(tmp_path, monkeypatch, capsys):
    out = tmp_path / "survey"
    assert run_survey(monkeypatch, *TINY, f"hydra.run.dir={out}") == 0
    said = (out / "survey.log").read_text() + capsys.readouterr().err
    assert "survey table" in said and "error bar: calibrated" not in said  # train.py's advice, not the survey's
    table = (out / "survey.md").read_text()
    rows = [line for line in table.splitlines() if line.startswith("| ") and "---" not in line]
    assert rows[0] == "| method | scored | median | 90th percentile | worst (sensor) |"
    names = ["gyronet"] * 3 + ["PX4-cubic"] * 3 + ["PX4-script"] * 3 + ["form-bound"] * 3  # bound: true by default
    assert [r.split(" | ")[0].strip("| ") for r in rows[1:]] == names
    for row in rows[1:]:
        assert re.search(r"\| \d+\.\d\d \| \d+\.\d\d \| \d+\.\d\d \([01]\) \|$", row), row
    assert "gyronet / PX4-cubic, worst axis, as deployed: worst sensor" in table
    assert "Sensors that miss a goal: " in table
    assert re.search(r"gyronet's error bar as deployed \(2 sensors\): \d+ % of 60 s blocks within 1 sigma", table)
    assert re.search(r"Sensor-axes below the range a bar that holds gives on 9 runs in 10 .*: \d of 6\.", table)
    everything = json.loads((out / "survey.json").read_text())
    sensors = everything["sensors"]
    assert [s["sensor_seed"] for s in sensors] == [0, 1]
    # the table is the sensors' figures: recomputed from the per-sensor results it matches
    assert to_markdown(summarize(sensors, "gyronet", "PX4-cubic"), everything["settings"]) == table
    for s in sensors:
        for method in ("gyronet", "PX4-cubic", "PX4-script"):
            scores = s["methods"][method]
            assert all(np.isfinite(scores[v]).all() and min(scores[v]) > 0.5 for v in ("deployed", "as_is"))
        bar = s["methods"]["gyronet"]["error_bar"]  # the bar as deployed: coverage and the recalibration check
        assert all(0.0 <= w <= 1.0 for w in bar["within_1_sigma"]) and min(bar["worst_hour_rms_ratio"]) > 0
        assert all(0.0 <= low <= high <= 1.0 for low, high in bar["calibrated_range"])
        # few steps and a tiny record, but trained on its own history the network still beats the cubic
        assert max(s["methods"]["gyronet"]["deployed"]) < max(s["methods"]["PX4-cubic"]["deployed"])
        # the simulator's own formula, its coefficients fitted: better than both
        assert max(s["methods"]["form-bound"]["deployed"]) < max(s["methods"]["gyronet"]["deployed"])
    lines = (out / "survey_sensors.csv").read_text().splitlines()
    assert len(lines) == 3 and lines[0].startswith("sensor_seed,sharpest_knee_c,max_rate_gain_deg_per_c,max_axis_lag_s,")
    assert lines[0].split(",").index("gyronet:deployed:worst") == 7
    assert [float(v) for v in lines[1].split(",")[4:8]] == pytest.approx(sensors[0]["methods"]["gyronet"]["deployed"]
                                                                           + [max(sensors[0]["methods"]["gyronet"]["deployed"])], abs=1e-4)
    assert not list(out.glob("sensors/*/*.csv")), "records removed once scored (keep_records=false)"
    assert (out / "survey.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    # a sensor that failed is counted and named, and left out of the figures
    failed = summarize([*sensors, {"sensor_seed": 7, "error": "check.csv: nothing left to score"}], "gyronet", "PX4-cubic")
    assert failed["n_sensors"] == 2 and failed["rows"] == summarize(sensors, "gyronet", "PX4-cubic")["rows"]
    assert "Failed, left out of every figure above (1): 7 (check.csv: nothing left to score)." in to_markdown(
        failed, everything["settings"])
    with pytest.raises(GyronetError, match="every sensor of the survey failed; the first: boom"):
        summarize([{"sensor_seed": 7, "error": "boom"}], "gyronet", "PX4-cubic")
    # no reference (reference=null, a survey of gyronet alone): the same figures, no goal against another method
    alone = summarize(sensors, "gyronet", None)
    assert alone["vs_reference"] is None and set(alone["met"]) == {"p90", "worst"}
    assert alone["rows"] == summarize(sensors, "gyronet", "PX4-cubic")["rows"]
    assert "better than" not in to_markdown(alone, everything["settings"])
    assert all("/PX4" not in m and "/None" not in m for missed in alone["misses"].values() for m in missed)
    # resumed: run again, both sensors are read back as they were (no new training), the same table
    results = sorted(out.glob("sensors/*/result.json"))
    stamps = [p.stat().st_mtime_ns for p in results]
    capsys.readouterr()
    assert run_survey(monkeypatch, *TINY, f"hydra.run.dir={out}") == 0
    assert [p.stat().st_mtime_ns for p in results] == stamps
    assert (out / "survey.md").read_text() == table
    assert "2 of 2 sensors reused" in (out / "survey.log").read_text()


def test_the_survey_figure_draws_each_method_s_sorted_worst_axis_and_the_error_bar_s_misses():
    def sensor(seed, ours, cubic, within, low):
        bar = {"within_1_sigma": within, "calibrated_range": [[low, 0.95]] * 3, "worst_hour_rms_ratio": [1.0] * 3}
        return {"sensor_seed": seed, "methods": {
            "gyronet": {"deployed": ours, "turn_on_removed": [v - 0.02 for v in ours], "as_is": ours, "error_bar": bar},
            "PX4-cubic": {"deployed": cubic, "turn_on_removed": cubic, "as_is": cubic}}}

    results = [sensor(0, [1.2, 1.1, 1.0], [30, 40, 20], [0.7, 0.2, 0.9], 0.3),
               sensor(1, [1.05, 1.0, 1.08], [25, 10, 5], [0.65, 0.6, 0.5], 0.1), {"sensor_seed": 2, "error": "boom"}]
    fig = survey_figure(results, "gyronet", {"p90_max": 1.15, "worst_max": 1.3},
                        error_bar_arrays(results, "gyronet")[1:3], (0.6, 0.76))
    goals, every, bar = fig.axes
    ours, truth_bias, staircase = goals.get_lines()
    assert list(ours.get_ydata()) == [1.08, 1.2, 1.2] and list(truth_bias.get_ydata()) == pytest.approx([1.06, 1.18, 1.18])
    assert list(staircase.get_ydata()) == [1.15, 1.15, 1.3, 1.3]
    assert "PX4-cubic" not in [line.get_label() for line in goals.get_lines()], "far off the goals: beside them"
    assert list(every.get_lines()[2].get_ydata()) == [25, 40, 40] and every.get_yscale() == "log"
    assert [text.get_text() for text in bar.get_legend().get_texts()][-1] == "below that range (1)"  # 0.2 < 0.3
    assert bar.get_title() == "gyronet's error bar as deployed: 59 % pooled"
    # near the goals alone: no log panel; no error bar: no bar panel
    for r in results[:2]:
        del r["methods"]["PX4-cubic"], r["methods"]["gyronet"]["error_bar"]
    assert error_bar_arrays(results, "gyronet") is None
    assert len(survey_figure(results, "gyronet", {"p90_max": 1.15, "worst_max": 1.3}, None, (0.6, 0.76)).axes) == 1


def test_more_training_histories_train_every_method_as_a_campaign(tmp_path, monkeypatch):
    out = tmp_path / "campaign"
    second = "{profile:cycle,seed:3,profile_options:{dwell_s:300,rate_c_per_min:4}}"
    assert run_survey(monkeypatch, *TINY[1:], "n_sensors=1", f"more_train_histories=[{second}]",
                      "keep_records=true", f"hydra.run.dir={out}") == 0
    folder = out / "sensors" / "sensor_0000"
    for method in ("gyronet", "PX4-cubic", "PX4-script"):  # each trained on both power-ups, by run
        runs = json.loads((folder / method / "compensator" / "meta.json").read_text())["runs"]
        assert [Path(r["path"]).name for r in runs] == ["train.csv", "train2.csv"]
    result = json.loads((folder / "result.json").read_text())
    biases = [turn_on_bias(load_truth(folder / f"{name}.csv").columns) for name in ("check", "train", "train2")]
    assert result["turn_on_difference_dps"] == pytest.approx(biases[0] - (biases[1] + biases[2]) / 2, abs=1e-12)
    assert abs(biases[1] - biases[2]).min() > 1e-4, "each power-up its own turn-on bias"
    settings = json.loads((out / "survey.json").read_text())["settings"]
    assert settings["train"].count("profile=cycle") == 2


def test_the_bound_alone_needs_no_training(tmp_path, monkeypatch):
    """methods=null: form-bound on the same records, in seconds a sensor (docs/results/survey.md: what one cycle holds)."""
    out = tmp_path / "bound"
    assert run_survey(monkeypatch, *TINY, "methods=null", "ours=form-bound", "reference=null",
                      f"hydra.run.dir={out}") == 0
    sensors = json.loads((out / "survey.json").read_text())["sensors"]
    assert [list(s["methods"]) for s in sensors] == [["form-bound"]] * 2
    assert not list(out.glob("sensors/*/*/compensator")), "nothing trained"
    assert "Goals for form-bound, as deployed" in (out / "survey.md").read_text()


def test_a_sensor_another_process_is_running_is_refused_in_one_line(tmp_path):
    """A stopped survey's workers finished their sensors while a second survey in the same folder ran them too."""
    fcntl = pytest.importorskip("fcntl")
    from gyronet.analysis.survey import SurveySpec, run_sensor

    folder = tmp_path / "sensor_0007"
    folder.mkdir()
    with open(folder / ".lock", "w") as held:
        fcntl.flock(held, fcntl.LOCK_EX | fcntl.LOCK_NB)
        with pytest.raises(GyronetError, match="another process is running this sensor"):
            run_sensor(7, SurveySpec(methods={}), folder)
    assert not list(folder.glob("*.csv")) and not (folder / "result.json").exists()


@pytest.mark.parametrize("args, expected", [
    (["more_train_histories=[5]"], "more_train_histories: each item is a history {profile, seed, "),
    (["more_train_histories=[{seeds:3}]"], "more_train_histories: History.__init__() got an unexpected keyword"),
    (["n_sensors=0"], "n_sensors must be at least 1"),
    (["jobs=0"], "jobs must be a whole number >= 1"),
    (["+methods.mine=nope"], "methods: no conf/model/nope.yaml"),
    (["reference=PX4"], "reference=PX4 is not one of the methods"),
    (["distribution=wide"], "unknown sensor distribution 'wide'"),
    (["methods=null", "bound=false"], "nothing to score: no methods and bound=false"),
])
def test_bad_options_are_one_line(tmp_path, monkeypatch, capsys, args, expected):
    n = [] if args[0].startswith("n_sensors") else ["n_sensors=1"]
    code = run_survey(monkeypatch, *TINY[1:], *n, *args, f"hydra.run.dir={tmp_path}")
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert code == 2 and len(err) == 1 and err[0].startswith("error: ") and expected in err[0], err


def test_a_killed_worker_is_one_line_that_says_how_to_resume(tmp_path, monkeypatch):
    """The kernel's OOM killer took a worker after 96 sensors: the command said so with a traceback."""
    import joblib
    from joblib.externals.loky.process_executor import TerminatedWorkerError

    from gyronet.analysis.survey import SurveySpec, survey

    class Killed:
        def __init__(self, *args, **kwargs):
            pass

        def __call__(self, tasks):
            raise TerminatedWorkerError("A worker process managed by the executor was unexpectedly terminated.")

    monkeypatch.setattr(joblib, "Parallel", Killed)
    spec = SurveySpec(methods={"PX4-cubic": {}})
    with pytest.raises(GyronetError, match=r"^a survey worker process was killed .* run the same command again") as err:
        survey([0, 1], spec, tmp_path, jobs=2, progress=False)
    assert "\n" not in str(err.value)
