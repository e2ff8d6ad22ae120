"""The GA sweeper plugin: discovery, search-space parsing, and multiruns of a tiny Hydra app."""
from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path

import numpy as np
import pytest
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.core.plugins import Plugins
from hydra.core.utils import JobReturn, JobStatus
from hydra.plugins.sweeper import Sweeper
from omegaconf import OmegaConf

from hydra_plugins.gyronet_ga_sweeper._history import score
from hydra_plugins.gyronet_ga_sweeper._space import parse_search_space, tidy, to_overrides

ROOT = Path(__file__).resolve().parents[1]

# A stand-in for scripts/train.py: returns (x - 3)^2 + (y + 1)^2, writes compensator/ into
# its output dir, logs each call, and fails, returns junk or takes its time (+sleep_s=) on request.
APP = '''
import os
import time
import hydra
from hydra.core.hydra_config import HydraConfig


@hydra.main(version_base="1.3", config_path="conf", config_name="config")
def main(cfg):
    out = HydraConfig.get().runtime.output_dir
    with open(cfg.calls_log, "a") as f:
        f.write(f"{cfg.x} {cfg.y}\\n")
    time.sleep(cfg.get("sleep_s", 0))
    os.makedirs(os.path.join(out, "compensator"), exist_ok=True)
    with open(os.path.join(out, "compensator", "params.txt"), "w") as f:
        f.write(f"{cfg.x} {cfg.y}")
    with open(os.path.join(out, "compensator", "stage.txt"), "w") as f:
        f.write(str(cfg.get("stage", "")))
    if cfg.fail == "always" or (cfg.fail == "positive_x" and cfg.x > 0) or os.environ.get("GA_TEST_FAIL"):
        raise RuntimeError("boom")
    value = (cfg.x - 3) ** 2 + (cfg.y + 1) ** 2
    print(f"fitness={value!r}")
    return value


if __name__ == "__main__":
    main()
'''

# the app's own default search space, found through the sweeper's optional params group
SPACE = """\
x: interval(-5, 5)
y: interval(-5, 5)
"""


@pytest.fixture
def app(tmp_path: Path) -> Path:
    (tmp_path / "conf" / "hydra" / "sweeper" / "params").mkdir(parents=True)
    (tmp_path / "app.py").write_text(APP)
    (tmp_path / "conf" / "config.yaml").write_text(
        f"x: 0.0\ny: 0.0\nfail: never\ncalls_log: {tmp_path / 'calls.log'}\n")
    (tmp_path / "conf" / "hydra" / "sweeper" / "params" / "default.yaml").write_text(SPACE)
    return tmp_path


def _command(app: Path, overrides: tuple, sweep: str, multirun: bool) -> list[str]:
    args = [sys.executable, str(app / "app.py")]
    if multirun:
        args += ["-m", "hydra/sweeper=ga", "hydra.sweeper.population_size=4",
                 "hydra.sweeper.generations=2", f"hydra.sweep.dir={app / sweep}"]
    return args + list(overrides)


def _env() -> dict:
    # the repo root on the path is how Hydra finds hydra_plugins without an install
    return {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}


def start_app(app: Path, *overrides: str, sweep: str = "sweep") -> subprocess.Popen:
    """Start a GA multirun of the app in the background."""
    return subprocess.Popen(_command(app, overrides, sweep, True), cwd=app, env=_env(),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def finish(proc: subprocess.Popen) -> None:
    out, err = proc.communicate(timeout=120)
    assert proc.returncode == 0, f"exit {proc.returncode}\n{out}\n{err}"


def run_app(app: Path, *overrides: str, sweep: str = "sweep", multirun: bool = True,
            check: bool = True, env: dict | None = None) -> subprocess.CompletedProcess:
    """Run the app (a GA multirun of 4 x 2 by default) and wait for it; ``env`` is added to the environment."""
    proc = subprocess.run(_command(app, overrides, sweep, multirun), cwd=app, env={**_env(), **(env or {})},
                          capture_output=True, text=True, timeout=120)
    if check and proc.returncode != 0:
        raise AssertionError(f"exit {proc.returncode}\n{proc.stdout}\n{proc.stderr}")
    return proc


def history(app: Path, sweep: str = "sweep") -> dict:
    return json.loads((app / sweep / "ga_history.json").read_text())


def calls(app: Path) -> int:
    path = app / "calls.log"
    return len(path.read_text().splitlines()) if path.exists() else 0


# ---------------------------------------------------------------- in-process


def test_plugin_is_discovered() -> None:
    names = [f"{p.__module__}.{p.__name__}" for p in Plugins.instance().discover(Sweeper)]
    assert "hydra_plugins.gyronet_ga_sweeper.ga_sweeper.GASweeper" in names


def test_search_space_grammar() -> None:
    lines = ["a=int(interval(8, 64))", "b=interval(1e-3, 1e-1)", "c=tag(log, interval(1e-4, 1e-1))",
             "d=choice(relu, tanh)", "e=1,2,3", "f=range(0, 3)", "g=tag(log, int(interval(1, 1024)))",
             "data.path=F.csv", "b=interval(0, 1)", "d=relu"]
    space, fixed = parse_search_space(lines, OverridesParser.create())
    kinds = {p.name: (p.kind, p.low, p.high, p.choices) for p in space}
    assert kinds == {
        "a": ("int", 8, 64, ()), "b": ("float", 0.0, 1.0, ()),
        "c": ("log-float", 1e-4, 1e-1, ()), "e": ("choice", None, None, (1, 2, 3)),
        "f": ("choice", None, None, (0, 1, 2)), "g": ("log-int", 1, 1024, ()),
    }
    # a later plain value fixes a searched key (the command line wins over the config)
    assert fixed == ["data.path=F.csv", "d=relu"]


def test_overrides_round_trip_through_the_parser() -> None:
    ind = tidy({"lr": 1.234567891e-5, "n": 12, "act": "tanh", "flag": True, "w": 0.3}, [])
    parsed = OverridesParser.create().parse_overrides(to_overrides(ind))
    assert {o.key_or_group: o.value() for o in parsed} == ind


@pytest.mark.parametrize("status, value, expected", [
    (JobStatus.COMPLETED, 1.5, (1.5, "COMPLETED")),
    (JobStatus.COMPLETED, np.float32(2.0), (2.0, "COMPLETED")),
    (JobStatus.COMPLETED, math.nan, (math.inf, "NONFINITE")),
    (JobStatus.COMPLETED, -math.inf, (math.inf, "NONFINITE")),
    (JobStatus.COMPLETED, None, (math.inf, "INVALID")),
    (JobStatus.COMPLETED, "0.5", (math.inf, "INVALID")),
    (JobStatus.COMPLETED, {"val/rmse": 1.0}, (math.inf, "INVALID")),
    (JobStatus.FAILED, RuntimeError("boom"), (math.inf, "FAILED")),
])
def test_job_scores(status: JobStatus, value: object, expected: tuple) -> None:
    ret = JobReturn(status=status, _return_value=value)
    fitness, state, error = score(ret)
    assert (fitness, state) == expected
    assert (error is None) == (state == "COMPLETED")


def test_gyronet_default_search_space_matches_train_config() -> None:
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(ROOT / "conf"), version_base="1.3"):
        cfg = compose(config_name="train", overrides=["hydra/sweeper=ga"], return_hydra_config=True)
        tuned = compose(config_name="train", overrides=["search=ga"], return_hydra_config=True)
    params = cfg.hydra.sweeper.params
    assert set(params) == {"model.n_centers", "model.width_init", "optim.lr",
                           "train.weight_decay", "data.rate_tau_s", "seed", "train.for_bundle"}
    # search jobs stop at validation; the final run of the best makes the bundle
    assert params["train.for_bundle"] == "false" and dict(cfg.hydra.sweeper.final) == {"train.for_bundle": "true"}
    # every searched key exists in the training config, so each job's override applies
    missing = [k for k in params if OmegaConf.select(cfg, k, default="<missing>") == "<missing>"]
    assert missing == []
    assert tuned.hydra.sweeper._target_.endswith("GASweeper")
    assert tuned.hydra.sweeper.params == params


# ---------------------------------------------------------------- multiruns


def test_sweep_writes_history_results_and_best(app: Path) -> None:
    run_app(app)
    hist = history(app)
    gens = hist["generations"]
    assert [g["generation"] for g in gens] == [0, 1]
    assert all(len(g["individuals"]) == 4 for g in gens)
    assert {p["name"] for p in hist["search_space"]} == {"x", "y"}
    jobs = [e for g in gens for e in g["individuals"] if not e["cached"]]
    assert calls(app) == len(jobs) >= 5  # elites are reused, not run again
    for e in jobs:
        assert e["status"] == "COMPLETED"
        assert (app / "sweep" / e["job_dir"] / "compensator").is_dir()
        assert e["fitness"] == pytest.approx((e["params"]["x"] - 3) ** 2 + (e["params"]["y"] + 1) ** 2)
    results = OmegaConf.load(app / "sweep" / "optimization_results.yaml")
    best = min(jobs, key=lambda e: e["fitness"])
    assert results.name == "ga"
    assert results.best_evaluated_result == pytest.approx(best["fitness"])
    assert dict(results.best_evaluated_params) == best["params"]
    # the best job's artifact is copied, and its overrides give the same value back
    copied = (app / "sweep" / "best" / "compensator" / "params.txt").read_text()
    assert copied == f"{best['params']['x']} {best['params']['y']}"
    single = run_app(app, *results.best_overrides, multirun=False)
    assert f"fitness={results.best_evaluated_result!r}" in single.stdout
    assert list((app / "sweep" / "tb").glob("events.out.tfevents.*"))


def test_generation_zero_starts_from_the_config(app: Path) -> None:
    # x = 0 as the app's config has it; y = 9 lies outside y's space and is clipped to 5
    config = app / "conf" / "config.yaml"
    config.write_text(config.read_text().replace("y: 0.0", "y: 9.0"))
    run_app(app, "hydra.sweeper.generations=1")
    first = history(app)["generations"][0]["individuals"]
    assert first[0]["params"] == {"x": 0.0, "y": 5.0}
    assert all(e["params"] != {"x": 0.0, "y": 5.0} for e in first[1:])
    run_app(app, "hydra.sweeper.generations=1", "hydra.sweeper.start_from_config=false", sweep="random")
    assert history(app, "random")["generations"][0]["individuals"][0]["params"] != {"x": 0.0, "y": 5.0}


def test_failed_jobs_score_inf_and_the_sweep_goes_on(app: Path) -> None:
    # y from the command line replaces the app's interval with a choice
    run_app(app, "fail=positive_x", "hydra.sweeper.max_failure_rate=1.0", "y=choice(-1, 0, 1)")
    hist = history(app)
    assert {p["name"]: p for p in hist["search_space"]}["y"] == {
        "name": "y", "kind": "choice", "choices": [-1, 0, 1]}
    individuals = [e for g in hist["generations"] for e in g["individuals"]]
    assert all(e["params"]["y"] in (-1, 0, 1) for e in individuals)
    failed = [e for e in individuals if e["status"] == "FAILED"]
    assert failed and all(e["params"]["x"] > 0 for e in failed)
    assert all(e["fitness"] is None and "boom" in e["error"] for e in failed)
    results = OmegaConf.load(app / "sweep" / "optimization_results.yaml")
    assert results.best_evaluated_params.x <= 0


def test_the_final_run_makes_the_best_artifact_with_the_final_overrides(app: Path) -> None:
    (app / "conf" / "hydra" / "sweeper" / "final").mkdir()
    (app / "conf" / "hydra" / "sweeper" / "final" / "default.yaml").write_text('stage: "final"\n')
    with open(app / "conf" / "config.yaml", "a") as config:
        config.write("stage: search\n")
    run_app(app)
    jobs = [e for g in history(app)["generations"] for e in g["individuals"] if not e["cached"]]
    assert calls(app) == len(jobs) + 1  # every search job, then the best once more
    best = min(jobs, key=lambda e: e["fitness"])
    copied = app / "sweep" / "best" / "compensator"
    assert (copied / "stage.txt").read_text() == "final"
    assert (copied / "params.txt").read_text() == f"{best['params']['x']} {best['params']['y']}"
    results = OmegaConf.load(app / "sweep" / "optimization_results.yaml")
    assert results.best_overrides[-1] == "stage=final"
    assert (app / "sweep" / best["job_dir"] / "compensator" / "stage.txt").read_text() == "search"
    # run again, finished: the final run is reused from the history, not set aside as interrupted and run again
    final = history(app)["final_run"]
    assert final["job_idx"] == max(e["job_idx"] for e in jobs) + 1 and final["overrides"][-1] == "stage=final"
    proc = run_app(app)
    assert calls(app) == len(jobs) + 1 and "final run reused" in proc.stdout + proc.stderr
    assert not (app / "sweep" / "interrupted").exists() and (copied / "stage.txt").read_text() == "final"


def _tb_steps(tb_dir: Path, tag: str) -> list:
    """Every step logged for ``tag`` in the event files of ``tb_dir``, repeats included."""
    from tensorboard.backend.event_processing.event_file_loader import EventFileLoader

    return sorted(event.step for path in tb_dir.glob("events.out.tfevents.*") for event in EventFileLoader(str(path)).Load()
                  if any(value.tag == tag for value in event.summary.value))


def test_a_stopped_extension_keeps_the_final_bundle_and_logs_each_generation_once(app: Path) -> None:
    """An extension of a finished sweep that stopped for failures replaced best/ with a search job's bundle, and
    its stopping generation was in TensorBoard twice once resumed."""
    (app / "conf" / "hydra" / "sweeper" / "final").mkdir()
    (app / "conf" / "hydra" / "sweeper" / "final" / "default.yaml").write_text('stage: "final"\n')
    with open(app / "conf" / "config.yaml", "a") as config:
        config.write("stage: search\n")
    run_app(app)
    final = history(app)["final_run"]
    proc = run_app(app, "hydra.sweeper.generations=3", check=False, env={"GA_TEST_FAIL": "1"})
    assert proc.returncode != 0 and "GA sweep stopped" in proc.stderr
    assert (app / "sweep" / "best" / "compensator" / "stage.txt").read_text() == "final"
    results = OmegaConf.load(app / "sweep" / "optimization_results.yaml")
    assert results.best_artifact_job_dir == final["job_dir"] and results.best_artifact_is_final_run is True
    run_app(app, "hydra.sweeper.generations=3")
    assert _tb_steps(app / "sweep" / "tb", "ga/failed_jobs") == [0, 1, 2]


def test_a_sweep_in_which_every_job_failed_is_an_error(app: Path) -> None:
    proc = run_app(app, "fail=always", "hydra.sweeper.max_failure_rate=1.0", check=False)
    assert proc.returncode != 0 and "GA sweep ended without a result: none of its 8 jobs" in proc.stderr


def test_a_malformed_search_space_is_one_line(tmp_path: Path) -> None:
    """interval(3.0, 0.3) or a log interval from 0 gave a 39-line traceback."""
    for space, message in [("model.width_init=interval(3.0, 0.3)", "model.width_init: needs bounds low <= high"),
                           ("optim.lr=tag(log, interval(0, 0.1))", "optim.lr: a log scale needs low > 0")]:
        proc = subprocess.run([sys.executable, str(ROOT / "scripts" / "train.py"), "-m", "hydra/sweeper=ga",
                               "data.path=F.csv", f"hydra.sweep.dir={tmp_path / 'S'}", space], cwd=tmp_path,
                              env=_env(), capture_output=True, text=True, timeout=120)
        assert proc.returncode == 2 and proc.stderr.startswith(f"error: bad GA search space: {message}"), proc.stderr
        assert len(proc.stderr.strip().splitlines()) == 1


def test_a_final_run_that_cannot_start_leaves_the_best_search_jobs_artifact(app: Path) -> None:
    (app / "conf" / "hydra" / "sweeper" / "final").mkdir()
    (app / "conf" / "hydra" / "sweeper" / "final" / "default.yaml").write_text('no_such_key: "1"\n')
    proc = run_app(app)
    assert "the final run could not start" in proc.stdout + proc.stderr
    assert (app / "sweep" / "best" / "compensator" / "stage.txt").read_text() == ""


def test_too_many_failures_stop_the_sweep(app: Path) -> None:
    proc = run_app(app, "fail=always", check=False)
    assert proc.returncode != 0
    assert "GA sweep stopped: 4 of 4 jobs failed in generation 0" in proc.stderr
    assert "max_failure_rate=0.5" in proc.stderr
    assert len(history(app)["generations"]) == 1
    assert calls(app) == 4
    assert OmegaConf.load(app / "sweep" / "optimization_results.yaml").best_evaluated_result is None


def test_resume_continues_without_redoing_generations(app: Path) -> None:
    run_app(app)
    before, n_calls = history(app), calls(app)
    # what a killed third generation would have left: a job folder that is in no history
    leftover = app / "sweep" / str(1 + max(e["job_idx"] for g in before["generations"] for e in g["individuals"]))
    (leftover / "tb").mkdir(parents=True)
    (leftover / "tb" / "events.out.tfevents.killed").write_text("")
    run_app(app, "hydra.sweeper.generations=3")
    assert (app / "sweep" / "interrupted" / leftover.name / "tb" / "events.out.tfevents.killed").is_file()
    assert not (leftover / "tb" / "events.out.tfevents.killed").exists() and leftover.is_dir()  # run again, clean
    after = history(app)
    assert after["generations"][:2] == before["generations"]
    new_jobs = [e for e in after["generations"][2]["individuals"] if not e["cached"]]
    assert calls(app) == n_calls + len(new_jobs)
    first_new = min(e["job_idx"] for e in new_jobs)
    assert first_new == 1 + max(e["job_idx"] for g in before["generations"] for e in g["individuals"])
    assert OmegaConf.load(app / "sweep" / "optimization_results.yaml").generations == 3


@pytest.mark.slow
def test_resumed_sweep_is_the_uninterrupted_one(app: Path) -> None:
    # reseeding per generation: stopping after 2 and resuming breeds what 3 in one go breed
    straight = start_app(app, "hydra.sweeper.generations=3", "calls_log=straight.log",
                         sweep="straight")
    run_app(app)
    run_app(app, "hydra.sweeper.generations=3")
    finish(straight)
    def params(sweep: str) -> list:
        return [[e["params"] for e in g["individuals"]] for g in history(app, sweep)["generations"]]
    assert len(params("sweep")) == 3
    assert params("straight") == params("sweep")


def test_resume_refuses_other_fixed_overrides(app: Path) -> None:
    """Another recording (or any other fixed setting) on resume: the cached fitness would not compare."""
    run_app(app)
    before = calls(app)
    proc = run_app(app, "+sleep_s=0", check=False)
    assert proc.returncode != 0 and "other fixed overrides" in proc.stderr and "+sleep_s=0" in proc.stderr
    assert calls(app) == before


def test_rerun_after_a_failed_generation_runs_it_again(app: Path) -> None:
    """"Rerun to resume after fixing the cause": the failed generation was saved as done, so nothing was retried."""
    assert run_app(app, "fail=always", check=False).returncode != 0
    run_app(app, "fail=never")  # the fix is a changed setting: nothing of the failed sweep is reused
    gens = history(app)["generations"]
    assert len(gens) == 2 and all(e["status"] == "COMPLETED" for g in gens for e in g["individuals"])
    assert (app / "sweep" / "interrupted" / "0").is_dir()  # the failed jobs' folders, set aside


def test_resume_refuses_changed_data_and_breeding_but_not_reordered_overrides(app: Path) -> None:
    data = app / "data.txt"
    data.write_text("one")
    run_app(app, f"+data={data}", "fail=never")
    before = calls(app)
    run_app(app, "fail=never", f"+data={data}", "hydra.sweeper.generations=3")  # the same, in another order
    assert len(history(app)["generations"]) == 3
    proc = run_app(app, f"+data={data}", "fail=never", "hydra.sweeper.generations=3", "hydra.sweeper.seed=7",
                   check=False)
    assert proc.returncode != 0 and "bred with other options (seed 0 now 7)" in proc.stderr
    data.write_text("two")
    proc = run_app(app, f"+data={data}", "fail=never", "hydra.sweeper.generations=4", check=False)
    assert proc.returncode != 0 and f"a sweep of other data: {data} changed" in proc.stderr
    data.unlink()  # gone: was taken as unchanged
    proc = run_app(app, f"+data={data}", "fail=never", "hydra.sweeper.generations=4", check=False)
    assert proc.returncode != 0 and f"a sweep of other data: {data} (gone) changed" in proc.stderr
    assert calls(app) == before + sum(not e["cached"] for e in history(app)["generations"][2]["individuals"])


def test_a_killed_first_generation_and_a_sweep_started_over_leave_no_old_files_in_use(app: Path) -> None:
    killed = app / "sweep" / "0" / "tb"
    killed.mkdir(parents=True)
    (killed / "events.out.tfevents.killed").write_text("")
    run_app(app)
    assert (app / "sweep" / "interrupted" / "0" / "tb" / "events.out.tfevents.killed").is_file()
    assert not (killed / "events.out.tfevents.killed").exists()
    run_app(app, "hydra.sweeper.resume=false")
    assert (app / "sweep" / "interrupted" / "tb").is_dir() and (app / "sweep" / "interrupted" / "0.1").is_dir()
    # and its history: a kill before the new generation 0 is saved must not resume the discarded sweep
    assert (app / "sweep" / "interrupted" / "ga_history.json").is_file()
    assert len(list((app / "sweep" / "tb").glob("events.out.tfevents.*"))) == 1  # the new sweep's curves alone


def test_a_second_sweep_in_the_same_folder_is_refused(app: Path) -> None:
    first = start_app(app, "+sleep_s=5", "hydra.sweeper.generations=1")  # four jobs of 5 s, one at a time
    try:
        deadline = time.monotonic() + 60
        while calls(app) == 0:  # the first holds the lock once it launches: 15 s more at least
            assert first.poll() is None and time.monotonic() < deadline, "the first sweep did not start"
            time.sleep(0.05)
        proc = run_app(app, "+sleep_s=5", "hydra.sweeper.generations=1", check=False)
        assert proc.returncode != 0 and "another GA sweep is running in" in proc.stderr
    finally:
        finish(first)


def test_options_that_search_nothing_are_refused() -> None:
    from hydra_plugins.gyronet_ga_sweeper.config import GAOptions

    good = dict(population_size=4, generations=2, tournament_size=3, crossover_rate=0.9, mutation_rate=0.2,
                mutation_scale=0.1, elitism=1, seed=0, max_failure_rate=0.5, start_from_config=True, resume=True,
                best_artifact=None)
    GAOptions(**good)
    for key, value, message in [("population_size", 1, "population_size must be at least 2"),
                                ("generations", 0, "generations must be at least 1"),
                                ("elitism", 4, "elitism must be in"), ("elitism", -1, "elitism must be in"),
                                ("tournament_size", 0, "tournament_size"), ("crossover_rate", 5.0, "crossover_rate"),
                                ("mutation_scale", -0.1, "mutation_scale"), ("seed", -1, "seed must be >= 0")]:
        with pytest.raises(ValueError, match=message):
            GAOptions(**{**good, key: value})


def test_resume_refuses_another_search_space(app: Path) -> None:
    (app / "sweep").mkdir()
    space = [{"name": "x", "kind": "float", "low": 0.0, "high": 1.0}]
    (app / "sweep" / "ga_history.json").write_text(json.dumps(
        {"version": 1, "search_space": space, "fixed_overrides": [], "generations": []}))
    proc = run_app(app, check=False)
    assert proc.returncode != 0
    assert "another search space" in proc.stderr
    assert calls(app) == 0


def _processes_with(marker: str) -> list[int]:
    """Live processes (not zombies) whose environment holds ``marker``: a sweep and all it started."""
    found = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            if marker.encode() not in (entry / "environ").read_bytes():
                continue
            state = (entry / "stat").read_text().rsplit(")", 1)[1].split()[0]
        except OSError:  # gone meanwhile, or not ours to read
            continue
        if state != "Z":
            found.append(int(entry.name))
    return found


@pytest.mark.skipif(not Path("/proc/self/environ").exists(), reason="reads processes from Linux /proc")
def test_a_killed_sweep_leaves_no_worker_behind(app: Path) -> None:
    """Issue 10 item 13: after SIGKILL of the sweep, its joblib workers went on with their jobs."""
    marker = f"GYRONET_SWEEP_TEST={uuid.uuid4().hex}"
    name, value = marker.split("=")
    cmd = _command(app, ("hydra/launcher=joblib", "hydra.launcher.n_jobs=2", "+sleep_s=60"), "sweep", True)
    sweep = subprocess.Popen(cmd, cwd=app, env={**_env(), name: value},
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 90
        while calls(app) < 2:  # both workers run a job (and sleep): a worker is watched from its first job
            assert sweep.poll() is None and time.monotonic() < deadline, "no job started"
            time.sleep(0.1)
        workers = [pid for pid in _processes_with(marker) if pid != sweep.pid]
        assert workers, "the jobs should run in worker processes"
        sweep.kill()
        sweep.wait()
        started = calls(app)
        deadline = time.monotonic() + 20  # a loaded CI machine; the jobs sleep 60 s
        while _processes_with(marker) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert _processes_with(marker) == []
        time.sleep(0.5)
        assert calls(app) == started  # and no worker took another job meanwhile
    finally:
        for pid in _processes_with(marker):
            os.kill(pid, signal.SIGKILL)


def test_joblib_launcher(app: Path) -> None:
    run_app(app, "hydra/launcher=joblib", "hydra.launcher.n_jobs=2", "fail=positive_x",
            "hydra.sweeper.max_failure_rate=1.0")
    gens = history(app)["generations"]
    assert [len(g["individuals"]) for g in gens] == [4, 4]
    individuals = [e for g in gens for e in g["individuals"]]
    # each worker's own result reaches the sweeper: failed exactly where the app raised, else the app's fitness
    assert "COMPLETED" in {e["status"] for e in individuals}
    for e in individuals:
        x, y = e["params"]["x"], e["params"]["y"]
        assert e["status"] == ("FAILED" if x > 0 else "COMPLETED"), e
        assert e["fitness"] is None if x > 0 else e["fitness"] == pytest.approx((x - 3) ** 2 + (y + 1) ** 2), e
    assert (app / "sweep" / "best" / "compensator" / "params.txt").exists()
