"""The real-data table: floors, touched blocks, and each run held out in turn."""
from pathlib import Path

import sys

import numpy as np
import pytest
from hydra.utils import instantiate

from gyronet.model.baselines import TempPolynomial
from gyronet.analysis.campaign import floor_dps, held_out_table, to_markdown, touched_blocks
from gyronet.recordings.data import Recording
from gyronet.errors import GyronetError

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
import campaign_table  # noqa: E402

from conftest import CATS_RUNS as RUNS, needs_cats  # noqa: E402


def _still(n=7200, seed=0):
    rng = np.random.default_rng(seed)
    time_s = np.arange(n, dtype=float)
    temp = 15 - 10 * np.minimum(time_s / 1800, 1)  # cools, then dwells at 5 degC
    columns = {"time_s": time_s, "temp_c": temp}
    for a in "xyz":
        columns[f"gyro_{a}_dps"] = rng.normal(0, 0.1, n)
        columns[f"acc_{a}_g"] = rng.normal(-1.0 if a == "z" else 0.0, 0.002, n)
    return Recording(columns, {"fs_hz": "1"})


def test_floor_is_the_60s_allan_deviation_of_white_noise_in_the_cold_dwell():
    floor = floor_dps(_still())
    np.testing.assert_allclose(floor, 0.1 / np.sqrt(60), rtol=0.2)


def test_a_handled_block_is_found_from_the_accelerometer_or_the_gyro():
    rec = _still()
    assert not touched_blocks(rec).any()
    rec.columns["acc_x_g"][3000:3020] += np.linspace(0, 0.5, 20)
    rec.columns["gyro_y_dps"][5000:5010] += 5.0
    assert np.flatnonzero(touched_blocks(rec)).tolist() == [50, 83]


def test_a_px4_yaml_brings_its_own_data_settings_and_a_bare_one_train_pys_dt_dt():
    from omegaconf import OmegaConf

    data = OmegaConf.load(campaign_table.DATA_CONF)  # as train.py composes conf/data
    taken = {"rate_tau_s": float(data.rate_tau_s), "val_startup_s": float(data.val_startup_s)}
    spec, options = campaign_table._model_yaml("px4")
    assert spec._target_ == "gyronet.model.px4.Px4Cubic"
    assert options == {**taken, "features": [{"kind": "temp"}], "block_s": 1e-6, "run_offsets": False,
                       "in_sample": True}
    spec, options = campaign_table._model_yaml("poly3")
    assert "_target_" in spec and options == taken
    with pytest.raises(GyronetError, match="no conf/model/cubic.yaml"):
        campaign_table._model_yaml("cubic")


def test_a_variant_brings_its_own_model_overrides_and_data_settings():
    from omegaconf import OmegaConf

    variants = OmegaConf.load(campaign_table.MODEL_CONF.parents[1] / "conf" / "campaign.yaml").variants
    default_spec, default_options = campaign_table._model_yaml("default")
    spec, options = campaign_table._variant("default_screened_within", variants)
    assert spec == default_spec and options == {**default_options, "val_startup_s": 0}
    spec, options = campaign_table._variant("hybrid", variants)
    assert spec.select_capacity is False and options == default_options


@needs_cats
def test_the_real_runs_floors_and_the_cubic_held_out_as_the_study_found():
    spec, px4_options = campaign_table._model_yaml("px4")
    table = held_out_table([str(p) for p in RUNS], {"raw": None, "poly3": lambda n: TempPolynomial(n),
                                                     "px4": lambda n: instantiate(spec, n_inputs=n)},
                           data_options={"px4": px4_options})
    # PROVENANCE.md: 0.012 / 0.013 / 0.018 deg/s at 60 s in the cold dwell
    np.testing.assert_allclose(table["floor_dps"]["cats_run_z_down"], [0.012, 0.013, 0.018], rtol=0.1)
    assert table["touched_blocks"] == {"cats_run_z_down": 0, "cats_run_y_down": 0}
    cubic = table["rows"]["poly3 | startup 600 s"]["ratio"]
    # the published table these functions made (docs/results/real-data.md, its command): it still comes out so
    np.testing.assert_allclose(cubic["cats_run_z_down"], [7.83, 4.37, 1.33], rtol=0.05)
    np.testing.assert_allclose(cubic["cats_run_y_down"], [6.17, 8.77, 3.24], rtol=0.05)
    # PX4's script fitted on every sample of the other run (the same table's px4 row): worse than poly3
    px4 = table["rows"]["px4 | startup 600 s"]["ratio"]
    np.testing.assert_allclose(px4["cats_run_z_down"], [10.12, 4.43, 1.56], rtol=0.05)
    markdown = to_markdown(table)
    assert "| poly3 | startup 600 s |" in markdown and markdown.count("\n|") >= 5


def test_a_run_without_a_cold_dwell_long_enough_for_its_floor_is_one_line():
    time_s = np.arange(0.0, 1000.0, 0.5)  # a steady ramp: a few seconds within 1 degC of its coldest
    columns = {"time_s": time_s, "temp_c": 5.0 + 0.05 * time_s,
               **{f"gyro_{a}_dps": np.zeros_like(time_s) for a in "xyz"}}
    with pytest.raises(GyronetError, match=r"ramp.csv: its cold dwell .* is 40 samples, too short") as err:
        floor_dps(Recording(columns, {"fs_hz": "2"}, "ramp.csv"))
    assert "\n" not in str(err.value)


def test_runs_are_checked_as_train_py_checks_them_before_any_fold(paper_csv, cycle_csv, tmp_path):
    """Two runs named run.csv lost one from the table and scored the other in sample; a copy scored in sample; a
    glitch row gave no cold dwell; a short run gave NaN cells."""
    from gyronet.recordings.data import load_recording, write_recording

    for folder, source in (("a", paper_csv), ("b", cycle_csv)):
        (tmp_path / folder).mkdir()
        (tmp_path / folder / "run.csv").write_bytes(source.read_bytes())
    table = held_out_table([tmp_path / "a" / "run.csv", tmp_path / "b" / "run.csv"], {"raw": None},
                           startup_s=60, score_from_s=60)
    assert list(table["runs"]) == ["run", "run_1"] and all(len(r["ratio"]) == 2 for r in table["rows"].values())
    copy = tmp_path / "copy.csv"
    copy.write_bytes(paper_csv.read_bytes())
    with pytest.raises(GyronetError, match="holds the same samples"):
        held_out_table([paper_csv, copy], {"raw": None})
    cycle = load_recording(cycle_csv)
    columns = dict(cycle.columns)
    columns["temp_c"] = columns["temp_c"].copy()
    columns["temp_c"][len(columns["temp_c"]) // 2] = -150.0  # one glitch: far below the cold dwell
    write_recording(tmp_path / "glitch.csv", columns, cycle.meta)
    table = held_out_table([paper_csv, tmp_path / "glitch.csv"], {"raw": None}, startup_s=60, score_from_s=60)
    assert np.all(np.isfinite(table["floor_dps"]["glitch"]))
    short = {k: v[:200] for k, v in cycle.columns.items()}  # 100 s at 2 Hz
    write_recording(tmp_path / "short.csv", short, cycle.meta)
    with pytest.raises(GyronetError, match="short.csv: 100 s long"):
        held_out_table([paper_csv, tmp_path / "short.csv"], {"raw": None}, startup_s=60, score_from_s=60)


def test_the_command_takes_data_paths_as_train_py_does_and_runs_still(paper_csv, cycle_csv, tmp_path):
    """campaign_table.py refused data.paths, the contract's spelling, as an unknown setting."""
    import json
    import subprocess

    root = Path(__file__).resolve().parents[1]
    paths = f"[{paper_csv},{cycle_csv}]"
    for key in ("data.paths", "runs"):
        out = tmp_path / key / "t.md"
        done = subprocess.run([sys.executable, "scripts/campaign_table.py", f"{key}={paths}", "models=[raw]",
                               f"output={out}", "startup_s=60", "score_from_s=60", f"hydra.run.dir={tmp_path / key}"],
                              cwd=root, capture_output=True, text=True)
        assert done.returncode == 0, done.stderr
        assert set(json.loads(out.with_suffix(".json").read_text())["runs"]) == {"paper", "cycle"}
    for args, message in [((), "error: no runs given: add 'data.paths=[A.csv,B.csv]' (two or more runs of one unit)"),
                          ((f"data.paths={paths}", f"runs={paths}"), "error: give the runs once: data.paths=[...] "
                                                                     "(runs=[...] is its older spelling)")]:
        refused = subprocess.run([sys.executable, "scripts/campaign_table.py", *args,
                                  f"hydra.run.dir={tmp_path / 'refused'}"], cwd=root, capture_output=True, text=True)
        assert refused.returncode == 2 and refused.stderr.strip().splitlines() == [message]


def test_the_command_runs_without_variants(paper_csv, cycle_csv, tmp_path):
    """'~variants' (no variants at all) ended in "Key 'variants' is not in struct" once a model was named."""
    import subprocess

    done = subprocess.run([sys.executable, "scripts/campaign_table.py", f"data.paths=[{paper_csv},{cycle_csv}]",
                           "~variants", "models=[poly3]", f"output={tmp_path / 't.md'}", "startup_s=60",
                           "score_from_s=60", f"hydra.run.dir={tmp_path}"],
                          cwd=Path(__file__).resolve().parents[1], capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    assert "| poly3 |" in (tmp_path / "t.md").read_text()
