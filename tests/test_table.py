"""The paper's Table 1 on a held-out recording: rows, figures against the truth, the script."""
import json
import os
import subprocess
import sys

import numpy as np
import pytest

from gyronet.recordings.data import AXES, load_recording, load_truth
from gyronet.training.dataset import block_rmse
from gyronet.errors import BundleError, GyronetError
from gyronet.sim import simulate, write_simulation
from gyronet.analysis.table import held_out_paths, table_rows, to_markdown

from conftest import FAST_FS_HZ, ROOT


def _script(*args, cwd=ROOT):
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    return subprocess.run([sys.executable, str(ROOT / "scripts" / "table.py"), *map(str, args)],
                          cwd=cwd, env=env, capture_output=True, text=True)


def test_rows_score_each_bundle_against_the_truth(bundle, cycle_csv):
    rows = table_rows(cycle_csv, {"gyronet": bundle})
    assert list(rows) == ["Raw", "Noise only (truth)", "gyronet"]
    truth = load_truth(cycle_csv).columns
    time_s = load_recording(cycle_csv).time_s
    true_drift = np.column_stack([truth[f"drift_{a}_dps"] for a in AXES])
    # raw: the drift estimate is zero, so its error is the drift itself
    np.testing.assert_allclose(rows["Raw"]["drift_error_dps"], block_rmse(time_s, true_drift, 60.0))
    assert all(c < r / 10 for c, r in zip(rows["gyronet"]["drift_error_dps"], rows["Raw"]["drift_error_dps"]))
    assert max(rows["gyronet"]["ratio_to_floor"]) < 2.0 < min(rows["Raw"]["ratio_to_floor"])
    # the noise alone sets the floor of B: no compensation can go below it by much
    for axis in range(3):
        assert rows["gyronet"]["bias_instability_deg_hr"][axis] > 0.5 * rows["Noise only (truth)"][
            "bias_instability_deg_hr"][axis]
    table = to_markdown(rows).splitlines()
    assert table[0].startswith("| method | N x") and "residual / floor" in table[0]
    assert [line.split("|")[1].strip() for line in table[3:]] == list(rows)
    # a B that is only a bound reads "<=", as allan.py prints it
    cells = {line.split("|")[1].strip(): line.split("|")[5:8] for line in table[3:]}
    for name, row in rows.items():
        assert [c.strip().startswith("<=") for c in cells[name]] == row["bias_instability_upper_bound"]
    assert any(b for row in rows.values() for b in row["bias_instability_upper_bound"])  # the check bites here


def test_the_script_writes_markdown_and_json_into_its_run_folder(bundle, cycle_csv, tmp_path):
    """Without output=, the table goes under hydra.run.dir, not into the folder the command runs in."""
    here, run = tmp_path / "here", tmp_path / "run"
    here.mkdir()
    proc = _script(f"input={cycle_csv}", f"+bundles={{gyronet: {bundle}}}", f"hydra.run.dir={run}", cwd=here)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert list(here.iterdir()) == []
    out = run / "table1.md"
    figures = json.loads(out.with_suffix(".json").read_text())
    assert "gyronet" in json.dumps(figures) and "| gyronet |" in out.read_text()


def test_the_script_reports_a_missing_bundle_in_one_line(cycle_csv, tmp_path):
    proc = subprocess.run([sys.executable, "scripts/table.py", f"input={cycle_csv}", f"output={tmp_path / 't.md'}",
                           f"+bundles={{gyronet: {tmp_path / 'nope'}}}", f"hydra.run.dir={tmp_path}"],
                          cwd=ROOT, capture_output=True, text=True)
    assert proc.returncode != 0 and "Traceback" not in proc.stderr
    assert "nope" in proc.stderr


@pytest.fixture(scope="module")
def biased_csv(tmp_path_factory):
    """Another power-up of the bundle's sensor: a random history with a turn-on bias of its own."""
    path = tmp_path_factory.mktemp("sim") / "biased.csv"
    write_simulation(simulate("random", fs_hz=FAST_FS_HZ, seed=7, sensor_seed=0, duration_s=6 * 3600.0,
                              sensor={"turn_on_bias_dps": 0.05}), path)
    return path


def test_several_runs_get_a_table_each_from_a_fresh_state_and_the_mean(bundle, cycle_csv, biased_csv, tmp_path):
    """data.paths: each run scored as if alone (the order changes nothing), then residual / floor averaged."""
    proc = _script(f"data.paths=[{biased_csv},{cycle_csv}]", f"+bundles={{gyronet: {bundle}}}",
                   f"output={tmp_path / 't.md'}", f"hydra.run.dir={tmp_path}")
    assert proc.returncode == 0, proc.stderr[-2000:]
    figures = json.loads((tmp_path / "t.json").read_text())
    assert list(figures["runs"]) == ["biased", "cycle"]
    alone = table_rows(cycle_csv, {"gyronet": bundle})
    np.testing.assert_allclose(figures["runs"]["cycle"]["gyronet"]["ratio_to_floor"], alone["gyronet"]["ratio_to_floor"])
    markdown = (tmp_path / "t.md").read_text()
    assert "### biased" in markdown and "### cycle" in markdown and "Mean over the 2 runs" in markdown
    mean_line = next(line for line in markdown.splitlines() if line.startswith("| gyronet |") and line.count("|") == 6)
    expected = np.mean([figures["runs"][r]["gyronet"]["ratio_to_floor"] for r in ("biased", "cycle")], axis=0)
    np.testing.assert_allclose([float(c) for c in mean_line.split("|")[2:5]], expected, atol=0.006)


def test_the_startup_offset_removes_a_turn_on_bias_and_its_window_is_not_scored(bundle, biased_csv):
    plain = table_rows(biased_csv, {"gyronet": bundle})
    started = table_rows(biased_csv, {"gyronet": bundle}, startup={"still_s": 600})
    assert max(started["gyronet"]["ratio_to_floor"]) < 0.5 * max(plain["gyronet"]["ratio_to_floor"])
    # every row, raw included, is scored from the window's end: raw is not offset, only cut
    cut = table_rows(biased_csv, {}, score_from_s=600)
    assert started["Raw"] == cut["Raw"] and started["Raw"] != plain["Raw"]
    # what the offset alone does is a row of its own: the bar a model must clear as deployed
    assert "Raw, start-up offset" in started and "Raw, start-up offset" not in plain
    alone = started["Raw, start-up offset"]["ratio_to_floor"]
    assert max(alone) < max(started["Raw"]["ratio_to_floor"])
    assert all(g < a for g, a in zip(started["gyronet"]["ratio_to_floor"], alone))
    with pytest.raises(GyronetError, match="nothing left to score"):
        table_rows(biased_csv, {}, score_from_s=1e6)


def test_a_recording_without_truth_is_scored_against_its_own_floor(bundle, cycle_csv, tmp_path):
    """A real run has no truth: the floor is its own Allan deviation at 60 s in its cold dwell (gyronet.analysis.campaign)."""
    bare = tmp_path / "bare.csv"
    bare.write_text(cycle_csv.read_text())  # the recording alone, no truth beside it
    rows = table_rows(bare, {"gyronet": bundle})
    with_truth = table_rows(cycle_csv, {"gyronet": bundle})
    assert rows["gyronet"]["arw_deg_rthr"] == with_truth["gyronet"]["arw_deg_rthr"]
    assert "Noise only (truth)" not in rows and "drift_error_dps" not in rows["gyronet"]
    # the drift is gone down to near the noise; raw is far above it on every axis
    assert max(rows["gyronet"]["ratio_to_floor"]) < 3.0
    assert all(r > 5 * g for r, g in zip(rows["Raw"]["ratio_to_floor"], rows["gyronet"]["ratio_to_floor"]))


def test_held_out_recordings_are_named_once_and_rates_must_match(bundle, tmp_path):
    assert held_out_paths("a.csv") == ["a.csv"] and held_out_paths(paths=["a.csv", "b.csv"]) == ["a.csv", "b.csv"]
    for given in ({}, {"input_path": "a.csv", "paths": ["b.csv"]}, {"path": "a.csv", "input_path": "a.csv"}):
        with pytest.raises(GyronetError, match="give the held-out recording"):
            held_out_paths(**given)
    fast = tmp_path / "fast.csv"
    write_simulation(simulate("paper", fs_hz=4 * FAST_FS_HZ, seed=3, sensor_seed=0, duration_s=3600.0), fast)
    with pytest.raises(BundleError, match="Hz"):
        table_rows(fast, {"gyronet": bundle})


def test_a_bundle_scored_on_its_own_training_recording_is_named_in_sample(bundle, paper_csv, cycle_csv, caplog):
    """meta.json's checksum of the training data: a row on that recording is no held-out figure."""
    with caplog.at_level("WARNING", logger="gyronet.analysis.table"):
        rows = table_rows(paper_csv, {"gyronet": bundle})
    assert "gyronet (in sample)" in rows and "gyronet" not in rows
    assert any("was trained on" in r.getMessage() for r in caplog.records)
    assert "gyronet" in table_rows(cycle_csv, {"gyronet": bundle})
