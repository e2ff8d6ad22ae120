"""Smoke test of scripts/bench.py: the quick sizes run, print a table and write the JSON rows."""
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_bench_quick_smoke(tmp_path):
    pytest.importorskip("allantools")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    out = tmp_path / "bench.json"
    proc = subprocess.run([sys.executable, str(ROOT / "scripts" / "bench.py"), "--quick", "--only", "load_460k",
                           "allan_1e7", "--json", str(out), "--work-dir", str(tmp_path)],
                          cwd=ROOT, env=env, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert "ratio" in proc.stdout.splitlines()[0]
    rows = {r["name"]: r for r in json.loads(out.read_text())["rows"]}
    assert set(rows) == {"load_460k", "allan_1e7"}
    for r in rows.values():
        assert r["ours_s"] > 0 and r["reference_s"] > 0 and r["ratio"] == pytest.approx(
            r["ours_s"] / r["reference_s"], rel=0.01)
    assert "max rel diff" in rows["allan_1e7"]["notes"]


def test_bench_rejects_unknown_row():
    proc = subprocess.run([sys.executable, str(ROOT / "scripts" / "bench.py"), "--only", "nope"],
                          cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and "invalid choice" in proc.stderr
