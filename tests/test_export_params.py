"""PX4 and ArduPilot parameters from a bundle (gyronet/deploy/params.py, scripts/export.py): the .params
file read back gives the bundle's curve to the float precision it keeps; what it cannot express is refused."""
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from gyronet.bundle.compensator import build_meta
from gyronet.training.dataset import DriftData
from gyronet.deploy.params import (Cubic, ardupilot_cubic, bundle_cubic, export_params, px4_cubic, read_params,
                                   steady_features)
from gyronet.errors import BundleError, GyronetError
from gyronet.bundle.io import read_bundle, save_bundle
from gyronet.training.pipeline import model_info, train_run
from gyronet.model.px4 import Px4Cubic, Px4Onboard

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def px4_bundle(tmp_path_factory, paper_csv) -> Path:
    """model=px4 as conf/model/px4.yaml trains it: the whole recording, every sample."""
    out = tmp_path_factory.mktemp("px4")
    data = DriftData(str(paper_csv), features=[{"kind": "temp"}], block_s=1e-6, val_path=str(paper_csv))
    train_run(data, Px4Cubic(1), None, out, {"progress": False})
    return out / "compensator"


def bundle_curve(bundle: Path, temp_c: np.ndarray) -> np.ndarray:
    loaded = read_bundle(bundle)
    with torch.no_grad():
        return loaded.model(torch.as_tensor(steady_features(loaded.meta, temp_c))).numpy()


def float32_tolerance(cubic: Cubic) -> float:
    """What rounding the coefficients and temperatures to float32 can move the curve by, deg/s."""
    span = max(abs(cubic.temp_max_c - cubic.temp_ref_c), abs(cubic.temp_min_c - cubic.temp_ref_c))
    slope = sum(k * np.abs(cubic.coef_dps[k]).max() * span ** (k - 1) for k in range(1, 4))
    size = sum(np.abs(cubic.coef_dps[k]).max() * span**k for k in range(4))
    return 2.0 ** -23 * (size + slope * (abs(cubic.temp_ref_c) + span))


@pytest.fixture(scope="module")
def poly3_bundle(tmp_path_factory, paper_csv) -> Path:
    """model=poly3 as train.py trains it (10 s blocks of the training split)."""
    from gyronet.model.baselines import TempPolynomial

    out = tmp_path_factory.mktemp("poly3")
    data = DriftData(str(paper_csv))
    train_run(data, TempPolynomial(data.n_features), None, out, {"progress": False})
    return out / "compensator"


def test_poly3_params_read_back_to_the_bundles_curve_and_clamp(poly3_bundle, tmp_path):
    summary = export_params(poly3_bundle, tmp_path / "poly3.params", "px4")
    from_params = px4_cubic(read_params(tmp_path / "poly3.params"))
    low, high = json.loads((poly3_bundle / "meta.json").read_text())["temp_range_c"]
    # poly3 clamps to the range of its training blocks, inside the recording's
    assert low < from_params.temp_min_c < low + 0.5 and high - 0.5 < from_params.temp_max_c < high
    grid = np.linspace(low - 10, high + 10, 3001)
    difference = np.abs(from_params(grid) - bundle_curve(poly3_bundle, grid)).max()
    assert difference < float32_tolerance(from_params) and difference < 1e-6
    assert max(summary["max_error_dps"].values()) < 1e-9


def test_px4_params_read_back_to_the_bundles_curve(px4_bundle, tmp_path):
    summary = export_params(px4_bundle, tmp_path / "tc.params", "px4", instance=1, device_id=2359306)
    values = read_params(tmp_path / "tc.params")
    assert values["TC_G_ENABLE"] == 1 and values["TC_G1_ID"] == 2359306 and len(values) == summary["n_params"] == 17
    lines = [line.split("\t") for line in (tmp_path / "tc.params").read_text().splitlines() if line[0] != "#"]
    assert {(f[0], f[1], f[4]) for f in lines if f[2].endswith("_ID") or f[2] == "TC_G_ENABLE"} == {("1", "1", "6")}
    assert {f[4] for f in lines if not (f[2].endswith("_ID") or f[2] == "TC_G_ENABLE")} == {"9"}
    meta = json.loads((px4_bundle / "meta.json").read_text())
    low, high = meta["temp_range_c"]
    grid = np.linspace(low - 10, high + 10, 3001)  # outside too: both clamp
    from_params = px4_cubic(values, instance=1)
    # model=px4 takes T_min, T_max from the raw samples: the exported range is the bundle's own
    assert (np.float32(from_params.temp_min_c), np.float32(from_params.temp_max_c)) == (np.float32(low),
                                                                                        np.float32(high))
    difference = np.abs(from_params(grid) - bundle_curve(px4_bundle, grid)).max()
    assert difference < float32_tolerance(from_params) and difference < 1e-6
    assert max(summary["max_error_dps"].values()) < 1e-9  # a cubic bundle is its own best cubic
    assert json.loads((tmp_path / "tc.json").read_text())["max_error_dps"] == summary["max_error_dps"]


def test_ardupilot_params_give_the_same_curve_about_35_degc(px4_bundle, tmp_path):
    export_params(px4_bundle, tmp_path / "ap.params", "ardupilot")
    values = read_params(tmp_path / "ap.params")
    assert values["INS_TCAL1_ENABLE"] == 1 and "INS_TCAL1_GYR3_Z" in values and len(values) == 12
    cubic = ardupilot_cubic(values)
    grid = np.linspace(cubic.temp_min_c - 5, cubic.temp_max_c + 5, 2001)
    # ArduPilot subtracts p(T) - p(T_cal): the constant is its boot-time gyro offset; compare shapes
    cal_c = 20.0
    ours = bundle_curve(px4_bundle, grid) - bundle_curve(px4_bundle, np.array([cal_c]))
    theirs = cubic(grid) - cubic(np.array([cal_c]))
    assert np.abs(ours - theirs).max() < 1e-5  # float32 of coefficients x 1e6 about 35 degC


def test_onboard_bundle_keeps_its_own_narrower_range_and_reference(tmp_path):
    rng = np.random.default_rng(3)
    temp = np.concatenate([np.full(30, 7.0), np.linspace(7.0, 40.0, 3000)]).astype(np.float32).astype(float)
    time_h = np.arange(len(temp)) / 3600.0
    drift = 0.01 + 0.001 * (temp - 19) + 1e-6 * (temp - 19) ** 3 + rng.normal(0, 1e-4, len(temp))
    model = Px4Onboard(2, time_index=1)
    x = torch.as_tensor(np.column_stack([temp, time_h]))
    model.fit_closed_form(x, torch.as_tensor(np.column_stack([drift, -drift, drift])))
    meta = build_meta([{"kind": "temp"}, {"kind": "time"}], ["temp_c", "age_h"], 1.0, (7.0, 40.0),
                      ["time_s", "temp_c", "gyro_x_dps", "gyro_y_dps", "gyro_z_dps"], "0" * 64, model_info(model))
    bundle = save_bundle(model, meta, tmp_path / "onboard")
    fit = bundle_cubic(bundle)
    # the clamp edges are the onboard rule's (cold soak at 7, stop past 7 + 24), not the data's 7 .. 40
    assert fit.cubic.temp_min_c == pytest.approx(float(model.temp_min_c), abs=1e-9)
    assert fit.cubic.temp_max_c == pytest.approx(float(model.temp_max_c), abs=1e-9) and fit.cubic.temp_max_c < 32
    grid = np.linspace(0, 45, 901)
    expected = model(torch.as_tensor(np.column_stack([grid, np.zeros_like(grid)]))).detach().numpy()
    assert np.abs(fit.cubic(grid) - expected).max() < 1e-9


def test_gyronets_own_model_gets_its_best_cubic_with_the_error_measured(bundle, tmp_path):
    summary = export_params(bundle, tmp_path / "rbf.params", "px4")
    meta = json.loads((bundle / "meta.json").read_text())
    grid = np.linspace(*meta["temp_range_c"], 4001)
    from_params = px4_cubic(read_params(tmp_path / "rbf.params"))
    error = np.abs(from_params(grid) - bundle_curve(bundle, grid)).max(0)
    stated = np.array([summary["max_error_dps"][a] for a in "xyz"])
    # the stated error (on its 2001-point grid) is the error of the cubic, up to grid and float32
    np.testing.assert_allclose(error, stated, rtol=0.05, atol=1e-6)
    assert np.all(stated > 1e-6)  # a network with Gaussians on temperature is no cubic


def test_bundles_a_polynomial_cannot_express_are_refused(bundle, tmp_path):
    meta = {k: v for k, v in json.loads((bundle / "meta.json").read_text()).items()
            if k not in ("format", "gyronet_version", "kalman", "sha256")}
    kalman = save_bundle(read_bundle(bundle).model, meta, tmp_path / "kf", kalman={"stage": "any"})
    with pytest.raises(BundleError, match="has a Kalman stage, which a temperature polynomial cannot express"):
        bundle_cubic(kalman)
    from gyronet.model.baselines import LinearFeatures

    aux = LinearFeatures(2)
    aux.fit_closed_form(torch.randn(40, 2, dtype=torch.float64), torch.randn(40, 3, dtype=torch.float64))
    aux_meta = build_meta([{"kind": "temp"}, {"kind": "column", "source": "vdd_v"}], ["temp_c", "vdd_v"], 1.0,
                          (0.0, 40.0), ["time_s", "temp_c", "vdd_v", "gyro_x_dps", "gyro_y_dps", "gyro_z_dps"],
                          "0" * 64, model_info(aux))
    with pytest.raises(BundleError, match="reads vdd_v, which a temperature polynomial cannot express"):
        bundle_cubic(save_bundle(aux, aux_meta, tmp_path / "aux"))
    with pytest.raises(GyronetError, match="instances 0-3"):
        export_params(bundle, tmp_path / "x.params", "px4", instance=4)


def test_a_params_file_with_a_bad_line_is_one_error(tmp_path):
    path = tmp_path / "bad.params"
    path.write_text("# Vehicle-Id Component-Id Name Value Type\n1\t1\tTC_G0_TMIN\tcold\t9\n")
    with pytest.raises(GyronetError, match=r"line 2: TC_G0_TMIN = 'cold' is not a number"):
        read_params(path)


def run_export(tmp_path: Path, *overrides: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(ROOT / "scripts" / "export.py"), f"hydra.run.dir={tmp_path}/run",
                           *overrides], capture_output=True, text=True, cwd=ROOT, timeout=300)


def test_export_command_refuses_an_unknown_format_in_one_line(tmp_path):
    failed = run_export(tmp_path, f"model={tmp_path}", "format=mavlink", f"output={tmp_path}/x.params")
    assert failed.returncode == 2 and "format must be one of px4, ardupilot, c, got 'mavlink'" in failed.stderr
    assert len(failed.stderr.strip().splitlines()) == 1


@pytest.mark.slow
def test_export_command_writes_params_and_fails_in_one_line(px4_bundle, tmp_path):
    done = run_export(tmp_path, f"model={px4_bundle}", "format=ardupilot", f"output={tmp_path}/ap.params")
    assert done.returncode == 0, done.stderr
    assert "12 parameters" in done.stdout and "largest error against the bundle's curve" in done.stdout
    assert (tmp_path / "ap.json").is_file()
    failed = run_export(tmp_path, f"model={tmp_path}/none", "format=px4", f"output={tmp_path}/x.params")
    assert failed.returncode == 2 and "not a compensator bundle" in failed.stderr, failed.stderr
    assert len(failed.stderr.strip().splitlines()) == 1 and "Traceback" not in failed.stderr


def test_an_output_that_is_not_an_export_is_never_replaced_and_ids_are_checked(px4_bundle, tmp_path):
    """output=<bundle>/model.pt replaced the model with parameters (and a recording, or the user's F.json)."""
    recording, notes = tmp_path / "rec.csv", tmp_path / "notes.json"
    recording.write_text("time_s\n0\n")
    notes.write_text("{}")
    vehicle = tmp_path / "vehicle.params"  # QGroundControl's dump of a vehicle's parameters
    vehicle.write_text("# Onboard parameters for Vehicle 1\n1\t1\tCAL_GYRO0_ID\t2359306\t6\n")
    for output, message in [(px4_bundle / "model.pt", "is inside the bundle"),
                            (recording, "exists and is not a parameter file gyronet exported"),
                            (vehicle, "exists and is not a parameter file gyronet exported"),
                            (tmp_path / "notes.params", "notes.json exists and is not an export's summary")]:
        with pytest.raises(GyronetError, match=message):
            export_params(px4_bundle, output, "px4", device_id=1)
    assert recording.read_text() == "time_s\n0\n" and notes.read_text() == "{}" and "CAL_GYRO0_ID" in vehicle.read_text()
    assert read_bundle(px4_bundle)  # intact
    for key, value in [("device_id", 2 ** 32), ("vehicle_id", 0), ("component_id", 256)]:
        with pytest.raises(GyronetError, match=f"{key} must be in"):
            export_params(px4_bundle, tmp_path / "x.params", "px4", **{key: value})
    export_params(px4_bundle, tmp_path / "x.params", "px4", device_id=2 ** 32 - 1)  # a ULog's uint32 id
    assert read_params(tmp_path / "x.params")["TC_G0_ID"] == -1  # as PX4's int32 parameter holds it
    export_params(px4_bundle, tmp_path / "x.params", "px4", device_id=1)  # its own earlier export is replaced


def test_an_option_of_the_other_kind_of_export_is_refused_not_ignored(tmp_path):
    for args, message in [(("format=c", "vehicle_id=3", "fit=px4"), "vehicle_id, fit: options of the .params formats"),
                          (("format=ardupilot", "device_id=7"), "device_id is PX4's TC_G{n}_ID; format=ardupilot"),
                          (("format=px4", "prefix=imu1"), "prefix: an option of format=c, not of format=px4"),
                          (("format=ardupilot", "temp_rate_c_per_s=5"), "temp_rate_c_per_s sets PX4's stated error")]:
        failed = run_export(tmp_path, f"model={tmp_path}", *args, f"output={tmp_path}/x.params")
        assert failed.returncode == 2 and message in failed.stderr, failed.stderr
        assert len(failed.stderr.strip().splitlines()) == 1


def test_a_curve_flat_to_rounding_beyond_its_edge_is_clamped_there():
    """A lag slot's clamp leaves 1e-16 of rounding beyond the edge: the exact test took 152 degC for 61.7 degC."""
    from gyronet.deploy.bundle_curve import clamp_range

    low, high = -38.4, 61.7
    span = high - low

    def curve(temp_c):
        t = np.asarray(temp_c, dtype=np.float64)
        ripple = np.where((t > high + 1.0) & (t < high + span - 2.0), 2e-16, 0.0)  # rounding, not at the probes
        return np.column_stack([0.5 + 0.01 * np.clip(t, low, high) + ripple] * 3)

    found_low, found_high = clamp_range(curve, low - 5.0, high + 5.0)
    assert found_low == pytest.approx(low, abs=1e-6) and found_high == pytest.approx(high, abs=1e-6)
