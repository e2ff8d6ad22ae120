"""The live loop with the LP-BUS and CSV flood paths (blocks of columns) against the loop with them turned off.

On the same reads, the output file and the summary must be the same bytes and counts; through a
real pseudo-terminal (where the chunking is the scheduler's), the same samples, faults and
values (the gyro columns to 1e-9: a chunk of a few rows runs in plain floats).
"""
import time

import numpy as np
import pandas as pd
import pytest

from gyronet.recordings.data import GYRO_COLUMNS, load_recording
from gyronet.deploy.stream import CsvLineParser, FaultPlan, plan_stream
from gyronet.deploy.stream.csv_run import LineRun
from gyronet.deploy.stream.lpbus_run import FrameRun
from conftest import OUT_OF_RANGE_TEMP_C
from test_live_chunks import assert_same_rows, offline_by_segment, reads_of, run

SUMMARY_KEYS = ("stopped", "n_samples", "faults", "n_faults", "n_out_of_range", "clock_restarts", "allan_bins")


class FloodPath:
    """Counts the samples the flood path decodes; ``off()`` turns it off (every frame goes one by one)."""

    def __init__(self, monkeypatch):
        self.monkeypatch, self.decoded, decode = monkeypatch, [], FrameRun.decode

        def counted(run, *args):
            block, step = decode(run, *args)
            self.decoded.append(0 if block is None else len(block))
            return block, step

        monkeypatch.setattr(FrameRun, "decode", counted)

    def off(self) -> None:
        self.monkeypatch.setattr(FrameRun, "decode", lambda run, *args: (None, 0))


@pytest.fixture
def flood_path(monkeypatch) -> FloodPath:
    return FloodPath(monkeypatch)


class CsvFloodPath:
    """Counts the samples the CSV flood path reads; ``off()`` turns it off (every line goes one by one)."""

    def __init__(self, monkeypatch):
        self.monkeypatch, self.decoded, decode = monkeypatch, [], LineRun.decode

        def counted(run, *args):
            block, step, retry = decode(run, *args)
            self.decoded.append(0 if block is None else len(block))
            return block, step, retry

        monkeypatch.setattr(LineRun, "decode", counted)

    def off(self) -> None:
        self.monkeypatch.setattr(LineRun, "decode", lambda run, buffer, position, check: (None, 0, len(buffer)))


@pytest.fixture
def csv_flood(paper_csv) -> tuple[dict, bytes]:
    """2,000 samples as CSV lines, the sensor replugged (its clock starts again) after 1,200, with garbage lines,
    non-numeric cells, cut lines, NaN and out-of-range temperatures."""
    recording = load_recording(paper_csv).slice(slice(0, 2000))
    columns = {c: v.copy() for c, v in recording.columns.items()}
    columns["time_s"][1200:] = columns["time_s"][1200:] - columns["time_s"][1200] + 0.5
    faults = FaultPlan(garbage_rate=0.01, corrupt_rate=0.01, truncate_rate=0.01, nan_rate=0.005, out_of_range_every=41,
                       out_of_range_temp_c=OUT_OF_RANGE_TEMP_C, seed=4)
    plan = plan_stream(columns, "csv", faults)
    return plan.log, plan.preamble + b"".join(event.data for event in plan.events if not event.drop)


@pytest.mark.parametrize("max_samples", [None, 1500])
def test_flood_path_writes_the_same_file_and_summary_as_frame_by_frame(bundle, flood, tmp_path, monkeypatch,
                                                                       flood_path, max_samples):
    _, data = flood
    reads = reads_of(data, seed=5, max_bytes=20000)
    options = {"max_samples": max_samples, "startup": {"still_s": 120.0, "motion_dps": 5.0}}
    fast, _ = run(monkeypatch, bundle, tmp_path, reads, False, "fast", **options)
    assert sum(flood_path.decoded) > 0.8 * fast["n_samples"] > 1000
    flood_path.off()
    slow, _ = run(monkeypatch, bundle, tmp_path, reads, False, "slow", **options)
    assert {k: fast[k] for k in SUMMARY_KEYS} == {k: slow[k] for k in SUMMARY_KEYS}
    assert fast["clock_restarts"] == 1 and fast["n_faults"] > 50
    if max_samples is not None:  # the stream stops there, on either path
        assert fast["n_samples"] == max_samples and fast["stopped"] == "max_samples"
    assert (tmp_path / "fast.csv").read_bytes() == (tmp_path / "slow.csv").read_bytes()


def test_flood_through_a_pty_equals_frame_by_frame(bundle, paper_csv, tmp_path, monkeypatch, flood_path):
    from gyronet.recordings.data import load_recording
    from gyronet.deploy.stream.live import run_stream
    from gyronet.deploy.stream.pty_sensor import play_in_thread

    columns = load_recording(paper_csv).slice(slice(0, 3000)).columns
    faults = FaultPlan(garbage_rate=0.01, corrupt_rate=0.01, truncate_rate=0.01, nan_rate=0.005, seed=7)
    summaries, outputs = {}, {}
    for name in ("fast", "slow"):
        if name == "slow":
            flood_path.off()
        link = tmp_path / f"sensor_{name}"
        thread = play_in_thread(plan_stream(columns, "lpbus", faults), link)
        deadline = time.monotonic() + 10
        while not link.exists() and time.monotonic() < deadline:
            time.sleep(0.01)
        summaries[name] = run_stream(bundle, str(link), tmp_path / f"{name}.csv", allan_every_s=0,
                                     reconnect={"give_up_s": 0.3, "backoff_s": 0.05})
        thread.join(10)
        outputs[name] = pd.read_csv(tmp_path / f"{name}.csv", comment="#")
        if name == "fast":
            assert sum(flood_path.decoded) > 0.5 * summaries[name]["n_samples"]  # the reads held runs of frames
    assert {k: summaries["fast"][k] for k in SUMMARY_KEYS} == {k: summaries["slow"][k] for k in SUMMARY_KEYS}
    assert summaries["fast"]["n_samples"] > 2800 and summaries["fast"]["faults"]["nan"] > 0
    assert_same_rows(outputs["fast"], outputs["slow"])
    np.testing.assert_array_equal(outputs["fast"]["time_s"].to_numpy(), outputs["slow"]["time_s"].to_numpy())


def test_first_rows_cuts_a_block_where_the_rows_end():
    from gyronet.deploy.stream import Sample
    from gyronet.deploy.stream.chunk import first_rows, n_rows
    from gyronet.deploy.stream.events import SampleBlock

    one = Sample(0.5, {"temp_c": 25.0})
    block = SampleBlock({"time_s": np.arange(1.0, 11.0), "temp_c": np.full(10, 25.0)})
    cut = first_rows([one, block, one], 5)
    assert n_rows(cut) == 5 and cut[0] is one and cut[1].columns["time_s"].tolist() == [1.0, 2.0, 3.0, 4.0]
    assert [len(first_rows([one, block, one], k)) for k in (0, 1, 11, 12, 13)] == [0, 1, 2, 3, 3]


@pytest.mark.parametrize("max_samples", [None, 1500])
def test_csv_flood_path_writes_the_same_file_and_summary_as_line_by_line_and_offline(bundle, csv_flood, tmp_path,
                                                                                    monkeypatch, max_samples):
    log, data = csv_flood
    counted = CsvFloodPath(monkeypatch)
    reads = reads_of(data, seed=5, max_bytes=20000)
    options = {"max_samples": max_samples, "startup": {"still_s": 120.0, "motion_dps": 5.0}}
    fast, rows = run(monkeypatch, bundle, tmp_path, reads, False, "fast", protocol="csv", **options)
    assert sum(counted.decoded) > 0.8 * fast["n_samples"] > 1000
    counted.off()
    slow, _ = run(monkeypatch, bundle, tmp_path, reads, False, "slow", protocol="csv", **options)
    assert {k: fast[k] for k in SUMMARY_KEYS} == {k: slow[k] for k in SUMMARY_KEYS}
    assert fast["clock_restarts"] == 1 and fast["n_faults"] > 50
    if max_samples is None:
        assert fast["faults"] == log["expected_faults"] and fast["n_samples"] == len(log["good_indices"])
    else:
        assert fast["n_samples"] == max_samples and fast["stopped"] == "max_samples"
    assert (tmp_path / "fast.csv").read_bytes() == (tmp_path / "slow.csv").read_bytes()
    time_s, rate_dps = offline_by_segment(bundle, reads, CsvLineParser(), **options["startup"])
    n = len(rows)
    np.testing.assert_array_equal(rows["time_s"].to_numpy(), time_s[:n])
    np.testing.assert_allclose(rows[list(GYRO_COLUMNS)].to_numpy(), rate_dps[:n], rtol=0, atol=1e-9)
