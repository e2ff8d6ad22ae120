"""Shared fixtures: seeded simulated recordings with known drift and noise, and a trained bundle."""
import os

# two xdist workers on two cores: each one, and every script a test starts, on one BLAS / OpenMP thread
# (threads fighting for the cores made the suite 1.3x slower); set before numpy and torch start theirs
for _threads in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_threads, "1")

from pathlib import Path  # noqa: E402

import pytest  # noqa: E402
from hypothesis import HealthCheck, settings  # noqa: E402

from gyronet.sim import simulate, write_simulation  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared"
CATS = SHARED / "data" / "real" / "cats-tag"  # the real tag's two shared runs (never copied into the repository)
CATS_RUNS = [CATS / "cats_run_z_down.csv.gz", CATS / "cats_run_y_down.csv.gz"]
needs_cats = pytest.mark.skipif(not all(p.is_file() for p in CATS_RUNS),
                                reason=f"the real cats-tag runs are not at {CATS} (../shared is not in the repository)")
FAST_FS_HZ = 2.0  # the drift is slow; 2 Hz keeps tests quick while the noise stays white

# property-based tests: a small example budget in every run (CI's too), ten times more with
# HYPOTHESIS_PROFILE=slow; no deadline, since CI machines vary in speed
_HYPOTHESIS_COMMON = dict(deadline=None, suppress_health_check=[HealthCheck.too_slow], derandomize=True)
settings.register_profile("default", max_examples=40, **_HYPOTHESIS_COMMON)
settings.register_profile("slow", max_examples=400, **_HYPOTHESIS_COMMON)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "default"))


@pytest.fixture(autouse=True)
def _root_logging_put_back():
    """Undo what a command run in this process (Hydra's job logging) adds to the root logger.

    Its console handler keeps the test's captured stdout; once that is closed, every later record
    in the same worker printed "--- Logging error ---" into another test's stderr.
    """
    import logging

    root = logging.getLogger()
    handlers, level = list(root.handlers), root.level
    yield
    for handler in [h for h in root.handlers if h not in handlers and not type(h).__module__.startswith("_pytest")]:
        root.removeHandler(handler)
        handler.close()
    root.setLevel(level)


@pytest.fixture(scope="session")
def paper_csv(tmp_path_factory) -> Path:
    """The paper's 12.7 h chamber profile, sensor 0, at 2 Hz."""
    path = tmp_path_factory.mktemp("sim") / "paper.csv"
    write_simulation(simulate("paper", fs_hz=FAST_FS_HZ, seed=1, sensor_seed=0), path)
    return path


@pytest.fixture(scope="session")
def cycle_csv(tmp_path_factory) -> Path:
    """The same sensor through a different thermal history (down and up): held-out data."""
    path = tmp_path_factory.mktemp("sim") / "cycle.csv"
    write_simulation(simulate("cycle", fs_hz=FAST_FS_HZ, seed=2, sensor_seed=0), path)
    return path


@pytest.fixture(scope="session")
def bundle(tmp_path_factory, paper_csv) -> Path:
    """A small default-model bundle trained on ``paper_csv``, for the tests that consume bundles."""
    from gyronet.training.dataset import DriftData
    from gyronet.model.rbf import RBFNet
    from gyronet.training.pipeline import train_run

    out = tmp_path_factory.mktemp("run")
    data = DriftData(str(paper_csv))
    model = RBFNet(data.n_features, 3, 8, rbf_inputs=[0], linear=True, temp_degree=3, clamp=True)
    train_run(data, model, None, out, {"max_epochs": 300, "progress": False})
    return out / "compensator"


LPBUS_SAMPLES = 300  # the LP-BUS pty tests' short recording (test_lpbus_live, test_lpbus_replug)
OUT_OF_RANGE_TEMP_C = 150.0  # a temperature no test bundle is trained at


@pytest.fixture
def lpbus_recording(paper_csv, tmp_path) -> Path:
    """The paper run's first ``LPBUS_SAMPLES`` samples as a recording: what the emulated LP-BUS sensor plays."""
    from gyronet.recordings.data import load_recording, write_recording

    recording = load_recording(paper_csv).slice(slice(0, LPBUS_SAMPLES))
    return write_recording(tmp_path / "short.csv", recording.columns, recording.meta)


def lpbus_bytes(columns: dict, faults) -> bytes:
    """The bytes an emulated LP-BUS sensor sends for ``columns`` with ``faults`` (a ``FaultPlan``), drops left out."""
    from gyronet.deploy.stream import plan_stream

    plan = plan_stream(columns, "lpbus", faults)
    return plan.preamble + b"".join(event.data for event in plan.events if not event.drop)


@pytest.fixture(scope="module")
def flood(paper_csv) -> tuple[dict, bytes]:
    """2,000 samples with a replugged sensor (its clock starts again) after 1,200, as LP-BUS bytes with
    garbage, corrupt, cut and NaN frames and out-of-range temperatures."""
    from gyronet.deploy.stream import FaultPlan, plan_stream
    from gyronet.recordings.data import load_recording

    recording = load_recording(paper_csv).slice(slice(0, 2000))
    columns = {c: v.copy() for c, v in recording.columns.items()}
    columns["time_s"][1200:] = columns["time_s"][1200:] - columns["time_s"][1200] + 0.5
    faults = FaultPlan(garbage_rate=0.03, corrupt_rate=0.02, truncate_rate=0.02, nan_rate=0.01, out_of_range_every=41,
                       out_of_range_temp_c=OUT_OF_RANGE_TEMP_C, seed=4)
    return plan_stream(columns, "lpbus", faults).log, lpbus_bytes(columns, faults)


def toy_kalman_dict() -> dict:
    """A 2 Hz Kalman stage with a known AR(1) drift model, for tests that need one without identifying it."""
    from gyronet.model.kalman import AxisModel, KalmanModel, KalmanStage

    axis = AxisModel(ar=(0.999,), ar_se=(1e-4,), q_drift_dps2=1e-8, r_dps2=1e-2)
    return KalmanStage(KalmanModel(fs_hz=2.0, axes=(axis,) * 3)).to_dict()


@pytest.fixture
def torch_jit_warns(monkeypatch):
    """``torch.jit``'s script, save, load and freeze warn as torch 2.14's do (a FutureWarning, shown to users)."""
    import warnings

    import torch

    def warning(name):
        real = getattr(torch.jit, name)

        def warned(*args, **kwargs):
            warnings.warn(f"`torch.jit.{name}` is deprecated. Please switch to `torch.export`.", FutureWarning)
            return real(*args, **kwargs)
        return warned

    for name in ("script", "save", "load", "freeze"):
        monkeypatch.setattr(torch.jit, name, warning(name))
