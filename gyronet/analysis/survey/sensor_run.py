"""One sensor of the survey: simulate its histories, train every method on the training record(s), score on another.

The held-out history is scored against the simulator's truth, from the end of the start-up window
on, three ways (the same blocks for all three):

- ``deployed``: as ``compensate.py ... startup.still_s=S`` runs it, the run's own offset estimated
  over its first S s (the recording's static rate subtracted). This is the survey's headline: a
  turn-on bias is new at each power-up, so no model trained on another run can know it. Its floor
  is what a perfect drift model leaves when deployed so: the noise minus the window's mean noise,
  a constant the offset carries into every later sample (each sensor draws its own).
- ``turn_on_removed``: no start-up offset, the difference between the two runs' true turn-on
  biases taken from the truth (a campaign's: the held-out run's less its runs' mean): the
  temperature model alone.
- ``as_is``: no start-up offset at all (the turn-on bias difference stays in the residual).
"""
from __future__ import annotations

import contextlib
import dataclasses
import functools
import hashlib
import importlib
import json
import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from gyronet.atomic import atomic_output
from gyronet.bundle.compensator import Compensator
from gyronet.recordings.data import AXES, load_recording, load_truth
from gyronet.training.dataset import static_rate_dps
from gyronet.errors import GyronetError
from gyronet.bundle.offline import compensate_as_deployed
from gyronet.training.sigma_table import score_against_truth
from gyronet.training.train import residual_report

log = logging.getLogger(__name__)

TRAIN_PATH = "SURVEY_TRAINING_RECORD"  # stands for each sensor's training CSV in a method's data settings
VARIANTS = ("deployed", "turn_on_removed", "as_is")
RESULT_FILE = "result.json"


@dataclass(frozen=True)
class History:
    """One simulated thermal history: the arguments of :func:`gyronet.sim.simulate` that make it.

    ``simulate`` holds more arguments for this record alone, merged over the survey's own
    (:attr:`SurveySpec.simulate`): e.g. a training record with less noise than the one scored.
    """

    profile: str = "cycle"
    seed: int = 1
    duration_s: float | None = None
    profile_options: Mapping[str, Any] = field(default_factory=dict)
    simulate: Mapping[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class SurveySpec:
    """What every sensor of a survey gets.

    Attributes
    ----------
    methods
        Name -> ``{"model", "data", "optim", "train", "seed"}``, each a plain mapping as
        ``conf/train.yaml`` composes it (``_target_`` nodes), ``data.path`` being :data:`TRAIN_PATH`.
    distribution
        The sensors' distribution (:func:`gyronet.sim.sensor.draw_sensor`).
    train_history, check_history
        The history each sensor is trained on and the one it is scored on.
    more_train_histories
        More training records, each its own power-up (its own turn-on bias and noise): with any,
        every method trains on all of them as a campaign (``data.paths``, leave-one-run-out).
    fs_hz
        Sampling rate of both records, Hz.
    startup_s
        The start-up window, s: the ``deployed`` offset is measured over it, and every variant is
        scored after it.
    simulate
        More :func:`gyronet.sim.simulate` arguments for both records (noise, temperature, ...).
    keep_records
        Keep the CSVs after the sensor is scored (10 Hz records are tens of MB each).
    """

    methods: Mapping[str, Mapping[str, Any]]
    distribution: str = "survey"
    train_history: History = History("cycle", 1)
    check_history: History = History("random", 2)
    more_train_histories: tuple[History, ...] = ()
    fs_hz: float = 10.0
    startup_s: float = 600.0
    simulate: Mapping[str, Any] = field(default_factory=dict)
    keep_records: bool = False

    def fingerprint(self) -> str:
        """A hash of everything that decides a sensor's result (``keep_records`` aside): resumed only if equal."""
        settings = {k: v for k, v in dataclasses.asdict(self).items() if k != "keep_records"}
        if not settings["more_train_histories"]:  # results from before campaigns still resume
            del settings["more_train_histories"]
        for key in ("train_history", "check_history"):  # results from before the per-record setting still resume
            if not settings[key]["simulate"]:
                del settings[key]["simulate"]
        settings["noise"] = "each sensor its own"  # results from before that shared one noise draw: not resumed
        return hashlib.sha256(json.dumps(settings, sort_keys=True, default=str).encode()).hexdigest()[:16]


def build(spec: Mapping[str, Any], **kwargs: Any) -> Any:
    """The object a ``_target_`` node describes (``_partial_``: a partial), without Hydra."""
    options = {k: v for k, v in spec.items() if k not in ("_target_", "_partial_", "_convert_", "_recursive_")}
    module, _, name = str(spec["_target_"]).rpartition(".")
    target = getattr(importlib.import_module(module), name)
    if spec.get("_partial_", False):
        return functools.partial(target, **options, **kwargs)
    return target(**options, **kwargs)


def simulate_history(folder: Path, name: str, sensor_seed: int, history: History, spec: SurveySpec) -> Path:
    """Simulate one history of this sensor into ``folder/name.csv`` (and its truth)."""
    from gyronet.sim import simulate, write_simulation

    options = merged(spec.simulate, history.simulate)
    sensor = {"distribution": spec.distribution, **dict(options.pop("sensor", {}) or {})}
    # one chamber history for every sensor, but each sensor its own noise: else the start-up offset's
    # noise, a constant over the run, would be one draw shared by the whole survey
    noise_seed = int(np.random.SeedSequence([history.seed, sensor_seed]).generate_state(1)[0])
    sim = simulate(profile=history.profile, seed=history.seed, sensor_seed=sensor_seed, fs_hz=spec.fs_hz,
                   duration_s=history.duration_s, profile_options=dict(history.profile_options), sensor=sensor,
                   noise_seed=noise_seed, **options)
    path = folder / f"{name}.csv"
    write_simulation(sim, path)
    return path


def merged(base: Mapping[str, Any], extra: Mapping[str, Any]) -> dict[str, Any]:
    """``base`` with ``extra``'s settings over it, nested mappings merged key by key."""
    out = dict(base)
    for key, value in extra.items():
        both = isinstance(value, Mapping) and isinstance(out.get(key), Mapping)
        out[key] = merged(out[key], value) if both else value
    return out


def train_method(train_csvs: list[Path], method: Mapping[str, Any], out_dir: Path) -> Path:
    """Train one method on ``train_csvs`` as ``train.py`` would (``gyronet.training.pipeline.train_run``); its bundle.

    One record is ``data.path``; several are runs of a campaign, ``data.paths`` (validated by run).
    """
    from gyronet.training.axis_lag import with_axis_lags
    from gyronet.training.pipeline import train_run
    from gyronet.training.runs import training_data

    one = len(train_csvs) == 1  # else a campaign: validated by its runs, so PX4's val_path=path goes too
    data_options = {k: ((str(train_csvs[0]) if one else None) if v == TRAIN_PATH else v)
                    for k, v in method["data"].items() if k not in ("_target_", "_convert_")}
    if not one:
        data_options["paths"] = [str(p) for p in train_csvs]
    data = training_data(**data_options)
    model = build(method["model"], n_inputs=data.n_features)
    data, model = with_axis_lags(data, lambda n, columns: build(method["model"], n_inputs=n, axis_columns=columns),
                                 model)
    train_cfg = {**dict(method.get("train") or {}), "progress": False}
    train_run(data, model, build(method["optim"]), out_dir, train_cfg, seed=int(method.get("seed", 0)))
    return out_dir / "compensator"


def turn_on_bias(truth: Mapping[str, np.ndarray]) -> np.ndarray:
    """A run's true turn-on bias per axis (zero when it has none), shape (3,), deg/s."""
    columns = [f"turn_on_bias_{a}_dps" for a in AXES]
    if not all(c in truth for c in columns):
        return np.zeros(len(AXES))
    return np.array([float(truth[c][0]) for c in columns])


def deployed_floor_truth(truth: Mapping[str, np.ndarray], keep: np.ndarray) -> dict[str, np.ndarray]:
    """The truth's rows after the start-up window, their noise less the window's mean noise.

    As deployed, a perfect drift model leaves that: the offset carries the window's noise into every
    later sample. Scored on it, residual / floor is 1 where the drift is gone, as without a window.
    """
    out = {k: v[keep] for k, v in truth.items()}
    for a in AXES:
        out[f"noise_{a}_dps"] = out[f"noise_{a}_dps"] - truth[f"noise_{a}_dps"][~keep].mean()
    return out


def score_bundle(bundle: Path, check_csv: Path, startup_s: float, turn_on_difference_dps: np.ndarray) -> dict[str, Any]:
    """Residual / floor per axis of one bundle on the held-out record, each of :data:`VARIANTS`."""
    recording = load_recording(check_csv)
    truth = load_truth(check_csv).columns
    keep = recording.time_s >= recording.time_s[0] + startup_s
    if keep.sum() < 2:
        raise GyronetError(f"{check_csv}: nothing left to score after startup_s={startup_s:g} s")
    kept_truth = {k: v[keep] for k, v in truth.items()}
    compensator = Compensator.load(bundle)
    rates = {}
    compensator.use_startup(still_s=startup_s, static_rate_dps=static_rate_dps(recording).tolist())
    deployed = compensate_as_deployed(compensator, recording)
    rates["deployed"] = deployed.rate_dps
    compensator.use_startup(0.0)
    plain = compensate_as_deployed(compensator, recording)
    rates["as_is"] = plain.rate_dps
    rates["turn_on_removed"] = plain.rate_dps - turn_on_difference_dps
    scores: dict[str, Any] = {}
    for variant in VARIANTS:
        floor_truth = deployed_floor_truth(truth, keep) if variant == "deployed" else kept_truth
        report = residual_report(recording.time_s[keep], rates[variant][keep], floor_truth)
        scores[variant] = [report["ratio_to_floor"][a] for a in AXES]
    scores["n_out_of_range"] = int(plain.out_of_range[keep].sum())
    sigma = deployed.drift_sigma_dps[keep]
    if np.isfinite(sigma).all():  # the bar as deployed: blocks within 1 sigma, and allan.py's recalibration check
        score = score_against_truth(recording.time_s[keep], rates["deployed"][keep], sigma,
                                    deployed.out_of_range[keep], kept_truth)
        scores["error_bar"] = {"within_1_sigma": [score["within_1_sigma"][a] for a in AXES],
                               "worst_hour_rms_ratio": [score["recalibration"][a]["worst_hour_rms_ratio"] for a in AXES]}
    return scores


def describe_sensor(sensor: Mapping[str, Any]) -> dict[str, float]:
    """A few figures of a drawn sensor for the per-sensor table: sharpest knee, strongest dT/dt gain, longest axis lag."""
    widths = list(sensor["knee_width_c"]) + [w for w, a in zip(sensor.get("knee2_width_c", []),
                                                                  sensor.get("knee2_dps", [])) if a]
    return {"sharpest_knee_c": float(min(widths)),
            "max_rate_gain_deg_per_c": float(np.max(np.abs(sensor["rate_gain_deg_per_c"]))),
            "max_axis_lag_s": float(np.max(sensor.get("axis_lag_s", [0.0])))}


def run_sensor(sensor_seed: int, spec: SurveySpec, folder: str | Path, reuse: bool = True) -> dict[str, Any]:
    """Simulate, train every method and score one sensor; write and return ``folder/result.json``.

    With ``reuse``, a result already in ``folder`` with the same :meth:`SurveySpec.fingerprint` is
    returned as it is (an interrupted survey resumes sensor by sensor).
    """
    folder = Path(folder)
    result_path = folder / RESULT_FILE
    fingerprint = spec.fingerprint()
    if reuse and result_path.is_file():
        done = json.loads(result_path.read_text())
        if done.get("fingerprint") == fingerprint:
            done["reused"] = True
            return done
        log.info("sensor %d: settings changed since %s, run again", sensor_seed, result_path)
    start = time.perf_counter()
    folder.mkdir(parents=True, exist_ok=True)
    with _one_process_at_a_time(folder):
        result = _simulate_train_score(sensor_seed, spec, folder, fingerprint)
    result["seconds"] = time.perf_counter() - start
    with atomic_output(result_path) as tmp:
        tmp.write_text(json.dumps(result, indent=1) + "\n")
    return result


@contextlib.contextmanager
def _one_process_at_a_time(folder: Path):
    """Hold ``folder``'s lock while its sensor runs. The workers of a stopped survey finish their sensors, and a
    second survey in the same folder ran one of them at the same time: each deleted records the other was reading."""
    try:
        import fcntl
    except ImportError:  # not POSIX: no lock
        yield
        return
    with open(folder / ".lock", "w") as handle:
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise GyronetError(f"{folder}: another process is running this sensor (a survey in the same folder, or "
                               "the workers of one just stopped): run the same command again when it is done") from None
        yield


def _simulate_train_score(sensor_seed: int, spec: SurveySpec, folder: Path, fingerprint: str) -> dict[str, Any]:
    """:func:`run_sensor`'s work, its result without the time taken."""
    train_csvs = [simulate_history(folder, "train" if k == 0 else f"train{k + 1}", sensor_seed, history, spec)
                  for k, history in enumerate((spec.train_history, *spec.more_train_histories))]
    check_csv = simulate_history(folder, "check", sensor_seed, spec.check_history, spec)
    # a campaign's model keeps the mean of its runs' constants (gyronet.training.run_offsets)
    trained_bias = np.mean([turn_on_bias(load_truth(path).columns) for path in train_csvs], axis=0)
    difference = turn_on_bias(load_truth(check_csv).columns) - trained_bias
    sensor = json.loads(load_truth(check_csv).meta["sensor_model"])
    methods = {}
    try:
        for name, method in spec.methods.items():
            method_start = time.perf_counter()
            bundle = train_method(train_csvs, method, folder / _folder_name(name))
            methods[name] = {**score_bundle(bundle, check_csv, spec.startup_s, difference),
                             "seconds": time.perf_counter() - method_start}
    finally:
        _forget_records()
    if not spec.keep_records:
        for path in folder.glob("*.csv"):
            path.unlink()
    return {"sensor_seed": int(sensor_seed), "fingerprint": fingerprint, "methods": methods,
            "turn_on_difference_dps": difference.tolist(), **describe_sensor(sensor), "sensor": sensor}


def _forget_records() -> None:
    """Drop this sensor's recordings and features from the per-process caches and return freed memory: a
    long-lived worker otherwise grows by about 0.6 GB a sensor (a 100-sensor run was killed for memory twice)."""
    import ctypes
    import gc

    from gyronet.training import dataset

    dataset.clear_caches()
    gc.collect()
    try:  # glibc keeps freed heap pages: give them back (elsewhere there is nothing to do)
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


def _folder_name(method: str) -> str:
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in method)
