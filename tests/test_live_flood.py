"""The live loop with the LP-BUS flood path (blocks of columns) against the loop with it turned off.

On the same reads, the output file and the summary must be the same bytes and counts; through a
real pseudo-terminal (where the chunking is the scheduler's), the same samples, faults and
values (the gyro columns to 1e-9: a chunk of a few rows runs in plain floats).
"""
import time

import numpy as np
import pandas as pd
import pytest

from gyronet.stream import FaultPlan, plan_stream
from gyronet.stream.lpbus_run import FrameRun
from test_live_chunks import assert_same_rows, flood, reads_of, run  # noqa: F401 (flood: a fixture)

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
    assert (tmp_path / "fast.csv").read_bytes() == (tmp_path / "slow.csv").read_bytes()


def test_flood_through_a_pty_equals_frame_by_frame(bundle, paper_csv, tmp_path, monkeypatch, flood_path):
    from gyronet.data import load_recording
    from gyronet.stream.live import run_stream
    from gyronet.stream.pty_sensor import play_in_thread

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
    from gyronet.stream import Sample
    from gyronet.stream.chunk import first_rows, n_rows
    from gyronet.stream.events import SampleBlock

    one = Sample(0.5, {"temp_c": 25.0})
    block = SampleBlock({"time_s": np.arange(1.0, 11.0), "temp_c": np.full(10, 25.0)})
    cut = first_rows([one, block, one], 5)
    assert n_rows(cut) == 5 and cut[0] is one and cut[1].columns["time_s"].tolist() == [1.0, 2.0, 3.0, 4.0]
    assert [len(first_rows([one, block, one], k)) for k in (0, 1, 11, 12, 13)] == [0, 1, 2, 3, 3]
