"""Fleet calibration (gyronet.training.fleet, scripts/fleet.py, scripts/fleet_table.py): units from a file
pattern, one bundle per unit through the joblib and submitit_local launchers, one table."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from gyronet.recordings.data import load_recording
from gyronet.errors import GyronetError
from gyronet.training.fleet import (UNITS_FILE, find_units, fleet_table, set_aside_outputs, sweep_overrides, to_markdown,
                                   write_units)

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "scripts"))
import fleet as fleet_script  # noqa: E402 -- scripts/fleet.py's argument parsing


def touch(path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("time_s\n")
    return path


def test_units_are_named_after_their_files(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    for name in ("units/line1/a.csv", "units/line2/007.csv", "units/line2/007.truth.csv", "units/notes.txt"):
        touch(tmp_path / name)
    units, root, suffix = find_units("units/**/*.csv")
    assert units == {"line1/a": "units/line1/a.csv", "line2/007": "units/line2/007.csv"}  # truth files are not units
    assert (root, suffix) == ("units", ".csv")
    assert sweep_overrides(units, root, suffix) == [
        "+unit='line1/a','line2/007'", "data.path='units/${unit}.csv'", "hydra.sweep.subdir=${unit}"]
    with pytest.raises(GyronetError, match=r"no file matches 'units/\*.bag'"):
        find_units("units/*.bag")
    with pytest.raises(GyronetError, match=r"not recordings of one kind \(\.csv, \.txt\).*convert others first"):
        find_units("units/**/*")
    touch(tmp_path / "units" / "line3" / "b.csv.gz")  # said "()": both are recordings, of two kinds
    with pytest.raises(GyronetError, match=r"not recordings of one kind \(\.csv, \.csv\.gz\)"):
        find_units("units/**/*.csv*")
    touch(tmp_path / "odd" / "it's.csv")
    with pytest.raises(GyronetError, match="Hydra overrides cannot carry; rename the file"):
        find_units("odd/*.csv")


def test_a_unit_keeps_its_name_and_the_others_when_run_again(tmp_path, monkeypatch):
    """A re-run of one unit named it after its own folder (the matches' common folder) and dropped the others."""
    monkeypatch.chdir(tmp_path)
    for name in ("units/line1/a.csv", "units/line2/b.csv"):
        touch(tmp_path / name)
    write_units("S", find_units("units/**/*.csv")[0])
    units, root, _ = find_units("units/**/b.csv")  # only line2 matches: the name stays line2/b
    assert (units, root) == ({"line2/b": "units/line2/b.csv"}, "units")
    write_units("S", units)
    assert json.loads((tmp_path / "S" / UNITS_FILE).read_text())["units"] == {
        "line1/a": "units/line1/a.csv", "line2/b": "units/line2/b.csv"}
    with pytest.raises(GyronetError, match=r"units/line2/b.csv is unit 'line2/b' in .*, here 'b'"):
        write_units("S", find_units("units/line2/b.csv")[0])
    for spelled in ("./units/line2/b.csv", str(tmp_path / "units/line2/b.csv")):  # the same file, spelled otherwise
        with pytest.raises(GyronetError, match="is unit 'line2/b'"):
            write_units("S", {"b": spelled})


def test_failed_reruns_keep_the_last_good_run_in_previous(tmp_path):
    """A failed re-run leaves tb/; the next re-run replaced previous/ (the good bundle) with that tb/ alone."""
    unit = tmp_path / "u"
    (unit / "compensator").mkdir(parents=True)
    (unit / "report.json").write_text("good")
    set_aside_outputs(unit)  # the re-run starts: the good run is set aside
    for _ in range(2):  # two re-runs that fail after writing tb/
        (unit / "tb").mkdir()
        set_aside_outputs(unit)
        assert sorted(p.name for p in unit.iterdir()) == ["previous"]
        assert (unit / "previous" / "report.json").read_text() == "good" and (unit / "previous" / "compensator").is_dir()


def test_spec_range_is_checked_before_anything_runs(tmp_path):
    """[-40], [a,b] or 5 gave a traceback; [85,-40] to fleet.py trained every unit and then failed."""
    write_units(tmp_path, {"a": "units/a.csv"})
    for bad in ([-40], ["a", "b"], 5, [85, -40], [0, float("nan")]):
        with pytest.raises(GyronetError, match=r"spec_range_c must be \[LOW,HIGH\] in degC with HIGH > LOW"):
            fleet_table(tmp_path, bad)
    with pytest.raises(GyronetError, match="fleet.spec_range_c must be"):
        fleet_script.parse(["data.path=glob(u/*.csv)", "fleet.spec_range_c=[85,-40]"])


def test_fleet_arguments():
    pattern, spec, sweep_dir, rest = fleet_script.parse(
        ["-m", "data.path=glob(units/*.csv)", "model=poly3", "fleet.spec_range_c=[-40,85]", "hydra.sweep.dir=S"])
    assert (pattern, spec, sweep_dir, rest) == ("units/*.csv", [-40.0, 85.0], "S", ["model=poly3", "hydra.sweep.dir=S"])
    for bad, message in [(["data.path=units/a.csv"], "a fleet takes its units as data.path=glob"),
                         (["model=poly3"], "no units given"),
                         (["data.path=glob(u/*.csv)", "fleet.spec_range_c=[1]"], "must be \\[LOW,HIGH\\]"),
                         (["data.path=glob(u/*.csv)", "fleet.spec=1"], "unknown setting fleet.spec")]:
        with pytest.raises(GyronetError, match=message):
            fleet_script.parse(bad)


def fake_job(sweep: Path, unit: str, rmse: tuple[float, float, float], range_c: tuple[float, float],
             evals: dict | None = None) -> None:
    """A unit's job folder as train.py leaves it: report.json and compensator/meta.json."""
    (sweep / unit / "compensator").mkdir(parents=True)
    metrics = {f"val/rmse_{a}_dps": v for a, v in zip("xyz", rmse)}
    (sweep / unit / "report.json").write_text(json.dumps({"metrics": metrics, "eval": evals or {}}))
    (sweep / unit / "compensator" / "meta.json").write_text(json.dumps({"temp_range_c": list(range_c)}))


def test_table_of_every_unit(tmp_path):
    write_units(tmp_path, {"a": "units/a.csv", "b": "units/b.csv", "c": "units/c.csv"})
    fake_job(tmp_path, "a", (0.01, 0.02, 0.03), (-40.0, 60.0))
    fake_job(tmp_path, "b", (0.04, 0.05, 0.06), (-15.0, 60.0),
             {"held/b.csv": {"n_out_of_range": 30, "n_samples": 100}, "held/b2.csv": {"n_out_of_range": 0, "n_samples": 200}})
    (tmp_path / "c").mkdir()  # started, never finished
    table = fleet_table(tmp_path)
    assert table["reference_range_c"] == [-40.0, 60.0] and (table["n_units"], table["n_ok"]) == (3, 2)
    a, b, c = (table["units"][u] for u in "abc")
    assert a["val_rmse_dps"] == {"x": 0.01, "y": 0.02, "z": 0.03} and a["out_of_range_share"] == 0.0
    assert b["out_of_range_share"] == pytest.approx(0.25)  # 25 of 100 degC not covered
    assert b["eval_out_of_range_share"] == pytest.approx(0.1) and "eval_out_of_range_share" not in a
    assert c["status"] == "missing" and "no report.json" in c["reason"]
    assert table["units"]["b"]["bundle"] == str(tmp_path / "b" / "compensator")
    spec = fleet_table(tmp_path, spec_range_c=[-40.0, 85.0])
    assert spec["units"]["a"]["out_of_range_share"] == pytest.approx(0.2)  # 60..85 of 125 degC
    lines = to_markdown(spec).splitlines()
    assert lines[5].startswith("| a | ok | 0.01 | 0.02 | 0.03 | -40.00 to 60.00 | 0.200 | - |")
    assert lines[6].startswith("| b | ok |") and "| 0.100 |" in lines[6]  # the held-out samples' share
    assert lines[7].startswith("| c | missing: no report.json")
    with pytest.raises(GyronetError, match=f"no {UNITS_FILE}"):
        fleet_table(tmp_path / "a")
    (tmp_path / "a" / "report.json").write_text('{"metrics": {')  # cut short
    table = fleet_table(tmp_path)
    assert table["units"]["a"]["status"] == "missing" and "unreadable report.json" in table["units"]["a"]["reason"]
    (tmp_path / UNITS_FILE).write_text(json.dumps({"units": {"c": "units/c.csv"}}))  # no unit trained: no
    # reference range, still a table
    assert fleet_table(tmp_path)["reference_range_c"] == [None, None]
    assert to_markdown(fleet_table(tmp_path)).startswith(f"Fleet {tmp_path}: 0 of 1 units trained.\n")


def run(script: str, *args: str, cwd: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    return subprocess.run([sys.executable, str(ROOT / "scripts" / script), *args], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=600)


def test_bad_fleet_input_is_one_line(tmp_path):
    done = run("fleet.py", "data.path=glob(units/*.csv)", cwd=tmp_path)
    assert done.returncode == 2 and done.stderr.strip() == f"error: no file matches 'units/*.csv' (relative to {tmp_path})"
    assert not (tmp_path / "outputs").exists()  # nothing launched, no sweep folder
    done = run("fleet_table.py", f"sweep={tmp_path}", f"hydra.run.dir={tmp_path / 'h'}", cwd=tmp_path)
    assert done.returncode == 2 and done.stderr.strip().splitlines()[-1].startswith(f"error: {tmp_path}: no {UNITS_FILE}")
    (tmp_path / "units").mkdir()
    (tmp_path / "units" / "a.csv").write_text("time_s,temp_c,gyro_x_dps,gyro_y_dps,gyro_z_dps\n0,20,0,0,0\n")
    done = run("fleet.py", "data.path=glob(units/*.csv)", "data.pth=3", "hydra.sweep.dir=S", cwd=tmp_path)
    assert done.returncode == 2 and "data.pth" in done.stderr and "fleet:" not in done.stderr  # refused before a unit
    assert not (tmp_path / "S" / "fleet_table.md").exists()
    done = run("fleet_table.py", f"sweep={tmp_path}", "spec_range_c=[-40]", f"hydra.run.dir={tmp_path / 'h'}",
               cwd=tmp_path)
    assert done.returncode == 2 and done.stderr.strip() == "error: spec_range_c must be [LOW,HIGH] in degC with " \
        "HIGH > LOW, got [-40]"


def test_a_failed_rerun_is_not_listed_with_the_earlier_bundle(tmp_path):
    """The table read the earlier run's report.json as the unit's result after its re-run failed."""
    (tmp_path / "units").mkdir()
    for name in ("a", "b"):
        (tmp_path / "units" / f"{name}.csv").write_text("time_s,temp_c,gyro_x_dps,gyro_y_dps,gyro_z_dps\n0,20,0,0,x\n")
    write_units(tmp_path / "S", {"a": "units/a.csv"})
    fake_job(tmp_path / "S", "a", (0.01, 0.02, 0.03), (-40.0, 60.0))  # the earlier run, when the file was fine
    done = run("fleet.py", "data.path=glob(units/*.csv)", "hydra.sweep.dir=S", cwd=tmp_path)
    assert done.returncode == 2 and "Traceback" not in done.stderr
    row = json.loads((tmp_path / "S" / "fleet_table.json").read_text())["units"]["a"]
    assert row["status"] == "missing" and "no report.json" in row["reason"]
    assert (tmp_path / "S" / "a" / "previous" / "compensator" / "meta.json").is_file()  # set aside, not lost
    # and the error of every failed unit is in its log (Hydra prints only the first)
    for name in ("a", "b"):
        assert "units/" + name + ".csv" in (tmp_path / "S" / name / "train.log").read_text()



def test_train_refuses_a_file_glob_that_hydra_would_sweep_as_nothing(tmp_path):
    done = run("train.py", "-m", "data.path=glob(units/*.csv)", cwd=tmp_path)
    assert done.returncode == 2 and "scripts/fleet.py" in done.stderr and len(done.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "multirun").exists()


# --- end to end through the launchers -------------------------------------------------------

def simulate_units(folder: Path, names: list[str]) -> None:
    from gyronet.sim import simulate, write_simulation

    for i, name in enumerate(names):  # tiny: 2 h at 1 Hz, each its own sensor
        write_simulation(simulate("random", fs_hz=1.0, seed=i, sensor_seed=i, duration_s=2 * 3600), folder / f"{name}.csv")


FAST_TRAIN = ("train.max_epochs=20", "train.progress=false")


@pytest.mark.slow
@pytest.mark.parametrize("launcher", ["joblib", "submitit_local"])
def test_fleet_sweep_through_a_launcher(tmp_path, launcher):
    if launcher.startswith("submitit"):
        pytest.importorskip("hydra_plugins.hydra_submitit_launcher")
    names = ["007", "sn-a"]  # 007 must stay a string through Hydra's overrides
    simulate_units(tmp_path / "units", names)
    args = [f"hydra/launcher={launcher}", "hydra.sweep.dir=S", *FAST_TRAIN]
    if launcher == "joblib":  # and a unit whose recording is broken: the others still get their bundles
        (tmp_path / "units" / "broken.csv").write_text("time_s,temp_c\n0,20\n1,20\n")
        args += ["hydra.launcher.n_jobs=3", "fleet.spec_range_c=[-40,85]"]
    done = run("fleet.py", "data.path=glob(units/*.csv)", *args, cwd=tmp_path)
    table = json.loads((tmp_path / "S" / "fleet_table.json").read_text())
    if launcher == "joblib":
        assert done.returncode == 2 and "Traceback" not in done.stderr
        assert "error: " in done.stderr and "broken.csv: missing required column(s)" in done.stderr
        assert table["units"]["broken"]["status"] == "missing"
    else:
        assert done.returncode == 0, done.stderr
    for name in names:
        row = table["units"][name]
        assert row["status"] == "ok" and row["bundle"] == str(Path("S") / name / "compensator")
        report = json.loads((tmp_path / "S" / name / "report.json").read_text())
        assert report["train_path"] == f"units/{name}.csv"
        assert row["val_rmse_dps"]["x"] == report["metrics"]["val/rmse_x_dps"]
        # each bundle was trained on its own unit's recording
        meta = json.loads((tmp_path / row["bundle"] / "meta.json").read_text())
        assert meta["data_sha256"] == load_recording(tmp_path / "units" / f"{name}.csv").checksum()
    assert "| 007 | ok |" in (tmp_path / "S" / "fleet_table.md").read_text()
    if launcher == "joblib":
        assert table["reference_range_c"] == [-40.0, 85.0]
        assert all(table["units"][n]["out_of_range_share"] > 0.3 for n in names)  # a random 2 h run spans far less
        return
    # the table again, with a spec range (what a second look at a finished fleet does)
    again = run("fleet_table.py", "sweep=S", "spec_range_c=[-40,85]", "output=T/fleet.md",
                "hydra.run.dir=T/hydra", cwd=tmp_path)
    assert again.returncode == 0, again.stderr
    spec = json.loads((tmp_path / "T" / "fleet.json").read_text())
    assert spec["reference_range_c"] == [-40.0, 85.0]
    assert all(spec["units"][n]["out_of_range_share"] > 0.3 for n in names)  # a random 2 h run spans far less
