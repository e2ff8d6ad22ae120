"""Every command on bad input: exit status 2, one line on stderr, no traceback; Hydra's own errors included.

Starting Python and importing torch costs seconds per process, so the commands run in one
"zygote" subprocess: it imports the heavy modules once, then forks a child per case that runs the
script as ``python scripts/X.py ...`` would (``runpy``, the real exit status, stdout and stderr
at the file-descriptor level). A few cases also run as real subprocesses, to check the zygote.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PRELOAD = ("torch", "hydra", "matplotlib.pyplot", "gyronet.training.pipeline", "gyronet.analysis.diagnose", "gyronet.bundle.offline",
           "gyronet.analysis.table", "gyronet.allan", "gyronet.sim", "gyronet.recordings.importers", "gyronet.deploy.stream.live",
           "gyronet.deploy.stream.pty_sensor", "gyronet.figures.tb")


# ---------------------------------------------------------------- the zygote


def _zygote(cases_path: str, out_dir: str) -> None:
    """Run each case of ``cases_path`` in a forked child; print one JSON line per case."""
    import importlib
    import runpy
    import time
    import traceback

    sys.path.insert(0, str(ROOT / "scripts"))
    for name in PRELOAD:
        importlib.import_module(name)
    importlib.import_module("_cli")
    for case in json.loads(Path(cases_path).read_text()):
        out, err = Path(out_dir) / f"{case['id']}.out", Path(out_dir) / f"{case['id']}.err"
        sys.stdout.flush()
        sys.stderr.flush()
        pid = os.fork()
        if pid == 0:  # the child: what `python scripts/X.py ARGS` would do
            code = 1
            try:
                os.dup2(os.open(out, os.O_WRONLY | os.O_CREAT | os.O_TRUNC), 1)
                os.dup2(os.open(err, os.O_WRONLY | os.O_CREAT | os.O_TRUNC), 2)
                sys.argv = [case["script"], *case["args"]]
                runpy.run_path(case["script"], run_name="__main__")
                code = 0
            except SystemExit as stop:
                code = stop.code if isinstance(stop.code, int) else (0 if stop.code is None else 1)
                if isinstance(stop.code, str):
                    print(stop.code, file=sys.stderr)
            except BaseException:  # noqa: BLE001 -- as the interpreter would: traceback, status 1
                traceback.print_exc()
            finally:
                sys.stdout.flush()
                sys.stderr.flush()
                os._exit(code)
        started = time.monotonic()
        deadline = started + case.get("timeout_s", 60)
        while True:
            done, status = os.waitpid(pid, os.WNOHANG)
            if done:
                code = os.waitstatus_to_exitcode(status)
                break
            if time.monotonic() > deadline:
                os.kill(pid, 9)
                os.waitpid(pid, 0)
                code = "timeout"
                break
            time.sleep(0.02)
        print(json.dumps({"id": case["id"], "code": code, "seconds": round(time.monotonic() - started, 2),
                          "stdout": out.read_text(errors="replace"),
                          "stderr": err.read_text(errors="replace")}), flush=True)


def run_cases(cases: list[dict], work: Path) -> dict[str, dict]:
    """Run ``cases`` (id, script, args) in one zygote; return what each did, by id."""
    work.mkdir(parents=True, exist_ok=True)
    (work / "cases.json").write_text(json.dumps(cases))
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    env.pop("HYDRA_FULL_ERROR", None)
    proc = subprocess.run([sys.executable, __file__, str(work / "cases.json"), str(work)], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=60 + 60 * len(cases))
    assert proc.returncode == 0, proc.stderr[-3000:]
    # importing every command's modules says nothing on stderr (a warning there would be a second line)
    assert proc.stderr == "", proc.stderr[-3000:]
    results = [json.loads(line) for line in proc.stdout.splitlines() if line.startswith("{")]
    return {r["id"]: r for r in results}


def assert_one_line_error(result: dict, *expected: str) -> str:
    """Exit 2, exactly one non-empty line on stderr (``error: ...``), no traceback anywhere; returns it."""
    lines = [line for line in result["stderr"].splitlines() if line.strip()]
    context = f"exit {result['code']}\nstderr:\n{result['stderr'][-2000:]}\nstdout:\n{result['stdout'][-1000:]}"
    assert result["code"] == 2, context
    assert len(lines) == 1 and lines[0].startswith("error: "), context
    assert "Traceback" not in result["stdout"] + result["stderr"], context
    for text in expected:
        assert text in lines[0], context
    return lines[0]


# ---------------------------------------------------------------- the cases


@pytest.fixture(scope="module")
def bad_files(tmp_path_factory) -> dict[str, Path]:
    """A recording each command must refuse: missing, not CSV, empty, without a required column."""
    folder = tmp_path_factory.mktemp("bad")
    (folder / "binary.csv").write_bytes(b"\x00\x01\x02\xff\xfe binary \x00")
    (folder / "empty.csv").write_text("")
    (folder / "no_gyro.csv").write_text("time_s,temp_c\n0,20\n0.5,20\n1.0,20.1\n")
    return {"missing": folder / "nope.csv", "not_csv": folder / "binary.csv", "empty": folder / "empty.csv",
            "no_column": folder / "no_gyro.csv"}


# what each of them is refused for, in the one line
BAD_FILE_REASONS = {"missing": "no such file", "not_csv": "not a CSV file", "empty": "empty file",
                    "no_column": "missing required column(s) gyro_x_dps"}


def command_cases(bundle: Path, work: Path) -> dict[str, dict]:
    """Per command: the key that names its input file (or None), base arguments, a typo and its fix."""
    return {
        "train": {"file": "data.path", "args": ["train.progress=false", "train.max_epochs=5"],
                  "typo": ("data.pth=F.csv", "did you mean data.path?")},
        "diagnose": {"file": "data.path", "args": ["train.max_epochs=5"],
                     "typo": ("data.pth=F.csv", "did you mean data.path?")},
        "table": {"file": "input", "args": [f"+bundles={{gyronet: {bundle}}}", f"output={work}/t.md"],
                  "typo": ("inptu=F.csv", "did you mean input?")},
        "allan": {"file": "input", "args": [f"output={work}/a.json"], "typo": ("per_decad=5", "did you mean per_decade?")},
        "compensate": {"file": "input", "args": [f"model={bundle}", f"output={work}/o.csv"],
                       "typo": ("outptu=O.csv", "did you mean output?")},
        "convert": {"file": "input", "args": [f"output={work}/c.csv"], "typo": ("fromat=csv", "did you mean format?")},
        "emulate_sensor": {"file": "input", "args": ["speed=0", "reader_timeout_s=0.1"],
                           "typo": ("sped=0", "did you mean speed?")},
        "simulate": {"file": None, "args": [f"output={work}/s.csv"], "typo": ("profil=cycle", "did you mean profile?")},
        "stream": {"file": "model", "args": ["port=loop://", f"output={work}/l.csv", "max_samples=10"],
                   "typo": ("bad=9600", "did you mean baud?")},
    }


def bad_input_cases(bundle: Path, bad_files: dict[str, Path], work: Path) -> list[dict]:
    cases = []
    for name, spec in command_cases(bundle, work).items():
        script, key, base = f"scripts/{name}.py", spec["file"], spec["args"]

        def add(case: str, args: list[str], expect: tuple = ()) -> None:
            cases.append({"id": f"{name}-{case}", "script": script, "expect": list(expect),
                          "args": [*args, f"hydra.run.dir={work / name / case}"]})

        # the stream's "file" is its bundle folder: a missing one, or a file that is no bundle
        files = {k: v for k, v in bad_files.items() if key != "model" or k in ("missing", "not_csv")}
        for case, path in files.items() if key else ():
            reason = "not a compensator bundle" if key == "model" else BAD_FILE_REASONS[case]
            add(case, [*[a for a in base if not a.startswith(f"{key}=")], f"{key}={path}"], (path.name, reason))
        typo, suggestion = spec["typo"]
        add("typo", [*base, typo], (suggestion,))
        # the mandatory value: the input file, or what the command cannot do without
        dropped = key or "output"
        add("missing_value", [a for a in base if not a.startswith(f"{dropped}=")], (dropped,))
        add("bad_override", [*base, "seed=[1,"], ("bad override",))
    return cases


# the brief's own examples for train.py, Hydra's errors among them
TRAIN_EXTRA = {
    "plus_typo": (["+data.pth=F.csv"], "unknown setting data.pth; did you mean data.path?"),
    "typo_top": (["trian.max_epochs=3"], "did you mean train.max_epochs?"),
    "typo_plus_in_train": (["+train.max_epoch=3", "data.path=F.csv"], "did you mean train.max_epochs?"),
    "unknown_top": (["foo=1"], "unknown setting foo; the settings at the top level are data,"),
    "no_such_option": (["model=nope"], "no option 'nope' for model; the options are default, default_nolag, lsq, poly3, px4, px4_onboard, rbf"),
    "close_option": (["model=rbff"], "did you mean model=rbf?"),
    "hydra_key_typo": (["hydra.run.dri=x"], "did you mean hydra.run.dir?"),
    "bad_interpolation": (["data.path=F.csv", "data.block_s=${nope}"], "nope"),
    "wrong_type": (["data.path=F.csv", "model.n_centers=abc"], "model.n_centers must be an integer, got 'abc'"),
    "wrong_item_type": (["data.path=F.csv", "data.static_rate_dps=[a,0,0]"],
                        "data.static_rate_dps must be a list of numbers"),
    "eval_paths_text": (["data.path=F.csv", "eval.paths=G.csv"],
                        "eval.paths must be a list, got 'G.csv' (a list on the command line: 'eval.paths=[G.csv]')"),
    "argparse_style": (["--model", "rbf"], "--model: options are key=value, not --key value: write model=rbf"),
}


def default_case(case_id: str) -> bool:
    """The default run: every bad input through train and diagnose, a typo through every other command."""
    name, kind = case_id.split("-", 1)
    return name in ("train", "diagnose") or kind == "typo"


@pytest.fixture(scope="module")
def results(tmp_path_factory, bad_files) -> dict[str, dict]:
    work = tmp_path_factory.mktemp("commands")
    # no default case gets as far as a bundle (the slow matrix below uses a real one)
    cases = [c for c in bad_input_cases(work / "no_bundle", bad_files, work) if default_case(c["id"])]
    for case, (args, expect) in TRAIN_EXTRA.items():
        cases.append({"id": f"train-{case}", "script": "scripts/train.py", "expect": [expect],
                      "args": [*args, "train.progress=false", f"hydra.run.dir={work / 'train' / case}"]})
    # an output that cannot be written (under a file): the path and the reason, no traceback
    not_a_folder = bad_files["empty"]
    cases.append({"id": "simulate-unwritable_output", "script": "scripts/simulate.py", "expect": [str(not_a_folder)],
                  "args": [f"output={not_a_folder}/s.csv", "profile=constant", "duration_s=60",
                           f"hydra.run.dir={work / 'simulate' / 'unwritable'}"]})
    # an output that is the input itself: the recording would be replaced (convert, compensate and allan did)
    victim = bad_files["no_column"]
    for name, extra in (("compensate", [f"model={work / 'no_bundle'}"]), ("convert", []), ("allan", [])):
        cases.append({"id": f"{name}-output_is_input", "script": f"scripts/{name}.py",
                      "expect": [str(victim), "the output is the input file itself"],
                      "args": [*extra, f"input={victim}", f"output={victim.parent / '.' / victim.name}",
                               f"hydra.run.dir={work / name / 'output_is_input'}"]})
    ok = [("help", ["--help"]), ("cfg_job", ["--cfg", "job", "data.path=F.csv"])]
    cases += [{"id": f"train-{case}", "script": "scripts/train.py", "args": args} for case, args in ok]
    # good runs through the same wrapper: a single run into hydra.run.dir, and a -m multirun
    quick = ["profile=constant", "duration_s=60", "fs_hz=2"]
    cases.append({"id": "simulate-run", "script": "scripts/simulate.py",
                  "args": [f"output={work}/one.csv", *quick, f"hydra.run.dir={work / 'one_run'}"]})
    cases.append({"id": "simulate-multirun", "script": "scripts/simulate.py",
                  "args": ["-m", f"output={work}/m0.csv,{work}/m1.csv", *quick, f"hydra.sweep.dir={work / 'sweep'}"]})
    # a multirun: the failed job raises inside the sweep, and the sweep's end is one line
    cases.append({"id": "train-ga_all_failed", "script": "scripts/train.py", "args": [
        "-m", "hydra/sweeper=ga", f"data.path={bad_files['no_column']}", f"hydra.sweep.dir={work / 'ga'}",
        "hydra.sweeper.population_size=2", "hydra.sweeper.generations=1", "train.progress=false"]})
    by_id = run_cases(cases, work)
    for case in cases:
        by_id[case["id"]]["expect"] = case.get("expect", [])
        by_id[case["id"]]["work"] = str(work)
    return by_id


def _default_ids() -> list[str]:
    placeholder = Path("/b")
    files = {"missing": placeholder, "not_csv": placeholder, "empty": placeholder, "no_column": placeholder}
    return [c["id"] for c in bad_input_cases(placeholder, files, placeholder) if default_case(c["id"])]


@pytest.mark.parametrize("case", _default_ids() + [f"train-{c}" for c in TRAIN_EXTRA] + ["simulate-unwritable_output"]
                         + [f"{name}-output_is_input" for name in ("compensate", "convert", "allan")])
def test_bad_input_is_one_line_and_exit_2(results, bad_files, case):
    result = results[case]
    assert_one_line_error(result, *result["expect"])
    assert bad_files["no_column"].read_text() == "time_s,temp_c\n0,20\n0.5,20\n1.0,20.1\n"  # no input was replaced


def test_help_and_show_config_still_work(results):
    assert results["train-help"]["code"] == 0, results["train-help"]["stderr"]
    assert "== Configuration groups ==" in results["train-help"]["stdout"]
    shown = results["train-cfg_job"]
    assert shown["code"] == 0 and "_target_: gyronet.training.runs.training_data" in shown["stdout"], shown["stderr"]


def test_good_runs_and_multiruns_still_work(results):
    work = Path(results["simulate-run"]["work"])
    for case in ("simulate-run", "simulate-multirun"):
        assert results[case]["code"] == 0, results[case]["stderr"][-2000:]
    assert (work / "one.csv").is_file() and (work / "one_run" / ".hydra" / "overrides.yaml").is_file()
    assert (work / "m0.csv").is_file() and (work / "m1.csv").is_file()
    assert (work / "sweep" / "0" / ".hydra").is_dir() and (work / "sweep" / "1" / ".hydra").is_dir()


def test_failed_jobs_of_a_sweep_still_raise_to_the_sweeper(results):
    line = assert_one_line_error(results["train-ga_all_failed"], "GA sweep stopped: 2 of 2 jobs failed")
    assert "RecordingError" in line and "missing required column" in line
    history = json.loads((Path(results["train-ga_all_failed"]["work"]) / "ga" / "ga_history.json").read_text())
    individuals = history["generations"][0]["individuals"]
    assert [i["status"] for i in individuals] == ["FAILED", "FAILED"]
    assert all(i["error"].startswith("RecordingError: ") for i in individuals)


def test_a_real_subprocess_agrees_with_the_zygote(tmp_path, bad_files):
    """The issue's case as a user runs it: a bad recording through train.py (was Hydra's 4 lines, exit 1)."""
    proc = subprocess.run([sys.executable, "scripts/train.py", f"data.path={bad_files['no_column']}",
                           f"hydra.run.dir={tmp_path}"], cwd=ROOT, capture_output=True, text=True, timeout=120)
    line = assert_one_line_error({"code": proc.returncode, "stdout": proc.stdout, "stderr": proc.stderr},
                                 "missing required column(s) gyro_x_dps")
    assert "Error in call to target" not in line


@pytest.mark.slow
def test_every_command_on_every_bad_input(tmp_path, bundle, bad_files):
    cases = bad_input_cases(bundle, bad_files, tmp_path)
    by_id = run_cases(cases, tmp_path)
    failures = []
    for case in cases:
        try:
            assert_one_line_error(by_id[case["id"]], *case["expect"])
        except AssertionError as err:
            failures.append(f"{case['id']}: {err}")
    assert not failures, "\n\n".join(failures)


if __name__ == "__main__":
    _zygote(*sys.argv[1:3])


def test_ctrl_c_is_one_line_and_exit_130(tmp_path):
    """Ctrl-C printed the traceback of wherever it landed (40 lines in a GA sweep)."""
    import signal
    import time

    proc = subprocess.Popen([sys.executable, "scripts/simulate.py", f"output={tmp_path / 'long.csv'}",
                             "duration_s=2000000", f"hydra.run.dir={tmp_path / 'run'}"], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 120
    while not (tmp_path / "run" / ".hydra" / "config.yaml").exists():  # the task is running (23 days to simulate)
        assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
        time.sleep(0.05)
    time.sleep(0.5)
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 130 and err.strip() == "interrupted (Ctrl-C)", err


def test_a_mapping_that_takes_entries_with_a_plus_says_both_forms():
    """table.py 'bundles={a: D}' named only +bundles.<name>=, not the '+bundles={...}' the docs use."""
    sys.path.insert(0, str(ROOT / "scripts"))
    from _settings import unknown_setting

    said = unknown_setting("bundles", ["bundles", "input"])
    assert "'+bundles={<name>: <value>, ...}'" in said and "+bundles.<name>=<value>" in said
