"""Fuzz the live decoders (CSV lines, LP-BUS): damaged streams in, every intact frame out exactly, no crash.

Each example is a stream of good frames with random damage: flipped bytes, cuts (with and without
the line end), inserted garbage, stale copies, extra cells and, for CSV, duplicated, cut and
damaged header lines. It is fed in one chunk and in random splits. The oracle:

- every intact good frame comes out as a ``Sample`` with exactly its values, in order (intact: its
  bytes unchanged and, for CSV, on a line of its own; the header of the stream is never damaged);
- every other output is a ``Fault`` with a reason of ``FAULT_REASONS``, or a ``Sample`` that the
  damage happened to make valid ("foreign": its values are finite and its time passed the check);
- a good frame may be missing only when a foreign sample explains it: its time was ahead by at
  most ``restart_back_s`` (the good frame then reads as stale), or, on LP-BUS, a foreign frame
  covered the good frame's bytes;
- one chunk and random splits give the same output.

LP-BUS checksum collisions: the LRC is a 16-bit sum and the footer two fixed bytes, so a damaged
span that passes both (two changes that cancel in the sum, a cut frame completed by the bytes
after it) is decoded as good: the protocol cannot tell. The test counts it as a foreign sample
and checks only that its values are finite and its time passed the check.
"""
from __future__ import annotations

import math

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from gyronet.deploy.stream import (FAULT_REASONS, CsvLineParser, Fault, LpBusLayout, LpBusParser, Sample,
                            encode_csv_header, encode_csv_line, encode_lpbus)

NAMES = ["time_s", "temp_c", "gyro_x_dps", "gyro_y_dps", "gyro_z_dps", "acc_x_g", "acc_y_g", "acc_z_g"]
NEEDED = ["time_s", "temp_c", "gyro_x_dps", "gyro_y_dps", "gyro_z_dps"]
LAYOUT = LpBusLayout()
RESTART_BACK_S = 1.0

CSV_DAMAGE = ["flip", "cut", "cut_keep_end", "extra_cell", "junk", "stale", "header", "header_cut",
              "header_flip"]
LPBUS_DAMAGE = ["flip", "flip2", "cut", "junk", "stale", "length"]


def feed(parser, stream: bytes, splits: list[int]) -> list:
    """Feed ``stream`` cut at ``splits`` (sorted positions), then flush."""
    out, start = [], 0
    for stop in [*splits, len(stream)]:
        out += parser.feed(stream[start:stop])
        start = stop
    return out + parser.flush()


@st.composite
def good_rows(draw, lpbus: bool) -> list[dict[str, float]]:
    n = draw(st.integers(1, 24))
    value = (st.floats(-1e6, 1e6, allow_nan=False, width=32) if lpbus
             else st.floats(allow_nan=False, allow_infinity=False))
    if lpbus:  # LP-BUS counts 400 Hz ticks
        ticks = np.cumsum(draw(st.lists(st.integers(1, 4000), min_size=n, max_size=n)))
        times = [int(t) / LAYOUT.timestamp_hz for t in ticks]
    else:
        times = (np.cumsum(draw(st.lists(st.floats(1e-3, 5.0), min_size=n, max_size=n)))
                 + draw(st.floats(0.0, 1e5))).tolist()
    rows = []
    for time_s in times:
        row = {"time_s": float(time_s), **{c: draw(value) for c in NAMES[1:]}}
        rows.append(LAYOUT.quantize(row) if lpbus else row)
    return rows


def _flip(data: bytes, draw) -> bytes:
    position = draw(st.integers(0, len(data) - 1))
    damaged = bytearray(data)
    damaged[position] ^= draw(st.integers(1, 255))
    return bytes(damaged)


def _cut(data: bytes, draw) -> bytes:
    return data[:draw(st.integers(0, len(data) - 1))]


@st.composite
def csv_case(draw):
    """Good rows, and the stream as pieces: bytes, and the good row a piece carries unchanged (or None)."""
    rows = draw(good_rows(lpbus=False))
    header = encode_csv_header(NAMES)
    pieces: list[tuple[bytes, int | None]] = [(header, None)]
    for index, row in enumerate(rows):
        line = encode_csv_line(row, NAMES)
        kind = draw(st.sampled_from([None] * 6 + CSV_DAMAGE))
        if kind == "flip":
            pieces.append((_flip(line, draw), None))
        elif kind == "cut":  # the line end goes too: it runs into the next line
            pieces.append((_cut(line, draw), None))
        elif kind == "cut_keep_end":
            pieces.append((_cut(line[:-1], draw) + b"\n", None))
        elif kind == "extra_cell":
            pieces.append((line[:-1] + b",1.5\n", None))
        else:
            inserted = {"junk": lambda: draw(st.binary(min_size=1, max_size=40)),
                        "stale": lambda: encode_csv_line(rows[max(index - 1, 0)], NAMES),
                        "header": lambda: header,
                        "header_cut": lambda: _cut(header[:-1], draw) + b"\n",
                        "header_flip": lambda: _flip(header[:-1], draw) + b"\n"}.get(kind)
            if inserted is not None:
                pieces.append((inserted(), None))
            pieces.append((line, index))
    return rows, pieces


@st.composite
def lpbus_case(draw):
    rows = draw(good_rows(lpbus=True))
    pieces: list[tuple[bytes, int | None]] = []
    for index, row in enumerate(rows):
        frame = encode_lpbus(row, LAYOUT)
        kind = draw(st.sampled_from([None] * 4 + LPBUS_DAMAGE))
        if kind == "flip":
            pieces.append((_flip(frame, draw), None))
        elif kind == "flip2":  # two changes that may cancel in the LRC sum
            pieces.append((_flip(_flip(frame, draw), draw), None))
        elif kind == "cut":
            pieces.append((_cut(frame, draw), None))
        elif kind == "length":  # a length field that claims more or fewer bytes
            damaged = bytearray(frame)
            damaged[5] = draw(st.integers(0, 255))
            pieces.append((bytes(damaged), None))
        else:
            if kind == "junk":
                pieces.append((draw(st.binary(min_size=1, max_size=60)), None))
            elif kind == "stale":
                pieces.append((encode_lpbus(rows[max(index - 1, 0)], LAYOUT), None))
            pieces.append((frame, index))
    return rows, pieces


def intact_spans(pieces, csv: bool) -> dict[int, tuple[int, int]]:
    """Good row index -> byte span of its frame, for the frames that arrive intact."""
    spans, position, previous = {}, 0, b"\n"
    for data, index in pieces:
        if index is not None and (not csv or previous.endswith(b"\n")):
            spans[index] = (position, position + len(data))
        position += len(data)
        previous = data if data else previous
    return spans


def check_outputs(out: list, rows: list[dict], spans: dict[int, tuple[int, int]], same) -> dict[str, int]:
    """The oracle of the module docstring; returns counts for the record."""
    good = sorted(spans)
    came_out: dict[int, int] = {}  # good row index -> output position
    foreign: list[tuple[int, Sample]] = []
    cursor = 0
    for position, item in enumerate(out):
        if isinstance(item, Fault):
            assert item.reason in FAULT_REASONS
            continue
        assert isinstance(item, Sample), item
        assert math.isfinite(item.time_s) and all(math.isfinite(v) for v in item.values.values())
        k = next((k for k in range(cursor, len(good)) if same(item, rows[good[k]])), None)
        if k is None:
            foreign.append((position, item))
        else:
            came_out[good[k]] = position
            cursor = k + 1
    for index in good:
        if index in came_out:
            continue
        time_s = rows[index]["time_s"]
        # stale after a foreign sample ahead of it by at most the restart threshold
        stale = any(0.0 <= sample.time_s - time_s <= RESTART_BACK_S for _, sample in foreign)
        # covered by a foreign frame: one came out between its good neighbours
        before = max((p for i, p in came_out.items() if i < index), default=-1)
        after = min((p for i, p in came_out.items() if i > index), default=len(out))
        covered = any(before < p < after for p, _ in foreign)
        assert stale or covered, f"good frame {index} (time_s={time_s!r}) lost without a reason; out: {out}"
    return {"good": len(good), "out": len(came_out), "foreign": len(foreign),
            "faults": sum(isinstance(item, Fault) for item in out)}


def same_csv(sample: Sample, row: dict) -> bool:
    """Every value by position (a damaged header may rename a column nothing needs), the needed ones by name too."""
    return (sample.time_s == row["time_s"] and list(sample.values.values()) == [row[c] for c in NAMES[1:]]
            and all(sample.values.get(c) == row[c] for c in NEEDED[1:]))


def same_lpbus(sample: Sample, row: dict) -> bool:
    return sample.row() == row


def splits_of(draw, n_bytes: int) -> list[int]:
    return sorted(set(draw(st.lists(st.integers(0, n_bytes), max_size=30))))


@given(case=csv_case(), data=st.data())
def test_csv_decoder_keeps_every_intact_line_through_any_damage(case, data):
    rows, pieces = case
    stream = b"".join(piece for piece, _ in pieces)
    whole = feed(CsvLineParser(required=NEEDED), stream, [])
    assert feed(CsvLineParser(required=NEEDED), stream, splits_of(data.draw, len(stream))) == whole
    assert feed(CsvLineParser(required=NEEDED), stream, list(range(1, len(stream)))) == whole
    check_outputs(whole, rows, intact_spans(pieces, csv=True), same_csv)


@given(case=lpbus_case(), data=st.data())
def test_lpbus_decoder_keeps_every_intact_frame_through_any_damage(case, data):
    rows, pieces = case
    stream = b"".join(piece for piece, _ in pieces)
    whole = feed(LpBusParser(LAYOUT), stream, [])
    assert feed(LpBusParser(LAYOUT), stream, splits_of(data.draw, len(stream))) == whole
    assert feed(LpBusParser(LAYOUT), stream, list(range(1, len(stream)))) == whole
    check_outputs(whole, rows, intact_spans(pieces, csv=False), same_lpbus)


@given(junk=st.binary(max_size=300), data=st.data())
def test_decoders_never_crash_on_arbitrary_bytes(junk, data):
    splits = splits_of(data.draw, len(junk))
    for make in (lambda: CsvLineParser(required=NEEDED), lambda: LpBusParser(LAYOUT)):
        out = feed(make(), junk, splits)
        assert out == feed(make(), junk, [])
        assert all(isinstance(item, (Sample, Fault)) for item in out)


def offline_cell(cell: str) -> float | None:
    """The offline loader's reading of one cell (pandas, float64): its value, or None when it refuses it."""
    import io

    import pandas as pd

    try:
        column = pd.read_csv(io.StringIO(f"time_s,gyro_x_dps\n0.1,{cell}\n"), dtype=np.float64)["gyro_x_dps"]
    except ValueError:
        return None
    return float(column.iloc[0]) if len(column) == 1 and np.isfinite(column.iloc[0]) else None


NUMBERISH = st.text(alphabet="0123456789.eE+-_ \tnaifyxX", min_size=1, max_size=10)


@given(cells=st.lists(NUMBERISH | st.floats(allow_nan=False).map(repr), min_size=1, max_size=12))
def test_csv_cells_are_read_as_the_offline_loader_reads_them(cells):
    cells = [c for c in cells if "\n" not in c and "," not in c and c.strip(" \t")]
    parser = CsvLineParser()
    parser.feed(b"time_s,gyro_x_dps\n")
    for time_s, cell in enumerate(cells, start=1):
        (item,) = parser.feed(f"{time_s},{cell}\n".encode())
        expected = offline_cell(cell)
        if expected is None:
            assert isinstance(item, Fault) and item.reason in ("non_numeric", "nan"), (cell, item)
        else:
            assert isinstance(item, Sample) and item.values["gyro_x_dps"] == expected, (cell, item)
