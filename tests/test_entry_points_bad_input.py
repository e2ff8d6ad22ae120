"""Bad input found by fuzzing the offline entry points: each case is one line and exit 2 (or a one-line error from
the library), never a traceback, and never an edited or wrong value used silently."""
from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from gyronet.bundle.compensator import build_meta
from gyronet.bundle.io import save_bundle
from gyronet.errors import BundleError
from gyronet.training.pipeline import model_info


@pytest.fixture(scope="module")
def tiny_bundle(tmp_path_factory) -> Path:
    """A linear model on temperature alone: what a cubic can express, saved with checksums."""
    from gyronet.model.baselines import LinearFeatures

    torch.manual_seed(0)
    model = LinearFeatures(1)
    model.fit_closed_form(torch.randn(40, 1, dtype=torch.float64), torch.randn(40, 3, dtype=torch.float64))
    meta = build_meta([{"kind": "temp"}], ["temp_c"], 2.0, (0.0, 40.0),
                      ["time_s", "temp_c", "gyro_x_dps", "gyro_y_dps", "gyro_z_dps"], "0" * 64, model_info(model))
    return save_bundle(model, meta, tmp_path_factory.mktemp("tiny") / "compensator")


def _edited(bundle: Path, folder: Path, **fields) -> Path:
    import shutil

    copy = Path(shutil.copytree(bundle, folder / "edited"))
    meta = json.loads((copy / "meta.json").read_text())
    meta.update(fields)
    (copy / "meta.json").write_text(json.dumps(meta))
    return copy


@pytest.mark.parametrize("fields, reason", [({"model": None}, "'model' must be an object"),
                                            ({"sha256": "abc"}, "'sha256' must map file names"),
                                            ({"output": 5}, "'output' must be a string")])
def test_params_export_refuses_an_edited_meta_as_compensate_does(tiny_bundle, tmp_path, fields, reason):
    """export.py format=px4|ardupilot read the bundle without the schema: ``model: null`` was an AttributeError,
    a damaged ``sha256`` or ``output`` was exported without a word."""
    from gyronet.deploy.params import export_params

    edited = _edited(tiny_bundle, tmp_path, **fields)
    for stack in ("px4", "ardupilot"):
        with pytest.raises(BundleError, match=reason):
            export_params(edited, tmp_path / f"{stack}.params", stack)
    export_params(tiny_bundle, tmp_path / "good.params", "px4")  # the unedited bundle still exports


def test_format_rosbag_on_a_file_that_is_no_bag_is_one_line(tmp_path):
    """convert.py format=rosbag (and allan.py on such a path) on a CSV: rosbags' AnyReaderError escaped as a traceback."""
    from gyronet.errors import RecordingError
    from gyronet.recordings.importers.rosbag import import_rosbag

    path = tmp_path / "F.csv"
    path.write_text("time_s,temp_c,gyro_x_dps,gyro_y_dps,gyro_z_dps\n0,20,0,0,0\n0.5,20,0,0,0\n")
    with pytest.raises(RecordingError, match=r"F.csv: unreadable ROS bag \(AnyReaderError"):
        import_rosbag(path)


@pytest.mark.parametrize("per_decade", [0, -3])
def test_allan_refuses_fewer_than_one_tau_per_decade(per_decade):
    """allan.py per_decade=0 wrote a one-point curve with every figure n/a and exit 0; -3 was a numpy traceback."""
    import numpy as np

    from gyronet.allan import allan_report
    from gyronet.errors import GyronetError

    time_s = np.arange(2000) / 10.0
    rate = np.random.default_rng(0).normal(0.0, 0.1, (2000, 3))
    with pytest.raises(GyronetError, match=f"per_decade must be .* at least 1, got {per_decade}"):
        allan_report(time_s, rate, per_decade=per_decade)
    assert len(allan_report(time_s, rate, per_decade=1)["x"]["taus_s"]) > 1


@pytest.mark.parametrize("static", [[float("nan"), 0.0, 0.0], [0.0, float("inf"), 0.0]])
def test_a_start_up_offset_refuses_a_static_rate_that_is_not_finite(static):
    """compensate.py startup.static_rate_dps=[nan,0,0] wrote NaN for every x output after the window, exit 0."""
    from gyronet.bundle.startup import StartupOffset
    from gyronet.errors import GyronetError

    with pytest.raises(GyronetError, match="startup.static_rate_dps needs 3 finite numbers"):
        StartupOffset(60.0, static_rate_dps=static)


# ---------------------------------------------------------------- the scripts' settings, in-process

SCRIPTS = Path(__file__).resolve().parents[1] / "scripts"


def _script_error(capsys, script: str, config_dir: str, overrides: list[str]) -> str:
    """The one line a script's task (as Hydra runs it, settings checked first) prints for ``overrides``, exit 2."""
    import importlib.util
    import sys

    from hydra import compose, initialize_config_dir

    sys.path.insert(0, str(SCRIPTS))
    try:
        spec = importlib.util.spec_from_file_location(f"_script_{script}", SCRIPTS / f"{script}.py")
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        with initialize_config_dir(str(SCRIPTS.parent / "conf" / config_dir), version_base="1.3"):
            cfg = compose(script, overrides=overrides)
        capsys.readouterr()
        with pytest.raises(SystemExit) as stop:
            module.main.__wrapped__(cfg)
    finally:
        sys.path.remove(str(SCRIPTS))
    lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert stop.value.code == 2 and len(lines) == 1 and lines[0].startswith("error: "), lines
    return lines[0]


@pytest.mark.parametrize("override, reason", [
    ("model=null", "model must be a string, got None"), ("input=[a,b]", "input must be a string"),
    ("output=null", "output must be a string, got None"), ("startup=5", "startup must be a mapping, got 5"),
    ("resample=maybe", "resample must be true or false, got 'maybe'")])
def test_compensate_refuses_settings_of_the_wrong_type(capsys, tmp_path, override, reason):
    """Paths that are null or a list were a TypeError traceback, startup=5 a ValueError; resample=maybe ran as true."""
    base = {"model": f"model={tmp_path}/b", "input": f"input={tmp_path}/F.csv", "output": f"output={tmp_path}/O.csv"}
    base[override.split("=")[0]] = override
    line = _script_error(capsys, "compensate", "deploy", list(base.values()))
    assert reason in line


@pytest.mark.parametrize("override", ["input=null", "output=null"])
def test_allan_refuses_a_path_that_is_null(capsys, tmp_path, override):
    """allan.py input=null or output=null was a TypeError traceback."""
    base = {"input": f"input={tmp_path}/F.csv", "output": f"output={tmp_path}/A.json"}
    base[override.split("=")[0]] = override
    assert f"{override.split('=')[0]} must be a string, got None" in _script_error(capsys, "allan", "", list(base.values()))


@pytest.mark.parametrize("override, reason", [
    ("score_from_s=abc", "score_from_s must be a number, got 'abc'"),
    ("startup.still_s=abc", "startup.still_s must be a number or null, got 'abc'"),
    ("+bundles={A: 5}", "bundles.A must be a bundle folder, got 5"),
    ("data.paths=F.csv", "data.paths must be a list or null, got 'F.csv'")])
def test_table_refuses_settings_of_the_wrong_type(capsys, tmp_path, override, reason):
    """score_from_s=abc and startup.still_s=abc were ValueError tracebacks, a bundle given as a number a TypeError;
    data.paths=F.csv was read letter by letter ("two runs share a name (, t, m, p, ...)")."""
    base = [f"input={tmp_path}/F.csv", f"output={tmp_path}/T.md"]
    if override.startswith("data.paths"):
        base = base[1:]
    line = _script_error(capsys, "table", "deploy", [*base, override])
    assert reason in line


@pytest.mark.parametrize("name", ["", ".", ".."])
def test_an_output_path_that_names_a_folder_is_one_line_naming_it(tmp_path, monkeypatch, name):
    """compensate.py, allan.py, convert.py, table.py with output= (or output=.): "<cwd>/..x1y2.part: Device or
    resource busy", a line naming a temporary file instead of the output and its problem."""
    from gyronet.atomic import OutputError, write_text

    monkeypatch.chdir(tmp_path)
    with pytest.raises(OutputError, match=r"cannot write \(it is a folder\)"):
        write_text(name, "x")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("block_s", [0, -5])
def test_train_refuses_a_held_out_block_that_is_not_positive(capsys, tmp_path, block_s):
    """train.py eval.block_s=-5 reported a "-5 s residual RMS" (per sample) into the log and report.json, exit 0."""
    line = _script_error(capsys, "train", "", [f"data.path={tmp_path}/F.csv", f"eval.block_s={block_s}",
                                               f"eval.paths=[{tmp_path}/G.csv]"])
    assert f"eval.block_s must be > 0 s (the held-out residual's averaging block), got {block_s}" in line


@pytest.mark.parametrize("output", ["", " "])
def test_export_refuses_an_empty_output(capsys, tmp_path, output):
    """export.py format=c output= wrote gyronet_compensator.h and .c into the working directory, exit 0."""
    line = _script_error(capsys, "export", "deploy", [f"model={tmp_path}/D", "format=c", f"output='{output}'"])
    assert "output is empty" in line
