"""One sensor of the survey: simulate its histories, train every method on the training record(s), score on another.

Each bundle is scored on the held-out history against the simulator's truth by :mod:`.scoring`.
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

from gyronet.analysis.survey.bound import BOUND, score_form_bound
from gyronet.analysis.survey.scoring import score_bundle, turn_on_bias
from gyronet.atomic import write_text
from gyronet.recordings.data import load_recording, load_truth
from gyronet.errors import GyronetError

log = logging.getLogger(__name__)

TRAIN_PATH = "SURVEY_TRAINING_RECORD"  # stands for each sensor's training CSV in a method's data settings
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
    bound
        Also score ``form-bound`` (:mod:`.bound`): least squares in the simulator's own drift formula, what the
        records' noise leaves to a model of the right form.
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
    bound: bool = False

    def fingerprint(self) -> str:
        """A hash of everything that decides a sensor's result (``keep_records`` aside): resumed only if equal."""
        settings = {k: v for k, v in dataclasses.asdict(self).items() if k != "keep_records"}
        for key in ("more_train_histories", "bound"):  # results from before these settings still resume
            if not settings[key]:
                del settings[key]
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
    sim = simulate(profile=history.profile, seed=history.seed, sensor_seed=sensor_seed, fs_hz=spec.fs_hz,
                   duration_s=history.duration_s, profile_options=dict(history.profile_options), sensor=sensor,
                   noise_seed=noise_seed_of(history, sensor_seed), **options)
    path = folder / f"{name}.csv"
    write_simulation(sim, path)
    return path


def noise_seed_of(history: History, sensor_seed: int) -> int:
    """One chamber history for every sensor, but each sensor its own noise: else the start-up offset's noise, a
    constant over the run, would be one draw shared by the whole survey."""
    return int(np.random.SeedSequence([history.seed, sensor_seed]).generate_state(1)[0])


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
    with _without_one_recording_note():
        train_run(data, model, build(method["optim"]), out_dir, train_cfg, seed=int(method.get("seed", 0)))
    return out_dir / "compensator"


@contextlib.contextmanager
def _without_one_recording_note():
    """Drop the pipeline's advice to train on two runs: the survey scores against the truth, and a warning per
    method and sensor broke up its progress bar."""
    from gyronet.training import pipeline

    def keep(record: logging.LogRecord) -> bool:
        return record.msg is not pipeline.ONE_RECORDING_BAR_NOTE

    pipeline.log.addFilter(keep)
    try:
        yield
    finally:
        pipeline.log.removeFilter(keep)


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
        result = {**_simulate_train_score(sensor_seed, spec, folder, fingerprint),
                  "seconds": time.perf_counter() - start}
        write_text(result_path, json.dumps(result, indent=1) + "\n")
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
    train_truths = [load_truth(path).columns for path in train_csvs]
    # a campaign's model keeps the mean of its runs' constants (gyronet.training.run_offsets)
    trained_bias = np.mean([turn_on_bias(truth) for truth in train_truths], axis=0)
    check, check_truth = load_recording(check_csv), load_truth(check_csv)  # read once, scored for every method
    difference = turn_on_bias(check_truth.columns) - trained_bias
    sensor = json.loads(check_truth.meta["sensor_model"])
    methods = {}
    try:
        for name, method in spec.methods.items():
            method_start = time.perf_counter()
            bundle = train_method(train_csvs, method, folder / _folder_name(name))
            methods[name] = {**score_bundle(bundle, check, check_truth.columns, spec.startup_s, difference),
                             "seconds": time.perf_counter() - method_start}
        if spec.bound:
            train = [(load_recording(path), truth) for path, truth in zip(train_csvs, train_truths)]
            methods[BOUND] = score_form_bound(train, check, check_truth.columns, sensor, spec.startup_s, difference)
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
    import gc

    from gyronet.deploy.stream.allocator import trim_heap
    from gyronet.training import dataset

    dataset.clear_caches()
    gc.collect()
    trim_heap()  # glibc keeps freed heap pages: give them back (elsewhere there is nothing to do)


def _folder_name(method: str) -> str:
    return "".join(c if c.isalnum() or c in "-_." else "_" for c in method)
