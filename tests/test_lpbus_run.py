"""The LP-BUS flood path (``LpBusParser(blocks=True)``, :mod:`gyronet.deploy.stream.lpbus_run`) against the per-frame path.

A stream of good frames with damage of every kind (cut frames, flipped bytes, garbage, frames of
another length or sensor id with a good LRC, time going back a little and a lot, jumping ahead,
NaN values, repeated frames) is fed in random chunk sizes to both parsers. Taken apart into
samples, the flood path's output must be the per-frame path's: the same samples and faults in the
same order, every value the same float64 to the bit, and the check left in the same state.
"""
import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from gyronet.deploy.stream import Fault, LpBusLayout, LpBusParser, Sample, SampleCheck, encode_lpbus, lpbus_frame
from gyronet.deploy.stream.events import SampleBlock, as_samples
from gyronet.deploy.stream.lpbus_run import MIN_RUN_FRAMES

LAYOUTS = {
    "legacy32": LpBusLayout(),
    "legacy16": LpBusLayout(precision=16),
    "float_time_euler": LpBusLayout(fields=("gyro", "acc", "euler", "temperature"), timestamp="float"),
    "ig1_id1": LpBusLayout(generation="ig1", fields=("acc", "gyro", "temperature"), sensor_id=1),
}
DAMAGE = ["cut", "flip", "garbage", "length", "other_id", "back_small", "back_large", "jump", "nan", "repeat"]


def key(item) -> tuple:
    """What must match exactly: floats by their bits (``hex`` tells -0.0 from 0.0)."""
    if isinstance(item, Fault):
        return ("fault", item.reason, item.raw, item.detail)
    assert isinstance(item, Sample)
    return ("sample", item.time_s.hex(), tuple((k, v.hex()) for k, v in item.values.items()), item.new_segment)


def damaged_stream(layout: LpBusLayout, rng: np.random.Generator, n_frames: int, damage_rate: float) -> bytes:
    """``n_frames`` good frames 1 ms apart, each damaged with probability ``damage_rate`` by one kind of ``DAMAGE``."""
    sensor_id = layout.sensor_id or 1
    scale = 1e4 if layout.precision == 16 else 1.0  # 16-bit values must fit an int16 once scaled
    frames, time_s = [], 10.0
    for _ in range(n_frames):
        time_s += 1e-2 if layout.timestamp == "count" else 1e-3
        row = {c: float(rng.normal(0.0, 1.0) / scale) for c in layout.columns[1:]}
        row["time_s"] = time_s
        frame = encode_lpbus(row, layout, sensor_id)
        kind = DAMAGE[rng.integers(len(DAMAGE))] if rng.random() < damage_rate else None
        if kind == "cut":
            frame = frame[:rng.integers(1, len(frame))]
        elif kind == "flip":
            at = rng.integers(len(frame))
            frame = frame[:at] + bytes([frame[at] ^ (1 << rng.integers(8))]) + frame[at + 1:]
        elif kind == "garbage":
            frame = rng.integers(0, 256, rng.integers(1, 60), dtype=np.uint8).tobytes() + frame
        elif kind == "length":
            frame = lpbus_frame(sensor_id, 9, layout.encode(row)[:-2]) + frame
        elif kind == "other_id":
            frame = lpbus_frame(sensor_id + 1, 9, layout.encode(row)) + frame
        elif kind in ("back_small", "back_large", "jump"):
            step_s = {"back_small": -0.5, "back_large": -5.0, "jump": 7200.0}[kind]
            frame = encode_lpbus({**row, "time_s": max(0.0, time_s + step_s)}, layout, sensor_id)
            time_s = time_s if kind == "back_small" else max(0.0, time_s + step_s)
        elif kind == "nan" and layout.precision == 32:
            frame = encode_lpbus({**row, layout.columns[1 + rng.integers(len(layout.columns) - 1)]: math.nan},
                                 layout, sensor_id)
        elif kind == "repeat":
            frame = frame + frame
        frames.append(frame)
    return b"".join(frames)


def parse(stream: bytes, layout: LpBusLayout, cuts: list[int], blocks: bool) -> tuple[list, SampleCheck]:
    check = SampleCheck(restart_back_s=1.0, restart_jump_s=3600.0)
    parser = LpBusParser(layout, check=check, blocks=blocks)
    out, start = [], 0
    for stop in [*cuts, len(stream)]:
        out += parser.feed(stream[start:stop])
        start = stop
    return out + parser.flush(), check


def assert_same(stream: bytes, layout: LpBusLayout, cuts: list[int]) -> list:
    """Both paths on ``stream`` cut at ``cuts``; returns the flood path's raw output."""
    per_frame, check = parse(stream, layout, cuts, blocks=False)
    flood, flood_check = parse(stream, layout, cuts, blocks=True)
    assert [key(item) for item in as_samples(flood)] == [key(item) for item in per_frame]
    assert (flood_check.last_time_s, flood_check.n_restarts) == (check.last_time_s, check.n_restarts)
    return flood


@pytest.mark.parametrize("name", sorted(LAYOUTS))
@pytest.mark.parametrize("seed", range(3))
def test_flood_path_equals_per_frame_path_on_damaged_streams(name, seed):
    layout, rng = LAYOUTS[name], np.random.default_rng(seed)
    stream = damaged_stream(layout, rng, n_frames=3000, damage_rate=0.02)
    cuts = np.cumsum(rng.integers(1, 8000, size=len(stream) // 500 + 1))
    flood = assert_same(stream, layout, sorted(cuts[cuts < len(stream)].tolist()))
    per_frame, _ = parse(stream, layout, [], blocks=False)
    # the flood path did the bulk of the work, and every kind of damage was met
    blocks = [item for item in flood if isinstance(item, SampleBlock)]
    assert sum(map(len, blocks)) > 0.6 * sum(isinstance(item, Sample) for item in per_frame) and len(blocks) > 20
    reasons = {item.reason for item in per_frame if isinstance(item, Fault)}
    assert {"garbage", "bad_length", "time_not_increasing", "bad_checksum"} <= reasons
    assert any(isinstance(item, Sample) and item.new_segment for item in per_frame)


@given(seed=st.integers(0, 2**32 - 1), damage_rate=st.sampled_from([0.0, 0.01, 0.1, 0.5]),
       name=st.sampled_from(sorted(LAYOUTS)), max_read=st.sampled_from([1, 50, 4096, 65536]))
def test_flood_path_equals_per_frame_path_for_any_damage_and_chunking(seed, damage_rate, name, max_read):
    layout, rng = LAYOUTS[name], np.random.default_rng(seed)
    stream = damaged_stream(layout, rng, n_frames=int(rng.integers(1, 400)), damage_rate=damage_rate)
    cuts = np.cumsum(rng.integers(1, max_read + 1, size=len(stream) + 1))
    assert_same(stream, layout, sorted(cuts[cuts < len(stream)].tolist()))


def test_a_run_stops_at_the_first_bad_frame_and_resumes_after_it():
    layout = LpBusLayout()
    rows = [{c: 0.5 for c in layout.columns} | {"time_s": 1.0 + i / 400} for i in range(3 * MIN_RUN_FRAMES)]
    frames = [encode_lpbus(row, layout) for row in rows]
    bad = bytearray(frames[MIN_RUN_FRAMES + 3])
    bad[10] ^= 0xFF  # a data byte: the LRC no longer matches
    stream = b"".join([*frames[:MIN_RUN_FRAMES + 3], bytes(bad), *frames[MIN_RUN_FRAMES + 4:]])
    out, _ = parse(stream, layout, [], blocks=True)
    assert [type(item).__name__ for item in out] == ["SampleBlock", "Fault", "SampleBlock"]
    assert (len(out[0]), out[1].reason, len(out[2])) == (MIN_RUN_FRAMES + 3, "bad_checksum", 2 * MIN_RUN_FRAMES - 4)


def test_fewer_frames_than_a_run_and_a_first_frames_check_go_frame_by_frame():
    layout = LpBusLayout()
    stream = b"".join(encode_lpbus({c: 0.5 for c in layout.columns} | {"time_s": 1.0 + i / 400}, layout)
                      for i in range(MIN_RUN_FRAMES - 1))
    out, _ = parse(stream, layout, [], blocks=True)
    assert all(isinstance(item, Sample) for item in out) and len(out) == MIN_RUN_FRAMES - 1

    class Probe:  # a first-frames check that sees every frame
        done, frames = False, []

        def see(self, time_s, values):
            self.frames.append(time_s)

        def check(self):
            pass

    parser = LpBusParser(layout, blocks=True)
    parser.probe = Probe()
    parser.feed(stream * 3)  # enough frames for a run: the check still sees each one
    assert len(parser.probe.frames) == 3 * (MIN_RUN_FRAMES - 1)
