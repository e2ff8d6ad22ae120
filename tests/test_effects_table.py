"""The README's effects table: its recipe prints the README's columns, one row per effect.

The figures themselves are the slow tests' business (tests/test_diagnose.py); here the records are
an hour at 1 Hz, the networks barely trained and the permutation test coarse. The fast test makes
its diagnosis in-process and lets the script reuse it (four interpreters, each importing torch,
would take half a minute); the slow one runs the whole recipe from nothing.
"""
import json
import re
import subprocess
import sys

import pytest

from gyronet.analysis.diagnose import diagnose
from gyronet.analysis.diagnose.effects import found_text, to_markdown
from gyronet.model.rbf import RBFNet
from gyronet.sim import simulate, write_simulation

from conftest import ROOT

HEADER = ("| effect in the data | found, in order | held-out, mdps: baseline -> final | drift error elsewhere, mdps "
          "| residual / noise floor elsewhere |")
AXES3 = r"-?\d+\.\d+/-?\d+\.\d+/-?\d+\.\d+"


def test_found_effects_are_named_by_kind_source_and_parameter():
    found = [{"kind": "lag", "source": "temp_c", "params": {"tau_s": 1773.2}},
             {"kind": "time", "source": "time_s", "params": {}}]
    assert found_text(found) == "lag `temp_c` tau_s=1773, time `time_s`"
    assert found_text([]) == "nothing"
    # equivalent explanations are named with the effect kept, so that a reader of the table sees them
    board = {"kind": "column", "source": "board_temp_c", "params": {"tau_s": 1150.0},
             "alternatives": [{"kind": "lag", "source": "temp_c", "params": {"tau_s": 2018.0}, "score": 2.28}]}
    assert found_text([board]) == "column `board_temp_c` tau_s=1150 (or lag `temp_c` tau_s=2018)"


def test_a_row_reads_baseline_to_final_per_axis():
    axes = {"x": 0.0081, "y": 0.0102, "z": 0.0137}
    check = {"drift_error_dps": {"x": 0.0069, "y": 0.0038, "z": 0.0039},
             "ratio_to_floor": {"x": 1.49, "y": 1.11, "z": 1.07}}
    row = {"effect": "none", "found": [], "held_out_dps": {"baseline": axes, "final": axes},
           "check": {"baseline": check, "final": check}, "drift_error_ratio": 1.0}
    lines = to_markdown([row]).splitlines()
    assert lines[0] == HEADER and len(lines) == 3
    assert lines[2] == ("| none | nothing | 8.1/10.2/13.7 -> 8.1/10.2/13.7 | 6.9/3.8/3.9 -> 6.9/3.8/3.9 (1.00) "
                        "| 1.49/1.11/1.07 -> 1.49/1.11/1.07 |")


def _row_cells(line: str) -> list[str]:
    """A Markdown row's cells, checked for the README's formats."""
    cells = line.strip("| ").split(" | ")
    assert len(cells) == 5
    assert re.fullmatch(f"{AXES3} -> {AXES3}", cells[2])
    assert re.fullmatch(rf"{AXES3} -> {AXES3} \(\d+\.\d\d\)", cells[3])
    assert re.fullmatch(f"{AXES3} -> {AXES3}", cells[4])
    return cells


def _check_table(out, effects: list[str]) -> dict:
    """The Markdown has the README's header and one row per effect in order; the JSON the same rows."""
    lines = (out / "effects_table.md").read_text().splitlines()
    assert lines[0] == HEADER and lines[1] == "|---|---|---|---|---|"
    assert [_row_cells(line)[0] for line in lines[2:]] == effects
    table = json.loads((out / "effects_table.json").read_text())
    assert [row["effect"] for row in table["rows"]] == effects
    for row in table["rows"]:
        assert all(0 < row["check"][part]["inside_share"] <= 1 for part in ("baseline", "final"))
        assert row["drift_error_ratio"] > 0
    return table


def test_the_script_tabulates_the_diagnoses_in_its_folder(tmp_path):
    # the records and the diagnosis made here, tiny, in this process; the script reuses them
    folder = tmp_path / "aux"
    folder.mkdir()
    for name, profile, seed in (("train", "cycle", 1), ("check", "random", 2)):
        write_simulation(simulate(profile, fs_hz=1.0, duration_s=3600.0, seed=seed, sensor_seed=3,
                                  effects={"aux": {}}), folder / f"{name}.csv")
    model = lambda n_inputs: RBFNet(n_inputs, 3, 4, rbf_inputs=[0], linear=True, temp_degree=3, clamp=True)  # noqa: E731
    diagnose({"path": str(folder / "train.csv"), "rate_tau_s": 5.0}, model, folder / "diagnose",
             train_cfg={"progress": False, "max_epochs": 50},
             options={"n_shifts": 9, "max_effects": 1, "refine_top": 1, "refine_passes": 0}, plots=False)
    cmd = [sys.executable, "scripts/effects_table.py", f"hydra.run.dir={tmp_path}", "effects=[aux]", "reuse=true"]
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-3000:]
    log = proc.stdout + proc.stderr
    assert "effects table" in log and "simulate.py" not in log and "diagnose.py" not in log  # nothing made again
    table = _check_table(tmp_path, ["aux"])
    assert table["settings"]["sensor_seed"] == 3 and table["settings"]["reuse"] is True


@pytest.mark.slow
def test_the_whole_recipe_runs_from_nothing(tmp_path):
    cmd = [sys.executable, "scripts/effects_table.py", f"hydra.run.dir={tmp_path}", "effects=[aux]",
           'simulate=["fs_hz=1","duration_s=3600"]',  # one effect (CI time)
           'diagnose=["train.max_epochs=50","diagnose.n_shifts=9","diagnose.max_effects=1","diagnose.refine_top=1",'
           '"diagnose.refine_passes=0"]']
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-3000:]
    _check_table(tmp_path, ["aux"])
    assert (tmp_path / "aux" / "check.truth.csv").is_file()
    assert (tmp_path / "aux" / "diagnose" / "diagnose.log").is_file()  # each step its own Hydra run
    assert (tmp_path / "aux" / "diagnose" / "compensator" / "meta.json").is_file()


def test_an_unknown_effect_is_refused_in_one_line_before_any_work(tmp_path):
    cmd = [sys.executable, "scripts/effects_table.py", f"hydra.run.dir={tmp_path}", "effects=[none,no_such_effect]"]
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True)
    assert proc.returncode == 2
    assert proc.stderr == ("error: effects: no conf/sim/effects/no_such_effect.yaml "
                           "(known: ageing, all, aux, board, hysteresis, lag2, none, warmup)\n")
    assert not (tmp_path / "none").exists()
