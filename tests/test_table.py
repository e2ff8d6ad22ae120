"""The paper's Table 1 on a held-out recording: rows, figures against the truth, the script."""
import json
import os
import subprocess
import sys

import numpy as np

from gyronet.data import AXES, load_recording, load_truth
from gyronet.dataset import block_rmse
from gyronet.table import table_rows, to_markdown

from conftest import ROOT


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


def test_the_script_writes_markdown_and_json_into_its_run_folder(bundle, cycle_csv, tmp_path):
    """Without output=, the table goes under hydra.run.dir, not into the folder the command runs in."""
    here, run = tmp_path / "here", tmp_path / "run"
    here.mkdir()
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.run([sys.executable, str(ROOT / "scripts" / "table.py"), f"input={cycle_csv}",
                           f"+bundles={{gyronet: {bundle}}}", f"hydra.run.dir={run}"],
                          cwd=here, env=env, capture_output=True, text=True)
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
