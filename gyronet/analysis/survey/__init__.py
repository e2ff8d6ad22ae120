"""The survey: many simulated sensors from a wide distribution, each trained on one history and scored on another.

One sensor is :func:`run_sensor` (:mod:`.sensor_run`, scored by :mod:`.scoring`, beside :mod:`.bound`'s fit of the
simulator's own formula); :func:`survey` runs many in parallel
(joblib, one process a job), resuming the sensors already finished; :mod:`.table` makes the
table of docs/results/survey.md (median, 90th percentile and worst of each sensor's worst axis).
"""
from __future__ import annotations

import contextlib

import logging
from pathlib import Path
from typing import Any, Sequence

from gyronet.errors import GyronetError
from gyronet.analysis.survey.scoring import VARIANTS, score_bundle
from gyronet.analysis.survey.sensor_run import RESULT_FILE, TRAIN_PATH, History, SurveySpec, build, run_sensor
from gyronet.analysis.survey.table import goal_keys, sensors_csv, summarize, to_markdown, worst_axis, write_outputs

log = logging.getLogger(__name__)

__all__ = ["goal_keys", "History", "RESULT_FILE", "SurveySpec", "TRAIN_PATH", "VARIANTS", "build", "run_sensor",
           "score_bundle", "sensor_folder", "sensors_csv", "summarize", "survey", "to_markdown", "worst_axis",
           "write_outputs"]


def sensor_folder(out_dir: str | Path, sensor_seed: int) -> Path:
    """Where one sensor's records, bundles and ``result.json`` go."""
    return Path(out_dir) / "sensors" / f"sensor_{int(sensor_seed):04d}"


def survey(seeds: Sequence[int], spec: SurveySpec, out_dir: str | Path, jobs: int = 2, reuse: bool = True,
           progress: bool | None = None) -> list[dict[str, Any]]:
    """Run :func:`run_sensor` for every seed, ``jobs`` at a time, and return the results in seed order.

    Parameters
    ----------
    seeds
        Sensor seeds, each one sensor of ``spec.distribution``.
    spec
        What every sensor gets (:class:`SurveySpec`).
    out_dir
        The survey folder: ``out_dir/sensors/sensor_<seed>/``.
    jobs
        Processes at once (joblib); 1 runs in this process.
    reuse
        Keep the sensors already finished with the same settings (resume).
    progress
        A progress bar on stderr; None: only on a terminal.
    """
    from joblib import Parallel, delayed
    from tqdm.auto import tqdm

    seeds = [int(s) for s in seeds]
    if not seeds:
        raise GyronetError("the survey needs at least one sensor (n_sensors >= 1)")
    if len(set(seeds)) != len(seeds):
        raise GyronetError("the survey lists a sensor seed twice")
    if int(jobs) < 1:
        raise GyronetError(f"jobs must be a whole number >= 1, got {jobs}")
    if not spec.methods and not spec.bound:
        raise GyronetError("the survey needs at least one method (or bound)")
    tasks = (delayed(_run_or_fail)(seed, spec, sensor_folder(out_dir, seed), reuse) for seed in seeds)
    results: dict[int, dict[str, Any]] = {}
    bar = tqdm(total=len(seeds), desc="survey", unit="sensor", disable=None if progress is None else not progress)
    with bar, _worker_lost(out_dir):
        for result in Parallel(n_jobs=int(jobs), return_as="generator_unordered")(tasks):
            results[int(result["sensor_seed"])] = result
            bar.update(1)
            if "error" in result:
                log.warning("sensor %d failed (left out of the figures): %s", result["sensor_seed"], result["error"])
                continue
            log.info("sensor %d %s in %.0f s: worst axis %s", result["sensor_seed"],
                     "reused" if result.get("reused") else "done", result["seconds"],
                     ", ".join(f"{m} {worst_axis(result, m):.2f}" for m in result["methods"]))
    n_reused = sum(1 for r in results.values() if r.get("reused"))
    if n_reused:
        log.info("%d of %d sensors reused from %s", n_reused, len(seeds), out_dir)
    return [results[s] for s in seeds]


@contextlib.contextmanager
def _worker_lost(out_dir: str | Path):
    """A worker process killed by the system (out of memory: seen after 96 sensors) as one line, not a traceback."""
    from joblib.externals.loky.process_executor import TerminatedWorkerError

    try:
        yield
    except TerminatedWorkerError as err:
        raise GyronetError(f"a survey worker process was killed by the system ({type(err).__name__}: out of memory?); "
                           f"the sensors finished so far are kept: run the same command again to resume "
                           f"(hydra.run.dir={out_dir})") from None


def _run_or_fail(sensor_seed: int, spec: SurveySpec, folder: Path, reuse: bool) -> dict[str, Any]:
    """:func:`run_sensor`, or its one-line error as ``{"sensor_seed", "error"}``: one bad sensor does not end
    a survey of a hundred (it is counted and named in the table, and tried again on the next run)."""
    try:
        return run_sensor(sensor_seed, spec, folder, reuse)
    except GyronetError as err:
        return {"sensor_seed": int(sensor_seed), "error": str(err).splitlines()[0] if str(err) else type(err).__name__}
