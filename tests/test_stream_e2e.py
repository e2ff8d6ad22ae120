"""End to end: emulate_sensor.py -> pty -> stream.py, as subprocesses, with faults mixed in.

The subprocess tests start Python with torch twice each (about 20-30 s) and are marked slow;
``test_run_stream_in_process_equals_offline`` runs the same loop in-process for every test run.
The live output must equal the offline path (``Compensator.process`` on the good samples as they
read after their trip through the framing) and the fault counts must equal the emulator's log.
"""
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from gyronet.bundle.compensator import Compensator
from gyronet.recordings.data import GYRO_COLUMNS, block_means, load_recording, load_truth, write_recording
from gyronet.bundle.offline import SIGMA_COLUMNS
from gyronet.deploy.stream import LpBusLayout
from gyronet.model.recalibration import check

ROOT = Path(__file__).resolve().parents[1]
N_SAMPLES = 400
OUT_OF_RANGE_TEMP_C = 150.0


@pytest.fixture
def short_recording(paper_csv, tmp_path) -> Path:
    """The first 400 samples (200 s at 2 Hz) of the paper profile."""
    recording = load_recording(paper_csv).slice(slice(0, N_SAMPLES))
    return write_recording(tmp_path / "short.csv", recording.columns, recording.meta)


@pytest.fixture
def processes():
    """Subprocesses started by a test; whatever is still running at the end is killed."""
    started: list[subprocess.Popen] = []
    yield started
    for process in started:
        if process.poll() is None:
            process.kill()
            process.wait(10)


def start(processes, script: str, *overrides: str, tmp_path: Path, name: str, preexec_fn=None) -> subprocess.Popen:
    with open(tmp_path / f"{name}.log", "w") as log:  # the child keeps its own copy of the file
        process = subprocess.Popen([sys.executable, f"scripts/{script}", *overrides,
                                    f"hydra.run.dir={tmp_path / name}"], cwd=ROOT, stdout=log,
                                   stderr=subprocess.STDOUT, preexec_fn=preexec_fn)
    processes.append(process)
    return process


def expected_output(bundle, recording_path: Path, emulator_log: dict, protocol: str, n: int | None = None):
    """Offline compensation of the good samples the emulator sent, as the stream decodes them."""
    recording = load_recording(recording_path)
    layout = LpBusLayout()
    rows = []
    for index in emulator_log["good_indices"][:n]:
        row = {c: float(recording.columns[c][index]) for c in recording.columns}
        if index in emulator_log["out_of_range_indices"]:
            row["temp_c"] = OUT_OF_RANGE_TEMP_C
        rows.append(layout.quantize(row) if protocol == "lpbus" else row)
    compensator = Compensator.load(bundle)
    compensator.reset()
    columns = {c: np.array([row[c] for row in rows]) for c in compensator.input_columns}
    out = compensator.process(columns)
    return columns["time_s"], columns["temp_c"], out


def read_output(path: Path) -> pd.DataFrame:
    return pd.read_csv(path, comment="#")


def assert_matches_offline(output: pd.DataFrame, time_s, temp_c, out) -> None:
    assert len(output) == len(time_s) > 0
    np.testing.assert_array_equal(output["time_s"].to_numpy(), time_s)
    np.testing.assert_array_equal(output["temp_c"].to_numpy(), temp_c)
    live = output[list(GYRO_COLUMNS)].to_numpy()
    np.testing.assert_allclose(live, out.rate_dps, rtol=0, atol=1e-9)
    np.testing.assert_array_equal(output["out_of_range"].to_numpy(), out.out_of_range.astype(int))


def test_run_stream_in_process_equals_offline(bundle, short_recording, tmp_path):
    """The live loop without the subprocesses: fast enough for every test run."""
    from gyronet.deploy.stream import FaultPlan, plan_stream
    from gyronet.deploy.stream.live import run_stream
    from gyronet.deploy.stream.pty_sensor import play_in_thread

    recording = load_recording(short_recording)
    faults = FaultPlan(garbage_rate=0.05, corrupt_rate=0.03, truncate_rate=0.03, nan_rate=0.02,
                       out_of_range_every=37, out_of_range_temp_c=OUT_OF_RANGE_TEMP_C, drop_port_at_s=(80.0,), seed=9)
    plan = plan_stream(recording.columns, "lpbus", faults)
    link = tmp_path / "sensor"
    thread = play_in_thread(plan, link)
    summary = run_stream(bundle, str(link), tmp_path / "live.csv", allan_every_s=60, tb_dir=tmp_path / "tb",
                         summary_path=tmp_path / "summary.json",
                         reconnect={"backoff_s": 0.05, "max_backoff_s": 0.2, "give_up_s": 0.5,
                                                    "wait_at_start": True})
    thread.join(10)
    expected_faults = dict(plan.log["expected_faults"])
    expected_faults["port_lost"] += 1
    assert summary["faults"] == expected_faults
    assert summary["n_out_of_range"] == len(plan.log["out_of_range_indices"]) > 0
    assert json.loads((tmp_path / "summary.json").read_text())["n_samples"] == len(plan.log["good_indices"])
    assert set(summary["allan"]) == {"x", "y", "z"}
    output = read_output(tmp_path / "live.csv")
    assert_matches_offline(output, *expected_output(bundle, short_recording, plan.log, "lpbus"))
    # the live recalibration check: allan.py's on the output file (the stream's lost frames split its blocks there)
    offline = check(output["time_s"].to_numpy(), output[list(GYRO_COLUMNS)].to_numpy(),
                    output[list(SIGMA_COLUMNS)].to_numpy(), output["out_of_range"].to_numpy())
    assert set(summary["recalibration"]) == set(offline) == {"x", "y", "z"}
    for axis, figures in offline.items():
        assert summary["recalibration"][axis]["n_blocks"] == figures["n_blocks"] == 3
        assert summary["recalibration"][axis]["worst_hour_rms_ratio"] == pytest.approx(figures["worst_hour_rms_ratio"], rel=1e-9)
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    tags = EventAccumulator(str(tmp_path / "tb"), size_guidance={"images": 0}).Reload().Tags()["scalars"]
    assert {f"recalibration/worst_hour_{axis}" for axis in "xyz"} <= set(tags)


def test_run_stream_refuses_fields_the_bundle_cannot_use(bundle, tmp_path):
    from gyronet.errors import BundleError
    from gyronet.deploy.stream.live import run_stream

    with pytest.raises(BundleError, match="temp_c"):
        run_stream(bundle, "loop://", tmp_path / "live.csv", layout=LpBusLayout(fields=("gyro", "acc")))


@pytest.mark.slow
@pytest.mark.parametrize("protocol", ["lpbus", "csv"])
def test_live_stream_equals_offline_and_counts_faults(bundle, short_recording, tmp_path, processes, protocol):
    link, emulator_log, summary = tmp_path / "sensor", tmp_path / "emulator.json", tmp_path / "summary.json"
    emulator = start(processes, "emulate_sensor.py", f"input={short_recording}", f"protocol={protocol}",
                     "speed=0", f"link={link}", f"log_file={emulator_log}", "faults.garbage_rate=0.05",
                     "faults.corrupt_rate=0.03", "faults.truncate_rate=0.03", "faults.nan_rate=0.02",
                     "faults.out_of_range_every=37", f"faults.out_of_range_temp_c={OUT_OF_RANGE_TEMP_C}",
                     "faults.drop_port_at_s=[60,150]", "faults.gap_s_at=[[100,10]]", "faults.seed=4",
                     "port_down_s=0.3", tmp_path=tmp_path, name="emulator")
    stream = start(processes, "stream.py", f"model={bundle}", f"port={link}", f"protocol={protocol}",
                   f"output={tmp_path / 'live.csv'}", f"summary={summary}", "reconnect.give_up_s=1",
                   "reconnect.wait_at_start=true",
                   "reconnect.backoff_s=0.05", "allan_every_s=60", f"tb_dir={tmp_path / 'tb'}",
                   tmp_path=tmp_path, name="stream")
    assert stream.wait(90) == 0, (tmp_path / "stream.log").read_text()[-3000:]
    assert emulator.wait(30) == 0, (tmp_path / "emulator.log").read_text()[-3000:]

    log = json.loads(emulator_log.read_text())
    result = json.loads(summary.read_text())
    expected_faults = dict(log["expected_faults"])
    expected_faults["port_lost"] += 1  # the emulator closing its port at the end
    assert log["injected"]["port_drop"] == 2 and log["injected"]["gap"] == 20
    assert result["faults"] == expected_faults
    assert result["stopped"] == "port_gone"
    assert result["n_samples"] == len(log["good_indices"])
    assert result["n_out_of_range"] == len(log["out_of_range_indices"]) > 0
    assert_matches_offline(read_output(tmp_path / "live.csv"), *expected_output(bundle, short_recording, log, protocol))
    assert any((tmp_path / "tb").iterdir())


@pytest.mark.slow
def test_sigint_stops_cleanly_with_summary(bundle, short_recording, tmp_path, processes):
    link, emulator_log, summary = tmp_path / "sensor", tmp_path / "emulator.json", tmp_path / "summary.json"
    output = tmp_path / "live.csv"
    emulator = start(processes, "emulate_sensor.py", f"input={short_recording}", "speed=10", f"link={link}",
                     f"log_file={emulator_log}", "faults.garbage_rate=0.05", tmp_path=tmp_path, name="emulator")
    stream = start(processes, "stream.py", f"model={bundle}", f"port={link}", f"output={output}",
                   f"summary={summary}", "allan_every_s=0", "reconnect.wait_at_start=true", tmp_path=tmp_path,
                   name="stream")
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and (not output.exists() or len(output.read_text().splitlines()) < 32):
        assert stream.poll() is None, (tmp_path / "stream.log").read_text()[-3000:]
        time.sleep(0.1)
    stream.send_signal(signal.SIGINT)
    assert stream.wait(30) == 0, (tmp_path / "stream.log").read_text()[-3000:]
    emulator.send_signal(signal.SIGTERM)  # as Ctrl-C: it stops cleanly, and its link goes with it
    assert emulator.wait(30) == 0 and not link.is_symlink(), (tmp_path / "emulator.log").read_text()[-3000:]

    result = json.loads(summary.read_text())
    assert result["stopped"] == "interrupted"
    live = read_output(output)
    assert len(live) == result["n_samples"] >= 30
    assert output.read_text().endswith("\n")  # no half-written line
    log = json.loads(emulator_log.read_text())
    assert_matches_offline(live, *expected_output(bundle, short_recording, log, "lpbus", n=len(live)))
    assert "stopped (interrupted)" in (tmp_path / "stream.log").read_text()


@pytest.mark.parametrize("how", ["max_samples", "interrupted"])
def test_run_stream_stops_on_max_samples_and_ctrl_c(bundle, tmp_path, monkeypatch, how):
    """Stop conditions, with the port replaced by a scripted stream of samples and faults."""
    import gyronet.deploy.stream.live as live
    from gyronet.deploy.stream import Fault, Sample

    def scripted(*args, **kwargs):
        yield [Fault("garbage", b"\x00")]
        # one read brings all 20: max_samples cuts the chunk
        yield [Sample(0.5 * i, {"temp_c": 25.0, "gyro_x_dps": 0.1, "gyro_y_dps": 0.2, "gyro_z_dps": 0.3})
               for i in range(20)]
        raise KeyboardInterrupt

    monkeypatch.setattr(live, "read_chunks", scripted)
    summary = live.run_stream(bundle, "/dev/null", tmp_path / "live.csv", allan_every_s=0,
                              max_samples=5 if how == "max_samples" else None, reconnect={"wait_at_start": True})
    assert summary["stopped"] == how
    assert summary["faults"] == {"garbage": 1}
    rows = read_output(tmp_path / "live.csv")
    assert len(rows) == summary["n_samples"] == (5 if how == "max_samples" else 20)
    assert list(rows.columns) == ["time_s", *GYRO_COLUMNS, "temp_c", "out_of_range", "bad_input", *SIGMA_COLUMNS]


# --- issue 10: restarted clocks, re-sent headers, signals, missing ports, a full disk ---------

def feeding(chunks):
    """A ``read_chunks`` stand-in that feeds scripted bytes through the real parser, one read a chunk
    (None: the port lost and reopened, as the reader tells the parser's check)."""
    from gyronet.deploy.stream import Fault

    def scripted(port, parser, *, should_stop, **kwargs):
        for chunk in chunks:
            if should_stop():
                return
            if chunk is None:
                yield [Fault("port_lost"), *parser.flush()]
                parser.check.reopened()
                continue
            items = parser.feed(chunk)
            if items:
                yield items
        yield parser.flush()

    return scripted


def csv_stream(rows: dict[str, np.ndarray], names: list[str]) -> list[bytes]:
    from gyronet.deploy.stream import encode_csv_line

    return [encode_csv_line({c: float(rows[c][i]) for c in names}, names) for i in range(len(rows["time_s"]))]


def offline(bundle, columns: dict[str, np.ndarray], startup: dict | None = None):
    """``compensate_recording`` on these samples, from a fresh state (with ``startup``'s offset if given)."""
    from gyronet.recordings.data import Recording
    from gyronet.bundle.offline import compensate_recording

    compensator = Compensator.load(bundle)
    compensator.use_startup(**(startup or {}))
    return compensate_recording(compensator, Recording(columns, {}, "good samples"))


def test_replugged_sensor_with_its_clock_restarted_loses_no_sample(bundle, paper_csv, tmp_path, monkeypatch):
    import gyronet.deploy.stream.live as live
    from gyronet.deploy.stream import encode_csv_header

    recording = load_recording(paper_csv).slice(slice(0, 1200))
    names = list(recording.columns)
    first = {c: v[:800] for c, v in recording.columns.items()}
    second = {c: v[800:].copy() for c, v in recording.columns.items()}
    second["time_s"] = second["time_s"] - second["time_s"][0] + 0.25  # its clock starts again near 0
    monkeypatch.setattr(live, "read_chunks", feeding([encode_csv_header(names), *csv_stream(first, names), None,
                                                      *csv_stream(second, names)]))
    summary = live.run_stream(bundle, "sensor", tmp_path / "live.csv", protocol="csv", allan_every_s=0,
                              reconnect={"wait_at_start": True})
    assert summary["n_samples"] == 1200 and summary["faults"] == {"port_lost": 1} and summary["clock_restarts"] == 1
    output = read_output(tmp_path / "live.csv")
    # each segment as offline from a fresh state: the compensator restarted with the sensor
    for rows, part in ((slice(0, 800), first), (slice(800, 1200), second)):
        assert_matches_offline(output.iloc[rows].reset_index(drop=True), part["time_s"], part["temp_c"],
                               offline(bundle, part))


def test_one_corrupted_stamp_costs_its_sample_not_a_new_start_up_window(bundle, paper_csv, tmp_path, monkeypatch):
    """A stamp corrupted 90 s back was a clock restart: the start-up window began again and closed on the
    next good sample, one sample's noise subtracted from every later row for good (a review's find)."""
    import gyronet.deploy.stream.live as live
    from gyronet.deploy.stream import encode_csv_header, encode_csv_line

    recording = load_recording(paper_csv).slice(slice(0, 1500))
    names = list(recording.columns)
    lines = csv_stream(recording.columns, names)
    corrupted = {c: float(recording.columns[c][700]) for c in names}
    corrupted["time_s"] -= 90.0
    lines[700] = encode_csv_line(corrupted, names)
    monkeypatch.setattr(live, "read_chunks", feeding([encode_csv_header(names), *lines]))
    startup = {"still_s": 60.0, "motion_dps": 5.0}
    summary = live.run_stream(bundle, "sensor", tmp_path / "live.csv", protocol="csv", allan_every_s=0,
                              reconnect={"wait_at_start": True}, startup=startup)
    assert summary["faults"] == {"time_jump": 1} and summary["clock_restarts"] == 0 and summary["n_samples"] == 1499
    output = read_output(tmp_path / "live.csv")
    kept = np.arange(1500) != 700
    part = {c: v[kept] for c, v in recording.columns.items()}
    assert_matches_offline(output, part["time_s"], part["temp_c"], offline(bundle, part, startup=startup))


def test_resent_header_without_a_needed_column_does_not_stop_the_stream(bundle, paper_csv, tmp_path, monkeypatch):
    import gyronet.deploy.stream.live as live
    from gyronet.deploy.stream import encode_csv_header

    recording = load_recording(paper_csv).slice(slice(0, 200))
    names = list(recording.columns)
    lines = csv_stream(recording.columns, names)
    cut = [n for n in names if n != "gyro_z_dps"]
    chunks = [encode_csv_header(names), *lines[:100], encode_csv_header(cut), b"#\n", *lines[100:]]
    monkeypatch.setattr(live, "read_chunks", feeding(chunks))
    summary = live.run_stream(bundle, "sensor", tmp_path / "live.csv", protocol="csv", allan_every_s=0,
                              reconnect={"wait_at_start": True})
    assert summary["n_samples"] == 200 and summary["faults"] == {"bad_header": 1}
    assert_matches_offline(read_output(tmp_path / "live.csv"), recording.time_s, recording.temp_c,
                           offline(bundle, recording.columns))


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM])
def test_signals_stop_the_run_even_when_the_parent_ignored_them(bundle, tmp_path, monkeypatch, signum):
    import os

    import gyronet.deploy.stream.live as live
    from gyronet.deploy.stream import Sample

    def scripted(port, parser, *, should_stop, **kwargs):
        for i in range(2000):
            if should_stop():
                return
            if i == 20:
                os.kill(os.getpid(), signum)  # handled in this (main) thread at the next bytecode
            yield [Sample(0.5 * i, {"temp_c": 25.0, "gyro_x_dps": 0.1, "gyro_y_dps": 0.2, "gyro_z_dps": 0.3})]

    monkeypatch.setattr(live, "read_chunks", scripted)
    previous = signal.signal(signum, signal.SIG_IGN)  # what a shell's background job inherits
    try:
        with live.stop_on_signals() as stop:
            summary = live.run_stream(bundle, "sensor", tmp_path / "live.csv", allan_every_s=0,
                                      summary_path=tmp_path / "summary.json", reconnect={"wait_at_start": True},
                                      stop=stop)
        assert signal.getsignal(signum) == signal.SIG_IGN  # put back as it was
    finally:
        signal.signal(signum, previous)
    assert summary["stopped"] == "interrupted" and 20 <= summary["n_samples"] < 30
    assert json.loads((tmp_path / "summary.json").read_text())["stopped"] == "interrupted"
    assert len(read_output(tmp_path / "live.csv")) == summary["n_samples"]


def test_a_port_missing_at_start_is_an_error_unless_waited_for(bundle, tmp_path):
    from gyronet.deploy.stream import PortError
    from gyronet.deploy.stream.live import run_stream

    missing = tmp_path / "no-such-sensor"
    started = time.monotonic()
    import gc

    with pytest.raises(PortError, match="no-such-sensor.*reconnect.wait_at_start=true"):
        run_stream(bundle, str(missing), tmp_path / "live.csv")
    assert time.monotonic() - started < 30 and not (tmp_path / "live.csv").exists()
    assert gc.get_freeze_count() == 0  # the refused set-up left the collector as it was
    summary = run_stream(bundle, str(missing), tmp_path / "live.csv", allan_every_s=0,
                         reconnect={"wait_at_start": True, "backoff_s": 0.05, "give_up_s": 0.2})
    assert summary["stopped"] == "port_gone" and summary["n_samples"] == 0


class FullDisk:
    """``os.write`` on one file with this many bytes of room left: a short write, then ENOSPC."""

    def __init__(self, path: Path, room_bytes: int):
        import os

        self.path, self.room, self.real_write = str(path), room_bytes, os.write

    def __call__(self, fd: int, data) -> int:
        import errno
        import os

        if os.readlink(f"/proc/self/fd/{fd}") != self.path:
            return self.real_write(fd, data)
        if self.room <= 0:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        n = self.real_write(fd, bytes(data[:self.room]))
        self.room -= n
        return n


@pytest.mark.parametrize("summary_writable", [True, False])
def test_a_full_disk_stops_with_one_line_whole_lines_and_the_summary(bundle, tmp_path, monkeypatch,
                                                                    summary_writable):
    import os

    import gyronet.deploy.stream.live as live
    import gyronet.deploy.stream.output as output_module
    from gyronet.deploy.stream import Sample
    from gyronet.deploy.stream.output import OutputError

    def scripted(port, parser, *, should_stop, **kwargs):
        samples = [Sample(0.5 * i, {"temp_c": 25.0 + 0.01 * i, "gyro_x_dps": 0.1, "gyro_y_dps": 0.2, "gyro_z_dps": 0.3})
                   for i in range(500)]
        for start in range(0, 500, 7):  # reads of 7 samples: the disk fills inside a chunk's write
            yield samples[start:start + 7]

    path = tmp_path / "live.csv"
    monkeypatch.setattr(live, "read_chunks", scripted)
    monkeypatch.setattr(output_module.os, "write", FullDisk(path, 5000))
    (tmp_path / "not-a-folder").write_text("")
    summary_path = tmp_path / ("summary.json" if summary_writable else "not-a-folder/summary.json")
    with pytest.raises(OutputError) as caught:
        live.run_stream(bundle, "sensor", path, allan_every_s=0, summary_path=summary_path,
                        reconnect={"wait_at_start": True})
    message = str(caught.value)
    assert "\n" not in message and "No space left on device" in message and str(path) in message
    monkeypatch.undo()
    text = path.read_text()
    assert text.endswith("\n") and os.path.getsize(path) <= 5000
    rows = read_output(path)
    assert rows.notna().all().all() and 10 < len(rows) < 500
    if summary_writable:
        summary = json.loads(summary_path.read_text())
        assert summary["stopped"] == "output_failed" and summary["n_samples"] == len(rows)
        assert f"summary in {summary_path}" in message
    else:
        assert "cannot write the summary" in message and not summary_path.exists()


# --- issue 10 goals: corrupt lines of every kind, and the README's lossy emulator example -----

def corrupt_lines(lines: list[bytes], names: list[str], n_corrupt: int, seed: int) -> tuple[list[bytes], dict]:
    """``lines`` with ``n_corrupt`` damaged lines of every kind inserted; and the faults they must give.

    Each inserted line is extra: every good line stays, unchanged, on a line of its own.
    """
    header = ",".join(names).encode()
    needed_but_short = b"time_s,temp_c,gyro_x_dps,gyro_y_dps,gyro_z_dps"
    kinds = {  # kind: (the line, given the good line after it and the one before; the fault it gives)
        "garbage": (lambda nxt, prev: bytes(range(0x80, 0x90)), "garbage"),
        "cut_header": (lambda nxt, prev: b"time_s,temp_c", "bad_header"),
        "header_without_gyro_z": (lambda nxt, prev: header.replace(b",gyro_z_dps", b""), "bad_header"),
        "stray_header_with_needed_columns": (lambda nxt, prev: needed_but_short, "bad_header"),
        "truncated_copy": (lambda nxt, prev: b",".join(nxt.split(b",")[:4]), "truncated"),
        "underscore_number": (lambda nxt, prev: b"1_000," + b",".join(nxt.split(b",")[1:]), "non_numeric"),
        "hex_number": (lambda nxt, prev: b",".join(nxt.split(b",")[:3] + [b"0x10"] + nxt.split(b",")[4:]),
                       "non_numeric"),
        "extra_cell": (lambda nxt, prev: nxt + b",9.5", "bad_field_count"),
        "nan": (lambda nxt, prev: b",".join(nxt.split(b",")[:2] + [b"nan"] + nxt.split(b",")[3:]), "nan"),
        "infinity": (lambda nxt, prev: b",".join(nxt.split(b",")[:2] + [b"-Infinity"] + nxt.split(b",")[3:]),
                     "nan"),
        "stale_copy": (lambda nxt, prev: prev, "time_not_increasing"),
        "too_long": (lambda nxt, prev: b"7" * 5000, "garbage"),
    }
    rng = np.random.default_rng(seed)
    where = np.sort(rng.choice(np.arange(1, len(lines)), n_corrupt, replace=False))
    order = [list(kinds)[i % len(kinds)] for i in range(n_corrupt)]
    out, expected, start = [], {}, 0
    for position, kind in zip(where, order):
        out += lines[start:position]
        make, reason = kinds[kind]
        out.append(make(lines[position].rstrip(b"\n"), lines[position - 1].rstrip(b"\n")) + b"\n")
        expected[reason] = expected.get(reason, 0) + 1
        start = position
    out += lines[start:]
    # a re-sent header and a comment are not faults
    out.insert(len(out) // 2, header + b"\n")
    out.insert(len(out) // 3, b"# sensor re-sent its metadata\n")
    return out, expected


def play_lines(link: Path, preamble: bytes, lines: list[bytes]):
    """A thread that plays these lines into a pty at ``link`` as fast as the reader takes them."""
    from gyronet.deploy.stream.emulator import Event, StreamPlan
    from gyronet.deploy.stream.pty_sensor import play_in_thread

    plan = StreamPlan([Event(0.0, b"".join(lines[i:i + 64])) for i in range(0, len(lines), 64)], preamble)
    return play_in_thread(plan, link)


@pytest.mark.parametrize("n_samples", [3000, pytest.param(20000, marks=pytest.mark.slow)])
def test_corrupt_lines_of_every_kind_lose_no_sample_and_live_equals_offline(bundle, paper_csv, tmp_path, n_samples):
    from gyronet.deploy.stream import encode_csv_header
    from gyronet.deploy.stream.live import run_stream

    recording = load_recording(paper_csv).slice(slice(0, n_samples))
    names = list(recording.columns)
    stream, expected = corrupt_lines(csv_stream(recording.columns, names), names, 60, seed=3)
    assert sum(expected.values()) == 60
    thread = play_lines(tmp_path / "sensor", encode_csv_header(names), stream)
    summary = run_stream(bundle, str(tmp_path / "sensor"), tmp_path / "live.csv", protocol="csv",
                         allan_every_s=600, summary_path=tmp_path / "summary.json",
                         reconnect={"wait_at_start": True, "backoff_s": 0.05, "give_up_s": 0.5})
    thread.join(10)
    assert summary["n_samples"] == n_samples
    assert summary["faults"] == {**expected, "port_lost": 1}  # the emulator closing at the end
    assert_matches_offline(read_output(tmp_path / "live.csv"), recording.time_s, recording.temp_c,
                           offline(bundle, recording.columns))


@pytest.mark.slow
def test_readme_emulator_example_with_lost_frames_equals_offline_and_stays_bounded(bundle, paper_csv, tmp_path):
    """README: emulate_sensor.py protocol=lpbus faults.garbage_rate=0.01 faults.corrupt_rate=0.01
    'faults.drop_port_at_s=[600]', then stream.py. Frames lost to the bad checksums are gaps in the
    record: the live output must equal offline on the good samples, finite and bounded, and (the
    issue's goal) its residual against the simulator's truth, in 60 s blocks, within 1.1x of the
    intact record's. Today the lost frames make dT/dt diverge (the feature extractor, offline and
    live alike: 10x the intact residual here, 2e6 deg/s at 375 s on the README's record); this
    test waits for that fix."""
    from gyronet.deploy.stream import FaultPlan, plan_stream
    from gyronet.deploy.stream.live import run_stream
    from gyronet.deploy.stream.pty_sensor import play_in_thread

    recording = load_recording(paper_csv).slice(slice(0, 20000))
    plan = plan_stream(recording.columns, "lpbus", FaultPlan(garbage_rate=0.01, corrupt_rate=0.01,
                                                             drop_port_at_s=(600.0,), seed=0))
    thread = play_in_thread(plan, tmp_path / "sensor")
    summary = run_stream(bundle, str(tmp_path / "sensor"), tmp_path / "live.csv", allan_every_s=60,
                         tb_dir=tmp_path / "tb",
                         reconnect={"wait_at_start": True, "backoff_s": 0.05, "max_backoff_s": 0.2, "give_up_s": 0.5})
    thread.join(10)
    good = plan.log["good_indices"]
    assert plan.log["injected"]["corrupt"] > 100 and summary["n_samples"] == len(good)
    output = read_output(tmp_path / "live.csv")
    time_s, temp_c, out = expected_output(bundle, paper_csv, plan.log, "lpbus", n=len(good))
    assert_matches_offline(output, time_s, temp_c, out)
    live = output[list(GYRO_COLUMNS)].to_numpy()
    raw_dps = recording.gyro_dps[good]
    assert np.isfinite(live).all()
    # bounded: within a few times the drift the intact record needs of the raw rate
    intact = offline(bundle, recording.columns)
    assert np.abs(live - raw_dps).max() <= 3.0 * np.abs(intact.drift_dps).max() + 0.1
    truth = load_truth(paper_csv).slice(slice(0, 20000))
    true_dps = np.column_stack([truth.columns[f"true_rate_{axis}_dps"] for axis in "xyz"])[good]
    block_rms = {name: np.sqrt((block_means(rate - true_dps, time_s, 60.0) ** 2).mean(axis=0))
                 for name, rate in (("live", live), ("intact", intact.rate_dps[good]))}
    assert (block_rms["live"] <= 1.1 * block_rms["intact"]).all(), block_rms


# --- issue 10 through the script: a background start, a missing port, a really full disk -------

def ignore_sigint() -> None:
    """What a shell does to a job it starts with '&': SIGINT ignored, inherited across exec."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)


@pytest.mark.slow
def test_stream_py_started_with_sigint_ignored_still_stops_on_sigint(bundle, short_recording, tmp_path, processes):
    link, summary, output = tmp_path / "sensor", tmp_path / "summary.json", tmp_path / "live.csv"
    emulator = start(processes, "emulate_sensor.py", f"input={short_recording}", "speed=10", f"link={link}",
                     tmp_path=tmp_path, name="emulator")
    stream = start(processes, "stream.py", f"model={bundle}", f"port={link}", f"output={output}",
                   f"summary={summary}", "allan_every_s=0", "reconnect.wait_at_start=true", tmp_path=tmp_path,
                   name="stream", preexec_fn=ignore_sigint)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and (not output.exists() or len(output.read_text().splitlines()) < 12):
        assert stream.poll() is None, (tmp_path / "stream.log").read_text()[-3000:]
        time.sleep(0.1)
    stream.send_signal(signal.SIGINT)
    assert stream.wait(30) == 0, (tmp_path / "stream.log").read_text()[-3000:]
    emulator.send_signal(signal.SIGTERM)
    emulator.wait(30)
    result = json.loads(summary.read_text())
    assert result["stopped"] == "interrupted" and len(read_output(output)) == result["n_samples"] >= 10


@pytest.mark.slow
def test_stream_py_port_missing_at_start_is_one_line_and_exit_2(bundle, tmp_path):
    result = subprocess.run([sys.executable, "scripts/stream.py", f"model={bundle}", f"port={tmp_path / 'ttyNone'}",
                             f"output={tmp_path / 'live.csv'}", f"hydra.run.dir={tmp_path / 'run'}"], cwd=ROOT,
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: port ") and "No such file or directory" in lines[0]
    assert not (tmp_path / "live.csv").exists()


@pytest.fixture
def full_disk(tmp_path):
    """A 256 KiB tmpfs (needs root: skipped elsewhere)."""
    mount_point = tmp_path / "small"
    mount_point.mkdir()
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=256k", "tmpfs", str(mount_point)],
                             capture_output=True, text=True)
    if mounted.returncode != 0:
        pytest.skip(f"cannot mount a small tmpfs here: {mounted.stderr.strip()[:80]}")
    yield mount_point
    subprocess.run(["umount", str(mount_point)], check=False)


@pytest.mark.slow
def test_stream_py_on_a_full_disk_says_so_in_one_line(bundle, paper_csv, tmp_path, full_disk):
    from gyronet.deploy.stream import encode_csv_header

    recording = load_recording(paper_csv).slice(slice(0, 8000))
    names = list(recording.columns)
    thread = play_lines(tmp_path / "sensor", encode_csv_header(names), csv_stream(recording.columns, names))
    output, summary = full_disk / "live.csv", tmp_path / "summary.json"
    result = subprocess.run([sys.executable, "scripts/stream.py", f"model={bundle}", f"port={tmp_path / 'sensor'}",
                             "protocol=csv", f"output={output}", f"summary={summary}", "allan_every_s=0",
                             "reconnect.wait_at_start=true", f"hydra.run.dir={tmp_path / 'run'}"], cwd=ROOT,
                            capture_output=True, text=True, timeout=300)
    thread.join(10)
    assert result.returncode == 2, result.stderr[-2000:]
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "No space left on device" in lines[0] and f"summary in {summary}" in lines[0]
    assert output.read_bytes().endswith(b"\n")
    rows = read_output(output)
    assert json.loads(summary.read_text())["n_samples"] == len(rows) > 100 and rows.notna().all().all()


def test_emulated_replug_with_a_restarted_clock_through_a_pty(bundle, short_recording, tmp_path):
    from gyronet.deploy.stream import FaultPlan, plan_stream
    from gyronet.deploy.stream.live import run_stream
    from gyronet.deploy.stream.pty_sensor import play_in_thread

    recording = load_recording(short_recording)
    plan = plan_stream(recording.columns, "lpbus", FaultPlan(garbage_rate=0.03, corrupt_rate=0.03,
                                                             restart_clock_at_s=(120.0,), seed=2))
    thread = play_in_thread(plan, tmp_path / "sensor")
    summary = run_stream(bundle, str(tmp_path / "sensor"), tmp_path / "live.csv", allan_every_s=0,
                         reconnect={"wait_at_start": True, "backoff_s": 0.05, "give_up_s": 0.5})
    thread.join(10)
    ((first_index, offset_s),) = plan.log["clock_offsets_s"]
    good = plan.log["good_indices"]
    assert summary["clock_restarts"] == 1 and summary["n_samples"] == len(good)
    expected_faults = dict(plan.log["expected_faults"])
    expected_faults["port_lost"] += 1  # the emulator closing at the end
    assert summary["faults"] == expected_faults
    output = read_output(tmp_path / "live.csv")
    layout = LpBusLayout()
    cut = sum(i < first_index for i in good)
    for rows, indices, shift in ((slice(0, cut), good[:cut], 0.0), (slice(cut, None), good[cut:], offset_s)):
        sent = [layout.quantize({**{c: float(recording.columns[c][i]) for c in recording.columns},
                                 "time_s": float(recording.time_s[i]) + shift}) for i in indices]
        columns = {c: np.array([row[c] for row in sent]) for c in sent[0]}
        assert_matches_offline(output.iloc[rows].reset_index(drop=True), columns["time_s"], columns["temp_c"],
                               offline(bundle, columns))


@pytest.mark.skipif(not hasattr(os, "sched_setscheduler"), reason="SCHED_FIFO is Linux's")
def test_run_stream_at_a_realtime_priority_equals_offline_and_gives_the_priority_back(bundle, short_recording,
                                                                                       tmp_path):
    """realtime_priority runs the loop under SCHED_FIFO (where the OS allows it) and changes no number."""
    from gyronet.errors import ConfigError
    from gyronet.deploy.stream import FaultPlan, plan_stream
    from gyronet.deploy.stream.live import run_stream
    from gyronet.deploy.stream.priority import use_realtime
    from gyronet.deploy.stream.pty_sensor import play_in_thread

    try:
        use_realtime(1)()
    except ConfigError:
        pytest.skip("this user may not use SCHED_FIFO")
    recording = load_recording(short_recording)
    plan = plan_stream(recording.columns, "lpbus", FaultPlan(seed=3))
    link = tmp_path / "sensor"
    thread = play_in_thread(plan, link)
    summary = run_stream(bundle, str(link), tmp_path / "live.csv", allan_every_s=60, tb_dir=tmp_path / "tb",
                         reconnect={"backoff_s": 0.05, "max_backoff_s": 0.2, "give_up_s": 0.5, "wait_at_start": True},
                         realtime_priority=20)
    thread.join(10)
    assert os.sched_getscheduler(0) == os.SCHED_OTHER
    assert summary["n_samples"] == len(plan.log["good_indices"])
    assert set(summary["allan"]) == {"x", "y", "z"}
    assert_matches_offline(read_output(tmp_path / "live.csv"),
                           *expected_output(bundle, short_recording, plan.log, "lpbus"))
