"""The C99 compensator (gyronet.deploy.c_export): compiled with the system C compiler, checked against Compensator.

Every bundle kind is exported, compiled with ``-std=c99 -Wall -Wextra -Werror -pedantic -O2`` and run
by ``gyronet/deploy/c/csv_driver.c`` over a recording with lost samples, a confirmed temperature
step, out-of-range temperatures and NaN / impossible inputs; its output must match
``Compensator.process`` (what compensate.py runs) to 1e-4 deg/s and its flags exactly.
"""
import json
import platform
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from gyronet.bundle.compensator import Compensator
from gyronet.recordings.data import GYRO_COLUMNS, load_recording, write_recording
from gyronet.deploy.c_export import DRIVER, write_c
from gyronet.errors import BundleError, GyronetError
from gyronet.model.features import PAPER_FEATURES
from gyronet.training.axis_lag import lagged_specs

ROOT = Path(__file__).resolve().parents[1]
CC = shutil.which("cc") or shutil.which("gcc")
CFLAGS = ["-std=c99", "-Wall", "-Wextra", "-Wdouble-promotion", "-Wfloat-equal", "-Wshadow", "-Werror", "-pedantic",
          "-O2"]  # float code stays float; no == on a float (ArduPilot builds with -Werror=float-equal)
TOL_DPS = 1e-4
AUX = "vdd_v"

needs_cc = pytest.mark.skipif(CC is None, reason="no C compiler (cc or gcc) on this machine")  # the tests that build


def _train(out: Path, csv: Path, model_factory, features=None, kalman=None, for_bundle=False) -> Path:
    from gyronet.training.dataset import DriftData
    from gyronet.training.pipeline import train_run

    data = DriftData(str(csv)) if features is None else DriftData(str(csv), features=features)
    kalman_cfg = None if kalman is None else {"enabled": True, **kalman}
    train_run(data, model_factory(data.n_features), None, out,
              {"max_epochs": 30, "progress": False, "for_bundle": for_bundle}, kalman_cfg=kalman_cfg)
    return out / "compensator"


def _train_members(out: Path, csv: Path, lagged: bool = False) -> Path:
    """The default's three starts, each kept (equal weights): an error bar with members in the bundle
    (``lagged``: y reading its inputs 20 s behind the die, as ``gyronet.training.axis_lag`` builds it)."""
    from gyronet.training import starts
    from gyronet.model.rbf import RBFNet

    features = [*PAPER_FEATURES, *lagged_specs(20.0, 5.0)] if lagged else None
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(starts, "stack_weights", lambda *residuals: np.full((len(residuals), 3), 1.0 / len(residuals)))
        return _train(out, csv, lambda n: RBFNet(n, 3, 6, rbf_inputs=[0], linear=True, temp_degree=3, clamp=True,
                                                 refit_all=True, validate_init=True,
                                                 axis_columns=_y_lagged(n) if lagged else None),
                      features=features, for_bundle=True)


def _y_lagged(n: int) -> list:
    """Axis y reads columns 3-5 (temperature, dT/dt, T*dT/dt 20 s behind the die) in the first three slots."""
    return [list(range(n)), [3, 4, 5, *range(3, n)], list(range(n))]


@pytest.fixture(scope="module")
def aux_csv(tmp_path_factory, paper_csv) -> Path:
    """The paper recording with a supply-voltage column (an aux input) that sags as the board warms."""
    recording = load_recording(paper_csv)
    columns = dict(recording.columns)
    columns[AUX] = 3.3 - 0.002 * (columns["temp_c"] - 25.0) + 1e-4 * np.sin(columns["time_s"] / 50.0)
    path = tmp_path_factory.mktemp("aux") / "aux.csv"
    write_recording(path, columns, {"fs_hz": "2"})
    return path


@pytest.fixture(scope="module")
def bundles(tmp_path_factory, bundle, paper_csv, aux_csv) -> dict:
    """One bundle of every kind: default RBFNet, with Kalman stages, the paper's RBF, poly3, lsq, every feature kind."""
    from gyronet.model.baselines import LinearFeatures, TempPolynomial
    from gyronet.model.px4 import Px4Cubic
    from gyronet.model.rbf import RBFNet

    root = tmp_path_factory.mktemp("c_bundles")
    default = lambda n: RBFNet(n, 3, 8, rbf_inputs=[0], linear=True, temp_degree=3, clamp=True)  # noqa: E731
    every_kind = [{"kind": "temp"}, {"kind": "rate", "tau_s": 5.0}, {"kind": "product"},
                  {"kind": "lag", "tau_s": 600.0}, {"kind": "column", "source": AUX, "tau_s": 30.0},
                  {"kind": "column", "source": AUX}, {"kind": "rate", "source": AUX, "tau_s": 20.0},
                  {"kind": "hysteresis", "width": 0.5}, {"kind": "power", "exponent": 4, "centre": 10.0},
                  {"kind": "time", "tau_s": 3600.0}, {"kind": "time"}]
    return {
        "default": bundle,
        "kalman": _train(root / "kalman", paper_csv, default, kalman={"mode": "smooth", "q_rate_dps2_per_s": 0.01}),
        # a narrow rate bandwidth: a long gain transient, and the drift estimate removed
        "kalman_rate": _train(root / "kalman_rate", paper_csv, default,
                              kalman={"mode": "rate", "q_rate_dps2_per_s": 1e-6}),
        "paper_rbf": _train(root / "rbf", paper_csv, lambda n: RBFNet(n, 3, 32, rbf_inputs=None)),
        "poly3": _train(root / "poly3", paper_csv, lambda n: TempPolynomial(n, 3, 3)),
        "px4": _train(root / "px4", paper_csv, lambda n: Px4Cubic(n, 3)),  # model=px4: PX4's own script's cubic
        "lsq": _train(root / "lsq", paper_csv, lambda n: LinearFeatures(n, 3)),
        "aux": _train(root / "aux", aux_csv, default, features=every_kind),
        "members": _train_members(root / "members", paper_csv),
        "axis_lag": _train(root / "axis_lag", paper_csv, lambda n: RBFNet(
            n, 3, 8, rbf_inputs=[0], linear=True, temp_degree=3, clamp=True, axis_columns=_y_lagged(n)),
            features=[*PAPER_FEATURES, *lagged_specs(20.0, 5.0)]),
        "members_axis_lag": _train_members(root / "members_axis_lag", paper_csv, lagged=True),
    }


def _columns(csv: Path) -> dict:
    return {k: np.array(v, dtype=np.float64) for k, v in load_recording(csv).columns.items()}


def _hard(columns: dict) -> dict:
    """Lost samples (bridged, restarted, an hour), bad rows first, NaN and impossible values, a confirmed step,
    repeated stamps."""
    n = len(columns["time_s"])
    keep = np.ones(n, dtype=bool)
    keep[1000:1002] = False  # 1.5 s: bridged by the rate tracker
    keep[2000:2011] = False  # 6 s: longer than its tau, a restart
    keep[5000:12200] = False  # an hour
    out = {k: v[keep].copy() for k, v in columns.items()}
    temp, gyro_x, gyro_z = out["temp_c"], out[GYRO_COLUMNS[0]], out[GYRO_COLUMNS[2]]
    temp[:3] = np.nan  # rejected before any accepted sample
    temp[[300, 301, 7000]] = np.nan
    temp[[400, 8000]] = 1e6  # no sensor reads that
    temp[9000] += 20.0  # a jump no thermal mass allows
    # a real step, confirmed after 5 samples and 2 s, where it pushes the top beyond the trained range
    temp[int(np.argmax(temp > np.nanmax(temp[temp < 1e3]) - 4.0)):] += 6.0
    gyro_x[[500, 20000]] = np.nan
    gyro_z[[600, 600 + 1, 25000]] = 1e5
    out["time_s"][[350, 21000, 21001]] = np.nan, np.inf, np.inf  # stamps that are no time: lost samples (two infs
    # in a row: inf - inf raised FE_INVALID in the rate watch)
    out["time_s"][15000:15010] = out["time_s"][15000]  # a FIFO's batch stamped once: no rate, no division by zero
    if AUX in out:
        out[AUX][[700, 26000]] = np.nan
    return out


def _python(bundle: Path, columns: dict, still_s: float = 0.0):
    compensator = Compensator.load(bundle)
    compensator.use_startup(still_s)
    compensator.reset()
    return compensator.process(columns)


def _build(bundle: Path, work: Path) -> tuple[Path, dict]:
    summary = write_c(bundle, work / "c")
    obj = work / "gyronet_compensator.o"
    subprocess.run([CC, *CFLAGS, "-c", str(work / "c" / "gyronet_compensator.c"), "-o", str(obj)], check=True)
    exe = work / "driver"
    # with floating-point traps on (as ArduPilot's SITL runs): NaN input must not raise FE_INVALID
    trap = ["-DGYRONET_TRAP_FP"] if platform.libc_ver()[0] == "glibc" else []  # feenableexcept is glibc's
    subprocess.run([CC, *CFLAGS, *trap, "-I", str(work / "c"), str(DRIVER), str(obj), "-lm", "-o", str(exe)], check=True)
    return exe, summary


def _run_c(exe: Path, columns: dict, aux: list, work: Path, still_s: float = 0.0) -> np.ndarray:
    names = ["time_s", "temp_c", *GYRO_COLUMNS, *aux]
    np.savetxt(work / "in.csv", np.column_stack([columns[c] for c in names]), delimiter=",", fmt="%.17g",
               header=",".join(names), comments="")
    subprocess.run([str(exe), str(work / "in.csv"), str(work / "out.csv"), "1", repr(still_s)], check=True,
                   capture_output=True)
    return np.loadtxt(work / "out.csv", delimiter=",", skiprows=1, ndmin=2)


def _check(c_out: np.ndarray, py) -> None:
    flags = py.out_of_range.astype(int) + 2 * py.bad_input.astype(int)
    np.testing.assert_array_equal(c_out[:, 3].astype(int), flags)
    error = np.abs(c_out[:, :3] - py.rate_dps)
    assert np.all(np.isfinite(c_out[:, :3]))
    print(f"max |C - Python| {error.max():.3g} deg/s")
    assert error.max() < TOL_DPS, f"max |C - Python| {error.max():.3g} deg/s at row {error.max(1).argmax()}"
    # the error bar (s->drift_sigma_dps): float32 against float64, relative to its size; NaN in both
    # for a bundle without one (written by hand here, or before gyronet had them)
    assert py.drift_sigma_dps is not None
    if np.isnan(py.drift_sigma_dps).all():
        assert np.isnan(c_out[:, 4:7]).all()
    else:
        assert np.isfinite(py.drift_sigma_dps).all()
        np.testing.assert_allclose(c_out[:, 4:7], py.drift_sigma_dps, rtol=1e-4, atol=1e-6)


@needs_cc
@pytest.mark.parametrize("kind", ["default", "kalman", "kalman_rate", "paper_rbf", "poly3", "px4", "lsq", "aux",
                                  "members", "axis_lag", "members_axis_lag"])
def test_c_matches_compensator_on_a_hard_recording(kind, bundles, paper_csv, aux_csv, tmp_path):
    exe, summary = _build(bundles[kind], tmp_path)
    columns = _hard(_columns(aux_csv if kind == "aux" else paper_csv))
    py = _python(bundles[kind], columns)
    assert py.out_of_range.sum() > 100 and py.bad_input.sum() >= 15  # the cases are really there
    _check(_run_c(exe, columns, summary["aux_inputs"], tmp_path), py)
    print(kind, summary)
    assert summary["kalman"] == kind.startswith("kalman") and summary["aux_inputs"] == ([AUX] if kind == "aux" else [])
    assert summary["error_bar"]
    if kind.endswith("axis_lag"):  # y's lagged dT/dt reads the unlagged feature's tracker, not one of its own
        assert (tmp_path / "c" / "gyronet_compensator.c").read_text().count("tracker_step(&s->") == 1
    if kind == "members":  # the spread's code path: every start kept as a member
        import json

        assert json.loads((bundles[kind] / "meta.json").read_text())["error_bar"]["n_members"] == 3


@needs_cc
def test_c_matches_compensate_py_with_a_startup_offset(bundles, paper_csv, tmp_path):
    """compensate_file (compensate.py's code) on a CSV with gaps and startup.still_s, against the C."""
    from gyronet.bundle.offline import compensate_file

    columns = _columns(paper_csv)
    keep = np.ones(len(columns["time_s"]), dtype=bool)
    keep[3000:3010] = keep[40000:47000] = False
    columns = {k: v[keep] for k, v in columns.items()}
    csv = tmp_path / "gappy.csv"
    write_recording(csv, columns, {"fs_hz": "2"})
    compensate_file(bundles["kalman"], csv, tmp_path / "py.csv", startup={"still_s": 600.0})
    py = load_recording(tmp_path / "py.csv").columns
    exe, summary = _build(bundles["kalman"], tmp_path)
    c_out = _run_c(exe, columns, [], tmp_path, still_s=600.0)
    error = np.abs(c_out[:, :3] - np.column_stack([py[c] for c in GYRO_COLUMNS]))
    assert error.max() < TOL_DPS
    # the error bar with the offset's own noise from the window's end on, as compensate.py writes it
    sigma = np.column_stack([py[f"drift_sigma_{a}_dps"] for a in "xyz"])
    np.testing.assert_allclose(c_out[:, 4:7], sigma, rtol=1e-4, atol=1e-6)
    # the offset is really applied: without it the output differs by far more than the tolerance
    plain = _run_c(exe, columns, [], tmp_path)
    assert np.abs(plain[2000:, :3] - c_out[2000:, :3]).max() > 10 * TOL_DPS
    # and so is its noise, in the bar from the window's end on only (this bundle's bar had no window)
    after = columns["time_s"] - columns["time_s"][0] >= 600.0
    assert np.all(c_out[after, 4:7] > plain[after, 4:7]) and np.array_equal(c_out[~after, 4:7], plain[~after, 4:7])
    # the host driver reads the recording itself, its "#" metadata lines skipped; other columns first: one line
    subprocess.run([str(exe), str(csv), str(tmp_path / "direct.csv"), "1", "600"], check=True, capture_output=True)
    np.testing.assert_allclose(np.loadtxt(tmp_path / "direct.csv", delimiter=",", skiprows=1, ndmin=2), c_out,
                               rtol=0, atol=1e-6)
    (tmp_path / "swapped.csv").write_text("# fs_hz=2\ntime_s,gyro_x_dps,temp_c,gyro_y_dps,gyro_z_dps\n0,0,25,0,0\n")
    refused = subprocess.run([str(exe), str(tmp_path / "swapped.csv"), str(tmp_path / "x.csv")], capture_output=True,
                             text=True)
    assert refused.returncode == 2 and refused.stderr.count("\n") == 1 and "must begin time_s,temp_c" in refused.stderr


@needs_cc
def test_c_takes_a_stamp_that_is_no_time_as_python_does_in_and_after_the_start_up_window(bundles, paper_csv, tmp_path):
    """NaN and inf stamps: lost samples that neither start nor end the window, with time features (aux bundle)."""
    columns = {k: v[:4000] for k, v in _columns(paper_csv).items()}
    columns["time_s"][[0, 5, 600, 1199, 1200, 1201, 3000]] = np.nan, np.inf, -np.inf, np.inf, np.nan, np.inf, np.nan
    for kind in ("kalman", "aux"):
        if kind == "aux":
            columns[AUX] = 3.3 - 0.002 * (columns["temp_c"] - 25.0)
        exe, summary = _build(bundles[kind], tmp_path / kind)
        py = _python(bundles[kind], columns, still_s=600.0)
        assert np.flatnonzero(py.bad_input).tolist() == [0, 5, 600, 1199, 1200, 1201, 3000]
        _check(_run_c(exe, columns, summary["aux_inputs"], tmp_path / kind, still_s=600.0), py)


@needs_cc
def test_a_start_up_window_without_a_good_sample_removes_nothing_in_c_and_python(bundles, paper_csv, tmp_path):
    columns = {k: v[:2000] for k, v in _columns(paper_csv).items()}
    columns["temp_c"][:700] = np.nan  # the first 350 s: every window sample flagged
    exe, summary = _build(bundles["kalman"], tmp_path)
    py = _python(bundles["kalman"], columns, still_s=300.0)
    assert np.isfinite(py.rate_dps).all()
    plain = _python(bundles["kalman"], columns)
    np.testing.assert_array_equal(py.rate_dps, plain.rate_dps)
    _check(_run_c(exe, columns, [], tmp_path, still_s=300.0), py)


@needs_cc
def test_a_build_without_ieee_nan_arithmetic_is_refused_at_compile_time(bundle, tmp_path):
    write_c(bundle, tmp_path / "c")
    for flags in (["-ffast-math"], ["-Ofast"], ["-ffinite-math-only"],
                  ["-fassociative-math", "-fno-signed-zeros", "-fno-trapping-math"]):
        built = subprocess.run([CC, "-std=c99", *flags, "-c", str(tmp_path / "c" / "gyronet_compensator.c"), "-o",
                                str(tmp_path / "x.o")], capture_output=True, text=True)
        assert built.returncode != 0 and "needs IEEE arithmetic" in built.stderr, (flags, built.stderr)


@needs_cc
def test_state_size_and_symbols(bundles, tmp_path):
    """sizeof(gyronet_state) is the size write_c reports; the object needs no heap and no libm but expf/fabsf/sqrtf."""
    exe, summary = _build(bundles["kalman"], tmp_path)
    probe = tmp_path / "size.c"
    probe.write_text('#include <stdio.h>\n#include "gyronet_compensator.h"\n'
                     'int main(void) { printf("%u\\n", (unsigned)sizeof(gyronet_state)); return 0; }\n')
    subprocess.run([CC, *CFLAGS, "-I", str(tmp_path / "c"), str(probe), "-o", str(tmp_path / "size")], check=True)
    size = int(subprocess.run([str(tmp_path / "size")], capture_output=True, text=True, check=True).stdout)
    assert size == summary["state_bytes"]
    nm = shutil.which("nm")
    if nm:
        undefined = subprocess.run([nm, "-u", str(tmp_path / "gyronet_compensator.o")], capture_output=True,
                                   text=True, check=True).stdout.split()
        assert set(undefined) - {"U"} <= {"expf", "fabsf", "sqrtf", "memcpy", "memset"}


@needs_cc
def test_a_column_name_that_would_end_a_c_comment_still_compiles(aux_csv, tmp_path):
    """An aux column named ``sup*/ply_v`` (a name a recording may hold) goes into the header's comments."""
    from gyronet.model.baselines import LinearFeatures

    columns = _columns(aux_csv)
    columns["sup*/ply_v"] = columns.pop(AUX)
    write_recording(tmp_path / "odd.csv", columns, {"fs_hz": "2"})
    bundle = _train(tmp_path / "odd", tmp_path / "odd.csv", lambda n: LinearFeatures(n, 3),
                    features=[{"kind": "temp"}, {"kind": "column", "source": "sup*/ply_v"}])
    _build(bundle, tmp_path)
    assert "sup* /ply_v" in (tmp_path / "c" / "gyronet_compensator.h").read_text()


def test_a_lagged_bundles_px4_export_clamps_at_its_trained_range(bundles, tmp_path):
    """The lag slots' clamp is flat only to rounding: the edge search took 152 degC for 61.7, and fitted the cubic there."""
    from gyronet.deploy.params import export_params, px4_cubic, read_params

    export_params(bundles["axis_lag"], tmp_path / "lagged.params", "px4")
    cubic = px4_cubic(read_params(tmp_path / "lagged.params"))
    low, high = json.loads((bundles["axis_lag"] / "meta.json").read_text())["temp_range_c"]
    assert low - 1e-3 < cubic.temp_min_c < low + 0.5 and high - 0.5 < cubic.temp_max_c < high + 1e-3


@needs_cc
def test_product_in_c_multiplies_t_by_its_own_rate_whatever_rate_comes_first(aux_csv, tmp_path):
    """The C export took the first rate of any source for T * dT/dt, as Python did."""
    from gyronet.model.baselines import LinearFeatures

    specs = [{"kind": "temp"}, {"kind": "rate", "source": AUX}, {"kind": "rate", "tau_s": 5.0}, {"kind": "product"}]
    bundle = _train(tmp_path / "aux_rate", aux_csv, lambda n: LinearFeatures(n, 3), features=specs)
    exe, summary = _build(bundle, tmp_path)
    columns = _hard(_columns(aux_csv))
    _check(_run_c(exe, columns, summary["aux_inputs"], tmp_path), _python(bundle, columns))


def test_unknown_model_class_is_one_line(bundle, tmp_path):
    """A bundle whose model is a class the generator does not know (a future PX4 polynomial) is refused in one line."""
    from gyronet.bundle.io import load_bundle, save_bundle

    class TempCubicPx4(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.register_buffer("coef", torch.zeros(4, 3, dtype=torch.float64))

        def forward(self, x: torch.Tensor) -> torch.Tensor:
            return x[:, 0:1].pow(3) @ self.coef[3:4]

    _, meta, _ = load_bundle(bundle)
    meta = {k: v for k, v in meta.items() if k not in ("format", "gyronet_version", "sha256", "kalman")}
    meta["model"] = {"class": "TempCubicPx4"}
    save_bundle(TempCubicPx4(), meta, tmp_path / "b")
    with pytest.raises(BundleError, match="TempCubicPx4 model, which the C export does not know") as err:
        write_c(tmp_path / "b", tmp_path / "c")
    assert "\n" not in str(err.value) and not (tmp_path / "c").exists()


def test_a_changed_model_form_is_refused(bundle):
    """If RBFNet's forward gains a term the generator does not know, the export fails instead of writing wrong C."""
    from gyronet.deploy.c._model import model_code
    from gyronet.model.rbf import RBFNet

    net = RBFNet(3, 3, 4, rbf_inputs=[0], linear=True, temp_degree=3, clamp=True)
    with torch.no_grad():
        for p in net.parameters():
            p.uniform_(-1.0, 1.0)
    net.original_name = "RBFNet"
    scale, centre = np.ones(3), np.zeros(3)
    model_code(net, scale, centre, "ok")  # its own form: accepted
    net.forward = lambda x: RBFNet.forward(net, x) + 1e-3 * x[:, 1:2]
    with pytest.raises(BundleError, match="the model's form changed"):
        model_code(net, scale, centre, "changed")


def test_fractional_power_is_refused():
    from gyronet.deploy.c._features import feature_code

    with pytest.raises(BundleError, match="exponent 1.5 is not a whole number"):
        feature_code([{"kind": "temp"}, {"kind": "power", "exponent": 1.5}], 2.0, [], "b")


def test_head_spans_hold_every_nonzero_weight_in_order():
    """The C stores each output row's span of nonzero weights: the dense head comes back from it, zero rows too."""
    from gyronet.deploy.c._model import head_spans

    head = np.array([[0.0, 1.5, 0.0, -2.0, 0.0],   # a gap inside the span is kept
                     [0.0, 0.0, 0.0, 0.0, 0.0],    # an axis below the full level: no Gaussians
                     [3.0, 0.0, 0.0, 0.0, 0.25]])
    weights, first, at = head_spans(head)
    assert at == [0, 3, 3, 8] and first == [1, 0, 0]
    dense = np.zeros_like(head)
    for a in range(len(head)):
        dense[a, first[a]:first[a] + at[a + 1] - at[a]] = weights[at[a]:at[a + 1]]
    np.testing.assert_array_equal(dense, head)


def test_export_command_writes_c(bundle, tmp_path):
    out = tmp_path / "fw"
    proc = subprocess.run([sys.executable, str(ROOT / "scripts" / "export.py"), f"model={bundle}", "format=c",
                           f"output={out}", f"hydra.run.dir={tmp_path / 'hydra'}"], cwd=ROOT, capture_output=True,
                          text=True)
    assert proc.returncode == 0, proc.stderr
    write_c(bundle, tmp_path / "direct")  # the command writes what the generator writes, byte for byte
    for name in ("gyronet_compensator.h", "gyronet_compensator.c"):
        assert (out / name).read_bytes() == (tmp_path / "direct" / name).read_bytes()


@needs_cc
@pytest.mark.slow
def test_bench_row_quick(tmp_path):
    """scripts/bench.py's c_compensator row runs (quick sizes) and its C agrees with Python."""
    import json
    import os

    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    proc = subprocess.run([sys.executable, str(ROOT / "scripts" / "bench.py"), "--quick", "--only", "c_compensator",
                           "--json", str(tmp_path / "b.json"), "--work-dir", str(tmp_path)], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    (result,) = json.loads((tmp_path / "b.json").read_text())["rows"]
    assert result["c_ns_per_sample"] > 0 and result["flash_bytes"]["-O2"] > 0
    assert result["max_diff_dps"] < TOL_DPS


@needs_cc
@pytest.mark.slow
def test_float32_at_1khz_with_a_long_lag_after_11_days(tmp_path):
    """1 kHz, a 600 s lag, a clock at 1e6 s: where float32 state or time would break, the C still agrees."""
    from gyronet.model.baselines import LinearFeatures
    from gyronet.bundle.compensator import build_meta
    from gyronet.bundle.io import save_bundle
    from gyronet.model.features import feature_name

    fs_hz, n = 1000.0, 600_000
    specs = [{"kind": "temp"}, {"kind": "rate", "tau_s": 5.0}, {"kind": "product"}, {"kind": "lag", "tau_s": 600.0}]
    model = LinearFeatures(len(specs))
    with torch.no_grad():
        model.weight.copy_(torch.tensor([[0.01, -0.02, 0.005], [2.0, 1.0, -1.5], [0.01, 0.02, 0.0],
                                         [0.02, -0.01, 0.01]], dtype=torch.float64))
        model.x_mean.copy_(torch.tensor([35.0, 0.0, 0.0, 35.0], dtype=torch.float64))
    meta = build_meta(specs, [feature_name(s) for s in specs], fs_hz, (20.0, 50.0),
                      ["time_s", "temp_c", *GYRO_COLUMNS], "0" * 64, {"class": "LinearFeatures"})
    save_bundle(model, meta, tmp_path / "b")
    rng = np.random.default_rng(3)
    time_s = 1e6 + np.arange(n) / fs_hz
    # a 0.05 degC/s ramp, quantised to 1/16 degC as sensors report it
    temp_c = np.round((20.0 + 0.05 * (time_s - time_s[0])) * 16.0) / 16.0
    columns = {"time_s": time_s, "temp_c": temp_c,
               **{c: 0.1 + 0.01 * rng.standard_normal(n) for c in GYRO_COLUMNS}}
    exe, _ = _build(tmp_path / "b", tmp_path)
    _check(_run_c(exe, columns, [], tmp_path), _python(tmp_path / "b", columns))


@needs_cc
def test_two_compensators_with_their_own_prefix_link_into_one_firmware(bundles, tmp_path):
    """A board with two IMUs: gyronet_init and the rest were defined twice."""
    for prefix, kind in (("imu1", "default"), ("imu2", "poly3")):
        summary = write_c(bundles[kind], tmp_path / prefix, prefix=prefix)
        assert [Path(f).name for f in summary["files"]] == [f"{prefix}_compensator.h", f"{prefix}_compensator.c"]
    main = tmp_path / "main.c"
    main.write_text('#include "imu1_compensator.h"\n#include "imu2_compensator.h"\n'
                    "int main(void)\n{\n    imu1_state a;\n    imu2_state b;\n    const float g[3] = {0, 0, 0};\n"
                    "    float o[3];\n    imu1_init(&a);\n    imu2_init(&b);\n"
                    "    return imu1_step(&a, 0.0, 20.0f, g, o) | imu2_step(&b, 0.0, 20.0f, g, o) | "
                    "(IMU1_FS_HZ > 0.0 && IMU2_FS_HZ > 0.0 ? 0 : 1);\n}\n")
    exe = tmp_path / "two"
    subprocess.run([CC, *CFLAGS, "-I", str(tmp_path / "imu1"), "-I", str(tmp_path / "imu2"), str(main),
                    str(tmp_path / "imu1" / "imu1_compensator.c"), str(tmp_path / "imu2" / "imu2_compensator.c"),
                    "-lm", "-o", str(exe)], check=True)
    assert subprocess.run([str(exe)]).returncode == 0
    for bad in ("9x", "IMU1"):  # upper case: IMU1 and imu1 would share the macros
        with pytest.raises(GyronetError, match="prefix must be a lower-case C identifier"):
            write_c(bundles["default"], tmp_path / "bad", prefix=bad)
    import shutil

    named = shutil.copytree(bundles["default"], tmp_path / "gyronet_unit7")  # the bundle's name is not a C name
    write_c(named, tmp_path / "imu3", prefix="imu3")
    assert "from the bundle gyronet_unit7 " in (tmp_path / "imu3" / "imu3_compensator.h").read_text()


@needs_cc
def test_an_offset_that_is_no_number_is_refused_in_c(bundle, tmp_path):
    """gyronet_start_offset(NaN) armed a window that never closed, and no flag said so."""
    write_c(bundle, tmp_path / "c")
    main = tmp_path / "main.c"
    main.write_text('#include <math.h>\n#include <stddef.h>\n#include "gyronet_compensator.h"\n'
                    "int main(void)\n{\n    gyronet_state s;\n    const float g[3] = {0.1f, 0.2f, 0.3f};\n"
                    "    float o[3];\n    int k, refused;\n    gyronet_init(&s);\n"
                    "    refused = gyronet_start_offset(&s, NAN, NULL) == -1 && gyronet_start_offset(&s, 0.0, NULL) == -1\n"
                    "        && gyronet_start_offset(&s, INFINITY, NULL) == -1;\n"
                    "    for (k = 0; k < 100; ++k) {\n        gyronet_step(&s, 0.5 * k, 20.0f, g, o);\n    }\n"
                    "    /* nothing applied: the rate is the gyro less the drift, finite */\n"
                    "    return !(refused && s.offset_mode == 0 && isfinite(o[1])) || gyronet_start_offset(&s, 10.0, NULL);\n}\n")
    exe = tmp_path / "offsets"
    subprocess.run([CC, *CFLAGS, "-I", str(tmp_path / "c"), str(main), str(tmp_path / "c" / "gyronet_compensator.c"),
                    "-lm", "-o", str(exe)], check=True)
    assert subprocess.run([str(exe)]).returncode == 0
