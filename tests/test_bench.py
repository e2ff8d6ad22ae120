"""Smoke test of scripts/bench.py: the quick sizes run, print a table and write the JSON rows."""
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def bench(*args: str, timeout: float = 60) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    return subprocess.run([sys.executable, str(ROOT / "scripts" / "bench.py"), *args], cwd=ROOT, env=env,
                          capture_output=True, text=True, timeout=timeout)


@pytest.fixture
def harness(monkeypatch):
    monkeypatch.syspath_prepend(str(ROOT / "scripts"))
    from bench_rows import harness

    return harness


def test_bench_quick_smoke(tmp_path):
    pytest.importorskip("allantools")
    out = tmp_path / "bench.json"
    proc = bench("--quick", "--only", "load_460k", "allan_1e7", "--json", str(out), "--work-dir", str(tmp_path),
                 timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert "ratio" in proc.stdout.splitlines()[0]
    rows = {r["name"]: r for r in json.loads(out.read_text())["rows"]}
    assert set(rows) == {"load_460k", "allan_1e7"}
    for r in rows.values():
        assert r["ours_s"] > 0 and r["reference_s"] > 0 and r["ratio"] == pytest.approx(
            r["ours_s"] / r["reference_s"], rel=0.01)
        assert r["row_wall_s"] >= 0 and set(r["load_1m"]) == {"start", "mean", "max", "end"}
    assert "max rel diff" in rows["allan_1e7"]["notes"]


def test_bench_rejects_unknown_row():
    proc = bench("--only", "nope")
    assert proc.returncode == 2 and "invalid choice" in proc.stderr


def test_long_rows_are_opt_in():
    proc = bench("--list")
    assert proc.returncode == 0, proc.stderr
    listed = dict(line.split(": ", 1) for line in proc.stdout.splitlines())
    assert "ga_sweep (long)" in listed
    for name in ("train_default_paper", "compensate_batch", "stream_pty"):
        assert name in listed


def test_row_keeps_extra_figures(harness):
    result = harness.row("x", 2.0, 4.0, "n", samples_per_s=1234567.891, breakdown_s={"model_s": 0.123456})
    assert result["ratio"] == 0.5 and result["samples_per_s"] == 1235000.0
    assert result["breakdown_s"] == {"model_s": 0.1235}
    assert harness.row("y", 1.0, None)["ratio"] is None


def test_log_times_reads_job_and_hydra_lines(harness, tmp_path):
    log = tmp_path / "train.log"
    log.write_text("[2026-01-02 03:04:05,250][gyronet.training.dataset][INFO] - training data F.csv: 10 samples\n"
                   "[2026-01-02 03:04:07,000][HYDRA] Launching jobs, sweep output dir : S\n"
                   "[2026-01-02 03:04:09,500][HYDRA] Launching jobs, sweep output dir : S\n")
    marks = harness.log_times(log, {"data": r"^training data ", "launch": r"^Launching jobs", "none": "^nope"})
    assert set(marks) == {"data", "launch"} and marks["launch"] - marks["data"] == pytest.approx(1.75)
    launches = harness.log_matches(log, r"^Launching jobs")
    assert launches[1] - launches[0] == pytest.approx(2.5)


def test_percentiles_ms(harness):
    figures = harness.percentiles_ms([0.001] * 99 + [0.1])
    assert figures["p50"] == pytest.approx(1.0) and figures["max"] == pytest.approx(100.0)
