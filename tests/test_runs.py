"""Several runs in one training: per-run features and blocks, leave-one-run-out, run offsets, the bundle's runs."""
import copy
import json
import logging
import subprocess
import sys

import numpy as np
import pytest
import torch

from gyronet.model.baselines import LinearFeatures, TempPolynomial
from gyronet.recordings.data import load_recording
from gyronet.training.dataset import featurize
from gyronet.errors import GyronetError
from gyronet.model.features import PAPER_FEATURES
from gyronet.model.rbf import RBFNet
from gyronet.training.run_offsets import RunOffsets
from gyronet.training.runs import RunsData, fit_by_run, load_runs, training_data
from gyronet.training.train import fit

from conftest import CATS_RUNS, ROOT, needs_cats


def _two_runs_data(**kw):
    """Three synthetic runs sharing one cubic in temperature, each with its own constant offset."""
    rng = np.random.default_rng(0)
    offsets = np.array([[0.05, -0.02, 0.01], [-0.03, 0.04, 0.0], [-0.02, -0.02, -0.01]])
    x, y, run = [], [], []
    for k, (low, high) in enumerate([(-10, 30), (0, 40), (-20, 20)]):
        temp = np.linspace(low, high, 400)
        curve = np.column_stack([0.002 * temp, -1e-4 * temp**2, 3e-6 * temp**3])
        x.append(np.column_stack([temp, rng.normal(0, 1e-3, 400), rng.normal(0, 1e-2, 400)]))
        y.append(curve + offsets[k] + rng.normal(0, 1e-4, (400, 3)))
        run.append(np.full(400, k))
    return np.vstack(x), np.vstack(y), np.concatenate(run), offsets


@pytest.mark.parametrize("make", [lambda: TempPolynomial(3), lambda: LinearFeatures(3)])
def test_closed_form_offsets_equal_the_joint_fit_with_dummy_columns(make):
    x, y, run, true_offsets = _two_runs_data()
    xt, yt = torch.as_tensor(x), torch.as_tensor(y)
    model, offsets = make(), RunOffsets(run, 3)
    offsets.fit_closed_form(model, xt, yt)
    values = offsets.values().detach().numpy()
    np.testing.assert_allclose(values.sum(0), 0, atol=1e-12)
    # the same least squares with the dummy columns written out
    basis = model._powers(xt).numpy() if isinstance(model, TempPolynomial) else np.column_stack([x, np.ones(len(x))])
    dummies = np.eye(3)[run][:, 1:]
    coef = np.linalg.lstsq(np.column_stack([basis, dummies]), y, rcond=None)[0]
    joint = np.vstack([np.zeros((1, 3)), coef[-2:]])
    np.testing.assert_allclose(values, joint - joint.mean(0), atol=1e-9)
    fitted = model(xt).numpy() + values[run]
    np.testing.assert_allclose(fitted, np.column_stack([basis, dummies]) @ coef, atol=1e-9)
    if isinstance(model, TempPolynomial):  # the cubic is the truth: the offsets come out as drawn
        np.testing.assert_allclose(values, true_offsets - true_offsets.mean(0), atol=2e-4)


def test_rbf_offsets_are_learnt_by_adam_with_the_model():
    x, y, run, true_offsets = _two_runs_data()

    class Data:  # the parts of a RunsData that fit reads
        pass

    data = Data()
    from gyronet.training.dataset import Blocks

    data.train = Blocks(x, y, np.arange(len(x)) * 10.0)
    data.val = data.train
    data.val_full = (data.train.time_s, x, y)
    data.offsets = RunOffsets(run, 3)
    model = RBFNet(3, 3, 8, rbf_inputs=[0], linear=True, temp_degree=3, clamp=True)
    fit(model, data, max_epochs=200, progress=False)
    np.testing.assert_allclose(data.offsets.values().detach().numpy(), true_offsets - true_offsets.mean(0), atol=3e-3)


def test_features_are_per_run_and_blocks_never_span_runs(paper_csv, cycle_csv):
    runs = load_runs([str(paper_csv), str(cycle_csv)], PAPER_FEATURES)
    fresh = featurize(load_recording(cycle_csv), PAPER_FEATURES)
    np.testing.assert_array_equal(runs[1].features, fresh)  # a fresh extractor, not continued from run 0
    data = RunsData(runs, list(PAPER_FEATURES))
    per_run = [len(r.blocks(10.0)) for r in runs]
    assert len(data.train) == sum(per_run)
    assert np.array_equal(np.bincount(data.train.run), per_run)
    low = min(r.recording.temp_c.min() for r in runs)
    high = max(r.recording.temp_c.max() for r in runs)
    assert data.temp_range_c == (low, high)
    fold = data.holding_out(0)
    assert [r.name for r in fold.train_runs] == ["cycle"] and len(fold.val_full[0]) == len(runs[0].time_s)
    assert fold.temp_range_c == runs[1].temp_range_c


@pytest.mark.parametrize("tau_s", [0.0, -2.0, float("nan")])
def test_rate_tau_s_must_be_positive(paper_csv, tau_s):
    """0 gave a ZeroDivisionError; a negative one diverged the fit with a hint to lower optim.lr."""
    with pytest.raises(GyronetError, match=r"data.rate_tau_s must be > 0 s .*got"):
        training_data(path=str(paper_csv), rate_tau_s=tau_s)


@pytest.mark.parametrize("block_s", [0.0, -10.0, float("nan")])
def test_block_s_must_be_positive(paper_csv, block_s):
    """-10 trained silently on single samples (every one its own block); 0 was a ValueError from np.bincount."""
    with pytest.raises(GyronetError, match=r"data.block_s must be > 0 s .*got"):
        training_data(path=str(paper_csv), block_s=block_s)


@pytest.mark.parametrize("startup_s", [-100.0, float("nan"), float("inf")])
def test_val_startup_s_must_be_a_window(paper_csv, startup_s):
    """-100 was taken as 0 but written to the bundle as -100, so use_startup never widened the bar for the offset."""
    with pytest.raises(GyronetError, match=r"data.val_startup_s must be >= 0 s .*got"):
        training_data(path=str(paper_csv), val_startup_s=startup_s)


def test_training_data_one_or_several_and_clear_errors(paper_csv, cycle_csv):
    assert type(training_data(path=str(paper_csv))).__name__ == "DriftData"
    assert type(training_data(paths=[str(paper_csv)])).__name__ == "DriftData"
    with pytest.raises(GyronetError, match="not both"):
        training_data(path=str(paper_csv), paths=[str(cycle_csv)])
    with pytest.raises(GyronetError, match="no training data"):
        training_data()
    with pytest.raises(GyronetError, match="val_path"):
        training_data(paths=[str(paper_csv), str(cycle_csv)], val_path=str(cycle_csv))
    with pytest.raises(GyronetError, match="twice"):
        training_data(paths=[str(paper_csv), str(paper_csv)])


def test_a_copy_of_a_run_under_another_name_is_refused(paper_csv, cycle_csv, tmp_path):
    """Its fold would be scored on the very samples it was trained on, and look better than any held-out run."""
    import shutil

    from gyronet.recordings.data import load_recording, write_recording

    copy = shutil.copy(cycle_csv, tmp_path / "copy_of_cycle.csv")
    with pytest.raises(GyronetError, match=f"copy_of_cycle.csv holds the same samples as {cycle_csv}"):
        training_data(paths=[str(paper_csv), str(cycle_csv), str(copy)])
    # re-exported with a column more: the same run
    recording = load_recording(cycle_csv)
    more = write_recording(tmp_path / "more.csv", {**recording.columns, "vdd_v": recording.temp_c * 0 + 3.3},
                           recording.meta, float_format="%.17g")
    with pytest.raises(GyronetError, match="more.csv holds the same samples"):
        training_data(paths=[str(cycle_csv), str(more)])


def test_a_run_too_short_to_score_after_its_start_up_window_is_named(paper_csv, cycle_csv, tmp_path):
    """It failed with numpy's 'Mean of empty slice' and 'no finite validation error', naming no run."""
    from gyronet.recordings.data import load_recording, write_recording

    short = load_recording(cycle_csv).slice(slice(0, 600))  # 300 s at 2 Hz
    path = write_recording(tmp_path / "short.csv", short.columns, short.meta, float_format="%.17g")
    with pytest.raises(GyronetError, match="short.csv: 300 s long; .*val_startup_s=600"):
        training_data(paths=[str(paper_csv), str(path)], val_startup_s=600.0)
    training_data(paths=[str(paper_csv), str(path)], val_startup_s=0.0)  # scored whole: enough


def test_leave_one_run_out_mixes_every_start_by_the_held_out_runs_and_trains_the_final_model_on_all(
        paper_csv, cycle_csv, caplog, monkeypatch):
    """Each start is fitted in each fold and weighted on the held-out runs (demeaned); the bundle is the
    same mixture of the starts trained on every run, run offsets included."""
    from gyronet.training import run_starts
    from gyronet.training.starts import stack_weights

    calls, fit_start = [], run_starts.fit_start  # (start, data, its fit, its offsets' raw values)

    def recorded(start, data, *args, **kwargs):
        figures, fitted, raw = fit_start(start, data, *args, **kwargs)
        calls.append((start.name, data, fitted, raw))
        return figures, fitted, raw

    monkeypatch.setattr(run_starts, "fit_start", recorded)
    data = training_data(paths=[str(paper_csv), str(cycle_csv)], run_offsets=True)
    model = RBFNet(3, 3, 6, rbf_inputs=[0], linear=True, temp_degree=3, clamp=True, validate_init=True,
                   kmeans_members=2)
    with caplog.at_level("INFO", logger="gyronet.training.runs"):
        metrics, folds = fit_by_run(model, data, max_epochs=120, progress=False)
    assert any("starts mixed per axis on the 2 held-out runs" in r.getMessage() for r in caplog.records)
    assert [f["held_out"] for f in folds] == ["paper", "cycle"]
    assert metrics["val/rmse_dps"] == pytest.approx(np.mean([f["val/rmse_dps"] for f in folds]))
    assert metrics["train/steps_ols"] == max(f["train/best_step_ols"] for f in folds)  # one member: its own count
    names = ["kmeans", "ols", "ols_narrow"]
    weights = np.array([[metrics[f"model/{n}_weight_{a}"] for a in "xyz"] for n in names])
    by_fold = [[c for c in calls if c[1].held_out == f] for f in (0, 1)]
    assert [[c[0] for c in fold] for fold in by_fold] == [names, names]
    residuals = [np.concatenate([run_starts.demeaned_residuals(fold[k][2], fold[k][1]) for fold in by_fold])
                 for k in range(3)]
    np.testing.assert_allclose(weights, stack_weights(*residuals))
    final = [c for c in calls if c[1] is data]
    assert [c[0] for c in final] == [n for n, w in zip(names, weights) if w.any()]
    x = torch.as_tensor(data.train.x)
    with torch.no_grad():
        expected = sum(torch.as_tensor(w) * (part(x) + (raw - raw.mean(0))[data.offsets.run])
                       for (_, _, part, raw), w in zip(final, weights[weights.any(1)]))
        torch.testing.assert_close(model(x) + data.offsets(), expected, rtol=0, atol=1e-9)
    # the final model saw both runs: its training box is the union
    assert model.z_low[0] * model.x_std[0] + model.x_mean[0] == pytest.approx(data.train.x[:, 0].min())


def test_a_start_one_fold_cannot_make_is_left_out_of_every_fold(paper_csv, cycle_csv, monkeypatch, caplog):
    """Forward selection needs a wide enough range: a start that fails on one fold's runs is dropped everywhere."""
    from gyronet.model.rbf_init import SelectionError
    from gyronet.training import run_starts

    fit_start = run_starts.fit_start

    def narrow(start, data, *args, **kwargs):
        if start.name == "ols" and data.held_out == 1:
            raise SelectionError("only 9 independent candidate Gaussians, 12 asked for")
        return fit_start(start, data, *args, **kwargs)

    monkeypatch.setattr(run_starts, "fit_start", narrow)
    data = training_data(paths=[str(paper_csv), str(cycle_csv)])
    model = RBFNet(3, 3, 6, rbf_inputs=[0], linear=True, temp_degree=3, clamp=True, validate_init=True,
                   kmeans_members=1)
    with caplog.at_level("INFO", logger="gyronet.training.run_starts"):
        metrics, _ = fit_by_run(model, data, max_epochs=60, progress=False)
    assert "no ols start (only 9 independent" in caplog.text
    assert "model/ols_weight_x" not in metrics and "train/steps_ols" not in metrics
    for a in "xyz":
        assert metrics[f"model/kmeans_weight_{a}"] + metrics[f"model/ols_narrow_weight_{a}"] == pytest.approx(1.0)


def test_with_no_axis_keeping_its_gaussians_the_final_fit_is_least_squares_at_the_levels(
        paper_csv, cycle_csv, monkeypatch, caplog):
    """Levels below the Gaussians are refitted in closed form, so the final fits take one step, not the folds' count,
    and the bundle is the least-squares fit at those levels (with the run offsets) whatever the training did."""
    from gyronet.training import capacity, run_starts

    steps, fit_start = [], run_starts.fit_start

    def recorded(start, data, *args, **kwargs):
        if data.held_out is None:
            steps.append(args[3] if len(args) == 4 else kwargs.get("steps"))
        return fit_start(start, data, *args, **kwargs)

    monkeypatch.setattr(run_starts, "fit_start", recorded)
    monkeypatch.setattr(capacity, "choose", lambda errors, tolerance=0.01: [0, 1, 2])
    data = training_data(paths=[str(paper_csv), str(cycle_csv)], run_offsets=True)
    model = RBFNet(3, 3, 6, rbf_inputs=[0], linear=True, temp_degree=3, clamp=True, validate_init=True,
                   kmeans_members=2, select_capacity=True)
    with caplog.at_level("INFO", logger="gyronet.training.runs"):
        metrics, _ = fit_by_run(model, data, max_epochs=120, progress=False)
    assert steps and set(steps) == {1}
    assert "final fit on every run by least squares" in caplog.text  # not "for 1/1 steps"
    assert [metrics[f"model/level_{a}"] for a in "xyz"] == [0, 1, 2]
    x, y = torch.as_tensor(data.train.x), torch.as_tensor(data.train.y)
    fresh, offsets = copy.deepcopy(model), RunOffsets(data.train.run, 2)
    offsets.init_from_data(fresh, x, y, 5)  # another seed's start, never trained
    data.offsets, bundle_offsets = offsets, data.offsets
    capacity.apply(fresh, data, [0, 1, 2])
    with torch.no_grad():
        torch.testing.assert_close(fresh(x) + offsets(), model(x) + bundle_offsets(), rtol=0, atol=1e-9)


def _script(script, tmp_path, *overrides):
    cmd = [sys.executable, f"scripts/{script}", *overrides, f"hydra.run.dir={tmp_path}", "train.progress=false"]
    return subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)


def test_train_script_on_two_runs_writes_every_run_and_every_fold(tmp_path, paper_csv, cycle_csv):
    proc = _script("train.py", tmp_path, f"data.paths=[{paper_csv},{cycle_csv}]", "train.max_epochs=60",
                   "data.run_offsets=true", "model=poly3")
    assert proc.returncode == 0, proc.stderr[-3000:]
    report = json.loads((tmp_path / "report.json").read_text())
    meta = json.loads((tmp_path / "compensator" / "meta.json").read_text())
    assert [f["held_out"] for f in report["folds"]] == ["paper", "cycle"]
    assert report["train_paths"] == [str(paper_csv), str(cycle_csv)]
    for run, path in zip(meta["runs"], (paper_csv, cycle_csv)):
        recording = load_recording(path)
        assert run["path"] == str(path) and run["sha256"] == recording.checksum()
        assert run["n_samples"] == len(recording)
        assert run["temp_range_c"] == [recording.temp_c.min(), recording.temp_c.max()]
    assert len(meta["data_sha256"]) == 64 and set(meta["run_offsets_dps"]) == {"paper", "cycle"}
    # the error bar: floor from both folds, and each run's blocks scored on a floor from the other alone
    calibration = meta["error_bar"]["calibration"]
    assert calibration["held_out"] == ["paper", "cycle"] and calibration["startup_s"] == 600  # conf/data's default
    shares = [calibration["cross_within_1_sigma"], *calibration["cross_within_1_sigma_by_run"].values()]
    assert len(shares) == 3 and all(len(s) == 3 and all(0 <= w <= 1 for w in s) for s in shares)
    assert "error bar cross-check" in proc.stdout and "this one recording" not in proc.stdout
    assert [report["metrics"][f"val/cross_within_1_sigma_{a}"] for a in "xyz"] == calibration["cross_within_1_sigma"]
    assert meta["temp_range_c"] == [min(r["temp_range_c"][0] for r in meta["runs"]),
                                    max(r["temp_range_c"][1] for r in meta["runs"])]


def test_path_and_paths_together_is_an_error(tmp_path, paper_csv, cycle_csv):
    proc = _script("train.py", tmp_path, f"data.path={paper_csv}", f"data.paths=[{cycle_csv}]")
    assert proc.returncode != 0 and "not both" in proc.stderr


def test_diagnose_accepts_several_runs(tmp_path, paper_csv, cycle_csv):
    proc = _script("diagnose.py", tmp_path, f"data.paths=[{paper_csv},{cycle_csv}]", "train.max_epochs=40")
    assert proc.returncode == 0, proc.stderr[-3000:]
    diagnosis = json.loads((tmp_path / "diagnosis.json").read_text())
    assert diagnosis["effects"] == [] and len(diagnosis["runs"]) == 2 and "leave-one-run-out" in diagnosis["note"]
    assert (tmp_path / "compensator" / "meta.json").is_file() and (tmp_path / "baseline" / "compensator").is_dir()


def test_ga_sweep_takes_several_runs(tmp_path, paper_csv, cycle_csv):
    sweep = tmp_path / "sweep"
    cmd = [sys.executable, "scripts/train.py", "-m", "hydra/sweeper=ga", f"data.paths=[{paper_csv},{cycle_csv}]",
           f"hydra.sweep.dir={sweep}", "hydra.sweeper.population_size=2", "hydra.sweeper.generations=1",
           "train.max_epochs=30", "train.progress=false"]
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-3000:]
    history = json.loads((sweep / "ga_history.json").read_text())
    individuals = history["generations"][0]["individuals"]
    assert all(i["status"] == "COMPLETED" and np.isfinite(i["fitness"]) for i in individuals)
    assert len(json.loads((sweep / "0" / "report.json").read_text())["folds"]) == 2
    assert len(json.loads((sweep / "best" / "compensator" / "meta.json").read_text())["runs"]) == 2


def test_run_offsets_recover_simulated_turn_on_biases(tmp_path):
    from gyronet.recordings.data import load_truth
    from gyronet.sim import simulate, write_simulation

    paths, biases = [], []
    for seed in (21, 22, 23):
        path = tmp_path / f"run{seed}.csv"
        write_simulation(simulate("paper", fs_hz=0.5, seed=seed, sensor_seed=0, sensor={"turn_on_bias_dps": 0.2}), path)
        paths.append(str(path))
        biases.append([load_truth(path).columns[f"turn_on_bias_{a}_dps"][0] for a in "xyz"])
    biases = np.array(biases)
    data = training_data(paths=paths, run_offsets=True)
    fit(RBFNet(3, 3, 12, rbf_inputs=[0], linear=True, temp_degree=3, clamp=True), data, max_epochs=300, progress=False)
    np.testing.assert_allclose(data.offsets.values().detach().numpy(), biases - biases.mean(0), atol=0.01)


def test_a_run_outside_the_other_runs_temperatures_is_named_as_an_extrapolation_fold(tmp_path, caplog):
    from gyronet.sim import simulate, write_simulation

    chamber, desk = tmp_path / "chamber.csv", tmp_path / "desk.csv"  # a full cycle, and two hours at 25 degC
    write_simulation(simulate("paper", fs_hz=0.5, seed=1, sensor_seed=0), chamber)
    write_simulation(simulate("constant", fs_hz=0.5, seed=2, sensor_seed=0, duration_s=7200.0), desk)
    short = tmp_path / "short.csv"  # 20 min wholly inside the others' temperatures: short, but no extrapolation
    write_simulation(simulate("constant", fs_hz=0.5, seed=3, sensor_seed=0, duration_s=1200.0), short)
    data = training_data(paths=[str(chamber), str(desk), str(short)])
    with caplog.at_level("WARNING", logger="gyronet.training.runs"):
        _, folds = fit_by_run(TempPolynomial(3), data, progress=False)
    warned = [r.getMessage() for r in caplog.records if "extrapolation" in r.getMessage()]
    assert len(warned) == 1 and warned[0].startswith("run chamber spends")
    assert folds[0]["in_box_s"] < 3600.0 <= folds[1]["in_box_s"] and folds[2]["in_box_s"] < 3600.0


def test_the_held_out_run_can_be_scored_as_deployed_with_a_startup_offset(paper_csv, cycle_csv):
    fold = training_data(paths=[str(paper_csv), str(cycle_csv)], val_startup_s=600).holding_out(1)
    time_s = fold.val_full[0]
    residual = np.ones((len(time_s), 3)) * [0.1, -0.2, 0.3]
    residual[time_s >= time_s[0] + 600] += 0.05
    scored, adjusted = fold.val_adjust(time_s, residual)
    assert scored.tolist() == (time_s >= time_s[0] + 600).tolist()  # the window's own rows are not scored
    np.testing.assert_allclose(adjusted[scored], 0.05)


@pytest.mark.slow
@needs_cats
def test_real_runs_choose_less_than_full_capacity_and_beat_the_cubic_inside_the_box(monkeypatch):
    """Two real runs of one tag: what the Gaussians learn from one run does not carry over to the other.

    The figures are the folds' own (each run held out, trained on the other, inside its box,
    its constant removed): the evidence the selection acts on, against the PX4 cubic's.
    """
    from gyronet.training import capacity, error_bar_fit

    gaussian_weights = []  # of each fold model whose held-out blocks calibrate the error bar
    stats = error_bar_fit.held_out_stats
    monkeypatch.setattr(error_bar_fit, "held_out_stats", lambda model, *args: gaussian_weights.append(
        model.head.weight.detach().abs().sum(1).numpy()) or stats(model, *args))
    data = training_data(paths=[str(p) for p in CATS_RUNS], run_offsets=True)
    model = RBFNet(3, 3, 12, rbf_inputs=[0], linear=True, temp_degree=3, clamp=True, select_capacity=True)
    metrics, folds = fit_by_run(model, data, progress=False)
    levels = [int(metrics[f"model/level_{a}"]) for a in "xyz"]
    assert all(level < 3 for level in levels), levels
    # the bar is calibrated on what is deployed: each fold refitted at the chosen levels, no Gaussians
    assert len(gaussian_weights) == 2 and np.all(np.array(gaussian_weights) == 0), gaussian_weights
    chosen = capacity.from_metrics(folds)[levels, [0, 1, 2]]
    cubic = []
    for run in data.runs:
        fold = data.holding_out(run.index)
        poly = TempPolynomial(3)
        fit(poly, fold, progress=False)
        cubic.append(capacity.held_out_error(poly, fold))
    cubic = np.mean(cubic, axis=0)
    assert np.all(chosen <= 1.05 * cubic), (chosen, cubic)
    assert chosen.mean() <= 0.85 * cubic.mean(), (chosen, cubic)


def test_run_offsets_repeat_bit_for_bit():
    """The same fit gives the same offsets however the heap lies (MKL's default least squares did not: a
    campaign's final fits then differed in the ninth digit from run to run)."""
    x, y, run, _ = _two_runs_data()
    xt, yt = torch.as_tensor(x), torch.as_tensor(y)
    results, heap = set(), []
    for k in range(200):
        heap.append(torch.ones(k * 37 % 1000 + 1, dtype=torch.float64))  # allocations of every size between fits
        offsets = RunOffsets(run, 3)
        offsets.fit_closed_form(TempPolynomial(3), xt, yt)
        results.add(offsets.raw.detach().numpy().tobytes())
        heap = heap[-3:] if k % 7 == 0 else heap
    assert len(results) == 1


def test_a_campaign_whose_span_is_a_glitch_s_is_refused(tmp_path):
    """A glitch row (655.35 degC, a sensor's 0xFFFF) is left out as a glitch; the 1 degC span must hold without it."""
    from gyronet.recordings.data import write_recording

    paths = []
    for k in range(2):
        time_s = np.arange(3000.0)
        columns = {"time_s": time_s, "temp_c": 25.0 + 0.3 * np.sin(time_s / 300.0 + k),
                   **{f"gyro_{a}_dps": np.zeros(3000) for a in "xyz"}}
        columns["temp_c"][1000] = 655.35
        paths.append(tmp_path / f"run{k}.csv")
        write_recording(paths[-1], columns)
    with pytest.raises(GyronetError, match=r"accepted temperatures span 0.6 degC together"):
        load_runs([str(p) for p in paths], PAPER_FEATURES)


def test_final_fit_record_does_not_depend_on_the_order_of_the_runs(paper_csv, cycle_csv, tmp_path):
    """Two runs of one length: the Kalman stage's record was whichever data.paths listed first."""
    rows = min(len(load_recording(p).time_s) for p in (paper_csv, cycle_csv))
    paths = []
    for source in (paper_csv, cycle_csv):
        lines = source.read_text().splitlines(keepends=True)
        header = sum(line.startswith("#") for line in lines) + 1
        paths.append(tmp_path / source.name)
        paths[-1].write_text("".join(lines[:header + rows]))
    chosen = {RunsData(load_runs([str(p) for p in order], PAPER_FEATURES), list(PAPER_FEATURES)).recording.path
              for order in (paths, paths[::-1])}
    assert len(chosen) == 1


@pytest.mark.parametrize("fraction, said", [(0.4, "one span in 2 of data.n_blocks=10: 5 spans, 50 %"),
                                            (0.25, "one span in 4 of data.n_blocks=10: 2 spans, 20 %")])
def test_a_val_fraction_no_split_gives_says_what_is_held_out(paper_csv, caplog, fraction, said):
    """0.4 held out half the record, silently (every k-th span, k = round(1 / val_fraction))."""
    with caplog.at_level(logging.WARNING, logger="gyronet.training.runs"):
        training_data(path=str(paper_csv), val_fraction=fraction)
    assert said in caplog.text
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="gyronet.training.runs"):
        training_data(path=str(paper_csv))
    assert "val_fraction" not in caplog.text
    with pytest.raises(GyronetError, match=r"data.val_fraction must be in \(0, 1\)"):
        training_data(path=str(paper_csv), val_fraction=1.5)


@pytest.mark.parametrize("option, said", [({"n_blocks": 0}, "no span to validate on"),
                                          ({"n_blocks": 2}, "no span to validate on"),
                                          ({"n_blocks": 1, "val_fold": 0}, "no span to train on")])
def test_n_blocks_that_leave_nothing_to_validate_or_train_on_are_one_line(tmp_path, option, said):
    """n_blocks=0 was refused as "too short to train on", of a recording long enough (from the entry-point fuzz)."""
    with pytest.raises(GyronetError, match=f"data.n_blocks=.*leaves {said}"):
        training_data(path=str(tmp_path / "F.csv"), **option)  # refused before the file is read
