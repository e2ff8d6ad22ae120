"""record.py's output and options: a recording is hours of a chamber, so what would lose it, or a bad option that
would end in a traceback after the sensor was set up, is refused in one line before the port opens."""
from __future__ import annotations

from pathlib import Path

import pytest

from gyronet.deploy.stream.lpbus_setup import LpBusSetup
from gyronet.deploy.stream.pty_sensor import play_in_thread
from gyronet.deploy.stream.record import _RecordingFile, record_stream
from gyronet.deploy.stream.summary import OutputError
from test_commands import assert_one_line_error, run_cases

MUTE = LpBusSetup(configure=True, timeout_s=0.1)  # loop:// answers nothing: reaching the sensor is a SensorError
COLUMNS = ["time_s", "temp_c", "gyro_x_dps", "gyro_y_dps", "gyro_z_dps"]


@pytest.fixture
def chamber_run(tmp_path) -> Path:
    path = tmp_path / "run1.csv"
    path.write_text("time_s,temp_c,gyro_x_dps,gyro_y_dps,gyro_z_dps\n0.0,60.0,0.1,0.2,0.3\n")
    return path


def test_an_existing_recording_is_refused_before_the_sensor_is_touched(chamber_run):
    before = chamber_run.read_text()
    with pytest.raises(OutputError, match="exists; a recording is not replaced unless overwrite=true"):
        record_stream("loop://", chamber_run, lpbus=MUTE)
    assert chamber_run.read_text() == before


def test_a_summary_that_is_the_output_is_refused(tmp_path):
    path = tmp_path / "run.csv"
    with pytest.raises(OutputError, match="summary= names the recording itself"):
        record_stream("loop://", path, lpbus=MUTE, summary_path=tmp_path / "." / "run.csv")
    assert not path.exists()


def test_a_file_that_appeared_during_the_set_up_is_not_replaced_unless_asked(chamber_run):
    before = chamber_run.read_text()
    with pytest.raises(OutputError, match="overwrite=true"):
        _RecordingFile(chamber_run, COLUMNS, {})
    assert chamber_run.read_text() == before
    out = _RecordingFile(chamber_run, COLUMNS, {}, overwrite=True)
    out.close()
    assert chamber_run.read_text() == ",".join(COLUMNS) + "\n"


@pytest.mark.parametrize("summary_writable", [True, False])
def test_a_full_disk_leaves_whole_rows_and_the_summary_says_so(lpbus_recording, tmp_path, monkeypatch,
                                                               summary_writable):
    import json
    import os

    import numpy as np

    from gyronet.deploy.stream import record
    from gyronet.recordings.data import load_recording
    from test_lpbus_live import FAST, power_on, started
    from test_stream_e2e import FullDisk

    recording = load_recording(lpbus_recording)
    recording.columns["time_s"] = np.arange(len(recording)) / 100.0
    link, path = tmp_path / "sensor", tmp_path / "run.csv"
    (tmp_path / "not-a-folder").write_text("")
    summary_path = tmp_path / ("summary.json" if summary_writable else "not-a-folder/summary.json")
    started(play_in_thread(None, link, device=power_on("LPMS-CU2"), columns=recording.columns), link)
    monkeypatch.setattr(record.os, "write", FullDisk(path, 3000))
    with pytest.raises(OutputError) as caught:
        record_stream(str(link), path, lpbus=LpBusSetup(configure=True, rate_hz=100), reconnect=FAST,
                      summary_path=summary_path)
    monkeypatch.undo()
    message = str(caught.value)
    assert "\n" not in message and "No space left on device" in message and str(path) in message
    text = path.read_text()
    assert text.endswith("\n") and os.path.getsize(path) <= 3000
    saved = load_recording(path)
    assert 5 < len(saved) < len(recording)
    if summary_writable:
        summary = json.loads(summary_path.read_text())
        assert summary["stopped"] == "output_failed" and summary["n_samples"] == len(saved)
        assert "No space left on device" in summary["error"] and f"summary in {summary_path}" in message
    else:
        assert "cannot write the summary" in message and not summary_path.exists()


# ---------------------------------------------------------------- the scripts, in one zygote (test_commands.py)

def cases(work: Path, chamber_run: Path) -> dict[str, tuple[str, list[str], tuple[str, ...]]]:
    """id: (script, arguments, what the one line must say)."""
    record = ["port=loop://", "lpbus.timeout_s=0.1"]
    stream = [f"model={work}/no_bundle", "port=loop://", f"output={work}/l.csv"]
    bad = {  # option: (value, what the line says): each ended in a traceback, an empty file or a 1-sample run
        "baud": ("92160O", "baud must be an integer, got '92160O'"), "baud ": ("-5", "baud must be a positive integer"),
        "duration_s": ("abc", "duration_s must be a number or null"),
        "duration_s ": ("-1", "duration_s must be a positive number of seconds or null, got -1"),
        "max_samples": ("abc", "max_samples must be an integer or null"),
        "max_samples ": ("-3", "max_samples must be a positive integer or null, got -3"),
        "read_timeout_s": ("abc", "read_timeout_s must be a number"),
        "read_timeout_s ": ("0", "read_timeout_s must be a positive number of seconds"),
    }
    limits = {f"{script}-{key.strip()}-{value}": (script, [*base, f"output={work}/{script}.csv" if script == "record"
                                                          else f"output={work}/l.csv", f"{key.strip()}={value}"],
                                                  (expect,))
              for script, base in (("record", record), ("stream", stream)) for key, (value, expect) in bad.items()}
    return {**limits,
        "record-existing_output": ("record", [*record, f"output={chamber_run}"], ("overwrite=true", str(chamber_run))),
        "record-summary_is_output": ("record", [*record, f"output={work}/r.csv", f"summary={work}/r.csv"],
                                     ("summary= names the recording itself",)),
        # a misspelt protocol ended in make_parser's traceback after the bundle loaded
        "stream-protocol": ("stream", [*stream, "protocol=lpbuss"], ("protocol must be lpbus or csv, got 'lpbuss'",)),
    }


@pytest.fixture(scope="module")
def results(tmp_path_factory) -> dict[str, dict]:
    work = tmp_path_factory.mktemp("options")
    chamber_run = work / "run1.csv"
    chamber_run.write_text("time_s,temp_c,gyro_x_dps,gyro_y_dps,gyro_z_dps\n0.0,60.0,0.1,0.2,0.3\n")
    listed = cases(work, chamber_run)
    by_id = run_cases([{"id": key, "script": f"scripts/{script}.py", "args": [*args, f"hydra.run.dir={work / key}"]}
                       for key, (script, args, _) in listed.items()], work)
    for key, (_, _, expect) in listed.items():
        by_id[key].update(expect=expect, work=str(work))
    by_id["chamber_run"] = {"text": chamber_run.read_text()}
    return by_id


@pytest.mark.parametrize("case", list(cases(Path("/w"), Path("/w/run1.csv"))))
def test_bad_options_are_one_line_before_the_port_opens(results, case):
    assert_one_line_error(results[case], *results[case]["expect"])
    assert results["chamber_run"]["text"].endswith("0.0,60.0,0.1,0.2,0.3\n")  # never replaced
    assert not (Path(results[case]["work"]) / "record.csv").exists()  # refused before the output was made
