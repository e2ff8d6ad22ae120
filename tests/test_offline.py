"""The offline path: the sampling rate is checked against the bundle's, outputs are written whole
or not at all, and compensated files read back within 1e-12."""
import errno
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from gyronet.atomic import OutputError
from gyronet.bundle.compensator import Compensator, RateChangeError
from gyronet.recordings.data import AXES, load_recording
from gyronet.errors import BundleError, exit_on_error
from gyronet.bundle.offline import compensate_file, write_compensated
from gyronet.sim import simulate, write_simulation
from gyronet.training.train import block_rmse

ROOT = Path(__file__).resolve().parents[1]
DURATION_S = 4 * 3600.0


@pytest.fixture(scope="module")
def cycles():
    """The bundle's sensor through the held-out thermal cycle, at its own 2 Hz and at 10 Hz."""
    return {fs: simulate("cycle", fs_hz=fs, seed=2, sensor_seed=0, duration_s=DURATION_S) for fs in (2.0, 10.0)}


def _drift_error_dps(compensator: Compensator, sim) -> float:
    """Worst axis' 60 s block RMS of estimated minus true drift, deg/s."""
    compensator.reset()
    drift_hat = compensator.process(sim.recording).drift_dps
    true = np.column_stack([sim.truth[f"drift_{a}_dps"] for a in AXES])
    return float(block_rmse(sim.recording["time_s"], drift_hat - true, 60.0).max())


def test_other_rate_is_refused_with_both_rates_and_the_fix(bundle):
    compensator = Compensator.load(bundle)
    with pytest.raises(BundleError) as info:
        compensator.use_input_rate(10.0, resample=False, source="F.csv")
    message = str(info.value)
    assert "\n" not in message and message.startswith("F.csv: ")
    assert "10 Hz" in message and "2 Hz" in message and "resample=true" in message
    for resample in (False, True):  # stamps in milliseconds: 0.002 Hz is named as such, never resampled
        with pytest.raises(BundleError, match="1000x slower .* is time_s in milliseconds"):
            compensator.use_input_rate(0.002, resample=resample, source="F.csv")
    compensator.use_input_rate(2.09, resample=False, source="F.csv")  # within 5 %: a clock error
    assert compensator.fs_hz == 2.0
    for bad in (0.0, -2.0, float("nan"), float("inf")):
        with pytest.raises(BundleError, match="not a rate"):
            compensator.use_input_rate(bad, resample=True, source="F.csv")


def test_resample_gives_what_the_bundle_gives_at_its_own_rate(bundle, cycles):
    """A 2 Hz bundle on 10 Hz data: measured here, rebuilding the filters at 10 Hz matches 2 Hz data
    to within a percent, so no averaging to the bundle's rate is needed; not resampling is 5x worse."""
    at_own_rate = _drift_error_dps(Compensator.load(bundle), cycles[2.0])
    with pytest.raises(RateChangeError, match="from 2 Hz to 10 Hz"):  # what compensate.py did before: 5x worse
        _drift_error_dps(Compensator.load(bundle), cycles[10.0])  # (the rate watch finds it after 48 samples)
    compensator = Compensator.load(bundle)
    compensator.use_input_rate(10.0, resample=True, source="F.csv")
    resampled = _drift_error_dps(compensator, cycles[10.0])
    assert resampled < 1.1 * at_own_rate, (resampled, at_own_rate)
    compensator.use_input_rate(2.0, resample=False, source="F.csv")  # back at the bundle's rate
    assert _drift_error_dps(compensator, cycles[2.0]) == at_own_rate


def test_resample_is_refused_for_a_kalman_stage(bundle, cycles):
    from gyronet.bundle.io import load_bundle
    from gyronet.model.kalman import KalmanStage, identify

    model, meta, _ = load_bundle(bundle)
    residual = np.random.default_rng(0).normal(0, 0.05, (4000, 3))
    kalman = KalmanStage(identify(residual, meta["fs_hz"])).to_dict()
    compensator = Compensator(model, {**meta, "kalman": True}, kalman, source=bundle)
    compensator.use_input_rate(2.0, resample=True, source="F.csv")
    with pytest.raises(BundleError, match="Kalman stage identified at 2 Hz, which cannot be resampled"):
        compensator.use_input_rate(10.0, resample=True, source="F.csv")


def test_compensate_file_checks_the_rate(bundle, cycles, tmp_path):
    path = tmp_path / "fast.csv"
    write_simulation(cycles[10.0], path)
    with pytest.raises(BundleError, match="sampled at 10 Hz, but the bundle .* was trained at 2 Hz"):
        compensate_file(bundle, path, tmp_path / "o.csv")
    assert not (tmp_path / "o.csv").exists()
    compensate_file(bundle, path, tmp_path / "o.csv", resample=True)
    written = load_recording(tmp_path / "o.csv", required=("time_s", "gyro_x_dps"))
    assert len(written) == len(cycles[10.0].recording["time_s"])


def test_a_file_in_kelvin_is_refused_and_one_glitch_in_a_hundred_is_not(bundle, cycles, tmp_path):
    """Kelvin gave every row bad_input and a number from the filters' prior, exit 0; training refused it."""
    from gyronet.errors import RecordingError

    kelvin, glitched = tmp_path / "kelvin.csv", tmp_path / "glitched.csv"
    write_simulation(cycles[2.0], kelvin)
    lines = kelvin.read_text().splitlines(keepends=True)
    header = next(i for i, line in enumerate(lines) if not line.startswith("#"))
    assert lines[header].split(",")[1] == "temp_c"

    def with_temp(rows, temp):
        out = list(lines)
        for i in rows:
            cells = out[i].split(",")
            cells[1] = temp(float(cells[1]))
            out[i] = ",".join(cells)
        return "".join(out)

    kelvin.write_text(with_temp(range(header + 1, len(lines)), lambda c: repr(c + 273.15)))
    with pytest.raises(RecordingError, match=r"temp_c = 2\d\d\.\d+ degC is outside any sensor's range"):
        compensate_file(bundle, kelvin, tmp_path / "o.csv")
    assert not (tmp_path / "o.csv").exists()
    glitches = range(header + 6, len(lines), 100)  # one row in a hundred: glitches the guard leaves out, flagged
    glitched.write_text(with_temp(glitches, lambda c: "500"))
    counts = compensate_file(bundle, glitched, tmp_path / "o.csv")
    assert counts["n_bad_input"] == len(glitches)
    short = tmp_path / "short.csv"  # one glitch in 60 rows (1.7 %): a glitch still, not a file in Kelvin
    short.write_text("".join(with_temp([header + 30], lambda c: "1e6").splitlines(keepends=True)[:header + 61]))
    assert compensate_file(bundle, short, tmp_path / "o2.csv")["n_bad_input"] == 1


def _run_compensate(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "scripts/compensate.py", *args], cwd=ROOT, capture_output=True, text=True)


def test_compensate_script_passes_resample(bundle, cycles, tmp_path):
    path = tmp_path / "fast.csv"
    write_simulation(cycles[10.0], path)
    out, hydra_dir = tmp_path / "o.csv", tmp_path / "hydra"
    proc = _run_compensate(f"model={bundle}", f"input={path}", f"output={out}", f"hydra.run.dir={hydra_dir}")
    assert proc.returncode == 2 and proc.stderr.strip().count("\n") == 0 and "resample=true" in proc.stderr
    proc = _run_compensate(f"model={bundle}", f"input={path}", f"output={out}", "resample=true",
                           f"hydra.run.dir={hydra_dir}")
    assert proc.returncode == 0, proc.stderr
    assert out.is_file() and (hydra_dir / ".hydra" / "config.yaml").is_file()


def test_full_disk_leaves_no_half_file_and_one_line(bundle, cycle_csv, tmp_path, monkeypatch, capsys):
    out = tmp_path / "o.csv"
    out.write_text("previous\n")
    real_open = open

    class FullDisk:
        """A file on a disk that fills up after the first megabyte."""

        def __init__(self, handle):
            self.handle = handle

        def write(self, data):
            if self.handle.tell() + len(data) > 1 << 20:
                self.handle.write(data[: (1 << 20) - self.handle.tell()])
                raise OSError(errno.ENOSPC, "No space left on device")
            return self.handle.write(data)

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.handle.close()

    def fake_open(file, mode="r", *args, **kwargs):
        handle = real_open(file, mode, *args, **kwargs)
        return FullDisk(handle) if "w" in mode and Path(file).parent == tmp_path else handle

    monkeypatch.setattr("builtins.open", fake_open)
    with pytest.raises(OutputError, match="no space left on the device"):
        compensate_file(bundle, cycle_csv, out)
    with pytest.raises(SystemExit) as info:
        exit_on_error(compensate_file)(bundle, cycle_csv, out)
    monkeypatch.undo()
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: {out}: cannot write") and err.count("\n") == 1
    assert out.read_text() == "previous\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["o.csv"]


@pytest.mark.parametrize("with_nan", [False, True])
def test_compensated_file_reads_back_within_1e12(tmp_path, with_nan):
    rng = np.random.default_rng(1)
    columns = {"time_s": np.arange(3000) / 10.0, "gyro_x_dps": rng.normal(0, 0.3, 3000),
               "gyro_y_dps": np.r_[1.5e6, rng.normal(0, 1e-3, 2999)], "gyro_z_dps": rng.normal(0, 1, 3000) * 1e-200,
               "out_of_range": (rng.random(3000) > 0.9).astype(np.int8)}
    if with_nan:
        columns["gyro_x_dps"][5] = np.nan  # the pandas path
    frame = pd.read_csv(write_compensated(tmp_path / "o.csv", columns, tmp_path), comment="#")
    for key, value in columns.items():
        np.testing.assert_allclose(frame[key].to_numpy(), value, rtol=1e-12, atol=0, equal_nan=True)


def test_json_outputs_are_strict_json_any_reader_takes(tmp_path):
    """diagnosis.json, the tables' JSON, kalman.json and report.json: NaN and inf as null, numpy as Python."""
    import json

    from gyronet.atomic import write_json

    value = {"nan": float("nan"), "inf": np.float32(np.inf), "row": np.array([1.5, np.nan]), "n": np.int64(3),
             "ok": np.bool_(True), "pair": (np.float64(-np.inf), 2), 7: "key"}
    write_json(tmp_path / "v.json", value)
    text = (tmp_path / "v.json").read_text()
    assert "NaN" not in text and "Infinity" not in text
    assert json.loads(text) == {"nan": None, "inf": None, "row": [1.5, None], "n": 3, "ok": True,
                                "pair": [None, 2], "7": "key"}
