"""The live loop by chunks (issue 13 item 5): a read's good samples go through the compensator together.

Chunked and per-sample processing must write the same file and the same summary on floods with
faults, out-of-range temperatures, clock restarts and the start-up window's end inside a chunk,
and both must equal the offline path on each segment's samples. A lone frame is still written
before the next read.
"""
import json

import numpy as np
import pandas as pd
import pytest

from gyronet.bundle.compensator import Compensator
from gyronet.recordings.data import GYRO_COLUMNS, Recording, load_recording
from gyronet.bundle.offline import compensate_recording
from gyronet.deploy.stream import FaultPlan, LpBusParser, Sample, lpbus_frame
from gyronet.deploy.stream.events import as_samples
from conftest import lpbus_bytes

def reads_of(data: bytes, seed: int, max_bytes: int = 6000) -> list[bytes]:
    """``data`` cut at random into reads of 1 to ``max_bytes`` bytes: chunks of many frames, cut frames."""
    rng = np.random.default_rng(seed)
    cuts = np.cumsum(rng.integers(1, max_bytes, size=len(data) // 50 + 2))
    cuts = [0, *cuts[cuts < len(data)].tolist(), len(data)]
    return [data[a:b] for a, b in zip(cuts, cuts[1:])]


def scripted_reads(reads: list[bytes], per_sample: bool):
    """A ``read_chunks`` stand-in: the real parser on these reads, one chunk a read (or one an item)."""

    def read_chunks(port, parser, *, should_stop, **kwargs):
        for data in reads:
            if should_stop():
                return
            items = parser.feed(data)
            if per_sample:  # a flood's block taken apart: one chunk a sample, as the loop before chunks
                yield from ([item] for item in as_samples(items))
            elif items:
                yield items
        yield parser.flush()

    return read_chunks


def run(monkeypatch, bundle, tmp_path, reads: list[bytes], per_sample: bool, name: str, **options):
    import gyronet.deploy.stream.live as live

    monkeypatch.setattr(live, "read_chunks", scripted_reads(reads, per_sample))
    path = tmp_path / f"{name}.csv"
    summary = live.run_stream(bundle, "sensor", path, allan_every_s=30, reconnect={"wait_at_start": True},
                              **options)
    return summary, pd.read_csv(path, comment="#")


def offline_by_segment(bundle, reads: list[bytes], parser=None, **startup) -> tuple[np.ndarray, np.ndarray]:
    """The good samples' times and ``compensate_recording`` of each segment from a fresh state (``parser``: the
    per-frame parser of the reads' framing, default LP-BUS)."""
    parser, samples = parser or LpBusParser(), []
    for data in reads:
        samples += [item for item in parser.feed(data) if isinstance(item, Sample)]
    starts = [i for i, s in enumerate(samples) if i == 0 or s.new_segment] + [len(samples)]
    rates = []
    for a, b in zip(starts, starts[1:]):
        segment = samples[a:b]
        columns = {"time_s": np.array([s.time_s for s in segment]),
                   **{c: np.array([s.values[c] for s in segment]) for c in segment[0].values}}
        compensator = Compensator.load(bundle)
        if startup:
            compensator.use_startup(**startup)
        rates.append(compensate_recording(compensator, Recording(columns, {}, "segment")).rate_dps)
    return np.array([s.time_s for s in samples]), np.concatenate(rates)


def assert_same_rows(a: pd.DataFrame, b: pd.DataFrame) -> None:
    assert list(a.columns) == list(b.columns) and len(a) == len(b) > 0
    exact = [c for c in a.columns if c not in GYRO_COLUMNS]
    pd.testing.assert_frame_equal(a[exact], b[exact])
    np.testing.assert_allclose(a[list(GYRO_COLUMNS)].to_numpy(), b[list(GYRO_COLUMNS)].to_numpy(), rtol=0, atol=1e-9)


def test_chunked_equals_per_sample_and_offline_with_faults_and_a_restart_inside_chunks(bundle, flood, tmp_path,
                                                                                        monkeypatch):
    log, data = flood
    reads = reads_of(data, seed=1)
    assert max(len(r) for r in reads) > 100 * 40  # reads of a hundred frames and more
    chunked, rows = run(monkeypatch, bundle, tmp_path, reads, False, "chunked")
    single, single_rows = run(monkeypatch, bundle, tmp_path, reads, True, "single")
    assert chunked["clock_restarts"] == single["clock_restarts"] == 1
    assert chunked["n_samples"] == len(log["good_indices"]) == len(rows)
    assert chunked["faults"] == single["faults"] == log["expected_faults"]
    assert chunked["n_out_of_range"] == single["n_out_of_range"] == len(log["out_of_range_indices"]) > 10
    for key in ("allan", "allan_bins"):
        assert chunked[key].keys() == single[key].keys()
    np.testing.assert_allclose([v for axis in "xyz" for v in chunked["allan"][axis].values()],
                               [v for axis in "xyz" for v in single["allan"][axis].values()], rtol=1e-9)
    assert chunked["allan_bins"] == single["allan_bins"]
    assert_same_rows(rows, single_rows)
    time_s, rate_dps = offline_by_segment(bundle, reads)
    np.testing.assert_array_equal(rows["time_s"].to_numpy(), time_s)
    np.testing.assert_allclose(rows[list(GYRO_COLUMNS)].to_numpy(), rate_dps, rtol=0, atol=1e-9)


def test_leaving_the_trained_range_is_one_warning_an_excursion(bundle, flood, tmp_path, monkeypatch, caplog):
    log, data = flood  # a sample outside every 41 (20 s at 2 Hz): one excursion a clock, named once each
    for per_sample in (False, True):
        caplog.clear()
        with caplog.at_level("WARNING", logger="gyronet.deploy.stream.chunk"):
            summary, _ = run(monkeypatch, bundle, tmp_path, reads_of(data, seed=1), per_sample, f"run{per_sample}")
        warned = [r.getMessage() for r in caplog.records if "outside the trained range" in r.getMessage()]
        assert len(warned) == 2 and "flagged out_of_range" in warned[0] and " at 20.000 s " in warned[0]
    assert summary["n_out_of_range"] == len(log["out_of_range_indices"]) > 10


def test_the_start_up_window_ends_inside_a_chunk_as_per_sample_and_offline(bundle, flood, tmp_path, monkeypatch):
    _, data = flood
    reads = reads_of(data, seed=2, max_bytes=20000)
    startup = {"still_s": 120.0, "motion_dps": 5.0}
    chunked, rows = run(monkeypatch, bundle, tmp_path, reads, False, "chunked", startup=startup)
    single, single_rows = run(monkeypatch, bundle, tmp_path, reads, True, "single", startup=startup)
    assert chunked["n_samples"] == single["n_samples"] > 1500
    assert_same_rows(rows, single_rows)
    _, rate_dps = offline_by_segment(bundle, reads, **startup)
    np.testing.assert_allclose(rows[list(GYRO_COLUMNS)].to_numpy(), rate_dps, rtol=0, atol=1e-9)
    # the live Allan figures leave each window's rows out, as allan.py does (they carry no offset yet)
    plain, _ = run(monkeypatch, bundle, tmp_path, reads, False, "plain")
    assert chunked["allan_bins"] == single["allan_bins"]
    window_bins = 120.0 / 0.5  # 0.5 s bins at 2 Hz
    assert window_bins <= plain["allan_bins"]["measured"] - chunked["allan_bins"]["measured"] <= 2.2 * window_bins
    assert all(isinstance(chunked["allan"][a]["bias_instability_upper_bound"], bool) for a in "xyz")


def test_motion_in_the_start_up_window_stops_after_the_windows_rows_as_per_sample(bundle, paper_csv, tmp_path,
                                                                                   monkeypatch):
    from gyronet.bundle.startup import StartupMotionError

    recording = load_recording(paper_csv).slice(slice(0, 600))
    columns = {c: v.copy() for c, v in recording.columns.items()}
    columns["gyro_x_dps"][100:110] += 30.0  # a turn 50 s in
    reads = reads_of(lpbus_bytes(columns, FaultPlan()), seed=3, max_bytes=20000)
    written = {}
    for per_sample in (False, True):
        name = "single" if per_sample else "chunked"
        with pytest.raises(StartupMotionError, match="motion in the start-up window"):
            run(monkeypatch, bundle, tmp_path, reads, per_sample, name, startup={"still_s": 120.0},
                summary_path=tmp_path / f"{name}.json")
        written[name] = pd.read_csv(tmp_path / f"{name}.csv", comment="#")
        summary = json.loads((tmp_path / f"{name}.json").read_text())  # the fault counts are kept, and why it ended
        assert summary["stopped"] == "error" and summary["error"].startswith("motion in the start-up window")
    assert len(written["chunked"]) == len(written["single"]) == 240  # the window's rows: 120 s at 2 Hz
    assert_same_rows(written["chunked"], written["single"])


def test_a_lone_frame_is_written_before_the_next_read(bundle, tmp_path, monkeypatch):
    """No waiting for a chunk to fill: each read's rows are on disk when the reader is asked again."""
    import gyronet.deploy.stream.live as live

    path = tmp_path / "live.csv"
    seen = []

    def read_chunks(port, parser, *, should_stop, **kwargs):
        for i in range(30):
            seen.append(len(pd.read_csv(path, comment="#")))
            yield [Sample(0.5 * i, {"temp_c": 25.0, "gyro_x_dps": 0.1, "gyro_y_dps": 0.2, "gyro_z_dps": 0.3})]

    monkeypatch.setattr(live, "read_chunks", read_chunks)
    live.run_stream(bundle, "sensor", path, allan_every_s=0, reconnect={"wait_at_start": True})
    # the first 20 wait for the rate check (RATE_PROBE_SAMPLES), then every sample is out before the next read
    assert seen == [0] * 20 + list(range(20, 30))


def test_read_chunks_brings_what_waits_in_one_chunk_and_a_lone_frame_at_once():
    import serial

    from gyronet.deploy.stream.reader import read_chunks

    frame = [lpbus_frame(1, 9, bytes(40 - i) + bytes([i])) for i in range(8)]
    port = serial.serial_for_url("loop://", timeout=0.05)
    port.write(b"".join(frame[:5]))
    got = []
    chunks = read_chunks(port, LpBusParser(), should_stop=lambda: len(got) >= 2)
    got.append(next(chunks))
    port.write(frame[5])
    got.append(next(chunks))
    chunks.close()
    assert [len(chunk) for chunk in got] == [5, 1]


def test_a_chunk_cut_by_a_full_disk_keeps_its_complete_lines(bundle, tmp_path, monkeypatch):
    import errno
    import os

    import gyronet.deploy.stream.output as output_module
    from gyronet.bundle.compensator import Compensated
    from gyronet.deploy.stream.output import LiveWriter, OutputError

    writer = LiveWriter(tmp_path / "live.csv", bundle)
    n = 10
    out = Compensated(np.full((n, 3), 0.125), np.zeros((n, 3)), np.zeros(n, dtype=bool), np.zeros(n, dtype=bool))
    line_bytes = len("0.0,0.125,0.125,0.125,25.0,0,0,nan,nan,nan\n")
    real_write, room = os.write, [int(3.5 * line_bytes)]

    def full_disk(fd, data):
        if room[0] <= 0:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        done = real_write(fd, bytes(data[:room[0]]))
        room[0] -= done
        return done

    monkeypatch.setattr(output_module.os, "write", full_disk)
    with pytest.raises(OutputError, match="after 3 rows"):
        writer.write(np.arange(n) * 0.0, np.full(n, 25.0), out)
    monkeypatch.undo()
    text = (tmp_path / "live.csv").read_text()
    assert text.endswith("\n") and writer.n_rows == 3
    assert text.splitlines()[2:] == ["0.0,0.125,0.125,0.125,25.0,0,0,nan,nan,nan"] * 3


def test_rows_in_floats_are_the_lines_write_makes_for_them(tmp_path):
    """``LiveWriter.write_rows`` (the few-frames path) and ``write`` give the same bytes."""
    from gyronet.bundle.compensator import Compensated
    from gyronet.deploy.stream.output import LiveWriter

    time_s, temp_c = [12.345678901234, 12.5, 1e16], [25.0625, -3.0, 1e-5]
    rate = [[0.1 + 1e-17, -2.5e-7, 1234.000000001], [float("nan"), 0.0, -0.0], [float("inf"), -float("inf"), 5e-324]]
    flags = [[True, False, False], [False, True, True]]
    one, many = LiveWriter(tmp_path / "one.csv", tmp_path), LiveWriter(tmp_path / "many.csv", tmp_path)
    sigma = [[1e-3 + 1e-19, 2.5e-4, 0.25], [0.0, float("nan"), 7.0], [1e-300, 3.0, 4.0]]
    one.write_rows([(time_s[k], rate[k], temp_c[k], flags[0][k], flags[1][k], sigma[k]) for k in range(3)])
    many.write(np.array(time_s), np.array(temp_c),
               Compensated(np.array(rate), np.zeros((2, 3)), np.array(flags[0]), np.array(flags[1]), np.array(sigma)))
    one.close(), many.close()
    assert (tmp_path / "one.csv").read_bytes() == (tmp_path / "many.csv").read_bytes()
    assert one.n_rows == many.n_rows == 3
    # the older 5-tuple (no sigmas) still writes, NaN where the sigmas go, as write does without them
    old, arrays = LiveWriter(tmp_path / "old.csv", tmp_path), LiveWriter(tmp_path / "arrays.csv", tmp_path)
    old.write_rows([(time_s[k], rate[k], temp_c[k], flags[0][k], flags[1][k]) for k in range(3)])
    arrays.write(np.array(time_s), np.array(temp_c),
                 Compensated(np.array(rate), np.zeros((2, 3)), np.array(flags[0]), np.array(flags[1])))
    old.close(), arrays.close()
    assert (tmp_path / "old.csv").read_bytes() == (tmp_path / "arrays.csv").read_bytes()


def test_a_chunks_floats_are_written_as_repr_writes_them():
    """The chunk formatting (orjson where installed) gives ``repr``'s text for every float, edge values included."""
    from gyronet.deploy.stream.output import _float_texts, _int_texts

    rng = np.random.default_rng(5)
    edges = [0.0, -0.0, 1e-4, np.nextafter(1e-4, 0), 1e15, np.nextafter(1e15, 0), 1e16, 1e-5, 5.97e-6, 5e-324,
             1.7976931348623157e308, float("nan"), float("inf"), -float("inf"), 12.0, 0.1, 123456.789]
    values = np.concatenate([edges, 2.0 ** np.arange(-20, 60), -(2.0 ** np.arange(-20, 60)),
                             rng.normal(0, 1, 20000) * 10.0 ** rng.uniform(-8, 18, 20000),
                             12.0 + 0.001 * np.arange(5000)])
    assert _float_texts(values) == [repr(v).encode() for v in values.tolist()]
    assert _float_texts(values[::3]) == [repr(v).encode() for v in values[::3].tolist()]  # not contiguous
    flags = np.array([0, 1, 1, 0], dtype=np.int8)
    assert _int_texts(flags) == [b"0", b"1", b"1", b"0"] == _int_texts(flags.astype(bool))


def test_a_chunk_is_the_same_bytes_without_orjson(tmp_path, monkeypatch):
    """``LiveWriter.write`` writes the same bytes through orjson and through ``repr`` alone."""
    import gyronet.deploy.stream.output as output_module
    from gyronet.bundle.compensator import Compensated
    from gyronet.deploy.stream.output import LiveWriter

    rng = np.random.default_rng(6)
    n = 500
    out = Compensated(rng.normal(0, 0.1, (n, 3)), np.zeros((n, 3)), rng.random(n) < 0.1, rng.random(n) < 0.1,
                      np.abs(rng.normal(0, 1e-4, (n, 3))))
    time_s, temp_c = 12.0 + 0.001 * np.arange(n), rng.normal(25.0, 3.0, n)
    fast = LiveWriter(tmp_path / "fast.csv", tmp_path)
    fast.write(time_s, temp_c, out)
    monkeypatch.setattr(output_module, "orjson", None)
    plain = LiveWriter(tmp_path / "plain.csv", tmp_path)
    plain.write(time_s, temp_c, out)
    fast.close(), plain.close()
    assert (tmp_path / "fast.csv").read_bytes() == (tmp_path / "plain.csv").read_bytes()
