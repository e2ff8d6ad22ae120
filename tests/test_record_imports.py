"""record.py starts without torch (seconds of imports a sensor's first frames would wait for): checked in a
fresh interpreter, whose ``sys.modules`` says what the imports pulled in."""
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def imports_torch(code: str) -> bool:
    result = subprocess.run([sys.executable, "-c", code + "\nimport sys\nprint('torch' in sys.modules)"], cwd=ROOT,
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr[-2000:]
    return result.stdout.strip().splitlines()[-1] == "True"


def test_the_recorder_and_its_script_import_no_torch():
    assert not imports_torch("import gyronet.deploy.stream.record, gyronet.deploy.stream.signals")
    assert not imports_torch("import runpy, sys\nsys.argv = ['scripts/record.py', '--help']\ntry:\n"
                             "    runpy.run_path('scripts/record.py', run_name='__main__')\nexcept SystemExit:\n"
                             "    pass")
