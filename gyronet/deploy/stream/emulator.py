"""Plan what an emulated sensor sends: a recording framed as LP-BUS or CSV lines, with seeded faults.

The plan is pure (no ports, no clock), so tests can check it; :mod:`gyronet.deploy.stream.pty_sensor`
plays it into a pseudo-terminal. Each injected fault is built to produce exactly one parser fault,
so the log's ``expected_faults`` is what a reader must count:

- ``garbage``: 1 to ``garbage_max_bytes`` random bytes before a sample (LP-BUS: never the header
  byte 0x3A; CSV: a line of non-ASCII bytes). The sample after it is still good.
- ``corrupt``: LP-BUS: the LRC is flipped (``bad_checksum``); CSV: a cell is made non-numeric.
- ``truncate``: LP-BUS: the frame is cut after its header, inside its data or trailer; CSV: the
  line loses its last cells at a comma (it keeps its newline). No garbage follows a cut frame,
  since the parser would count that as part of the cut one.
- ``nan``: a gyro value is NaN (32-bit LP-BUS and CSV only).
- ``out_of_range_every``: every N-th sample's ``temp_c`` is set to ``out_of_range_temp_c``: a good
  sample that the compensator must flag.
- ``gap_s_at``: ``[start_s, length_s]`` pairs; samples in that span are not sent (a break in the
  record, not a fault).
- ``drop_port_at_s``: the port disappears before the first sample at or after each time: one
  ``port_lost`` for the reader. No sample is lost: the player waits until the reader has read
  everything before it closes the port.
- ``restart_clock_at_s``: a replug: the port drops there (one ``port_lost``) and the sensor's
  clock starts again, so the first sample after it is sent at time 0 and the rest follow on. The
  log's ``clock_offsets_s`` lists ``[first index, offset]`` pairs: sent time = recording time + offset.
  The reader takes that new clock at once (the port was lost); one that starts without a port
  loss (the recording's own) once 5 of its samples confirm it, the 4 before ``time_jump`` faults
  (``SampleCheck`` with its default thresholds, which the plan assumes).

Times of faults are relative to the recording's first sample.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Mapping, Sequence

import numpy as np

from gyronet.deploy.stream.csvline import encode_csv_header, encode_csv_line
from gyronet.deploy.stream.events import RESTART_BACK_S, RESTART_JUMP_S
from gyronet.deploy.stream.lpbus import HEADER_BYTE, HEADER_LEN, encode_lpbus
from gyronet.deploy.stream.lpbus_layout import LpBusLayout
from gyronet.recordings.guard import CONFIRM_SAMPLES

PROTOCOLS = ("lpbus", "csv")
# The parser reason each injected fault kind produces, per protocol.
EXPECTED_REASON = {
    "lpbus": {"garbage": "garbage", "corrupt": "bad_checksum", "truncate": "truncated", "nan": "nan",
              "port_drop": "port_lost", "new_clock": "time_jump"},
    "csv": {"garbage": "garbage", "corrupt": "non_numeric", "truncate": "truncated", "nan": "nan",
            "port_drop": "port_lost", "new_clock": "time_jump"},
}


@dataclass(frozen=True)
class FaultPlan:
    """Faults to inject (rates are per sample, 0..1); see the module docstring."""

    garbage_rate: float = 0.0
    garbage_max_bytes: int = 24
    corrupt_rate: float = 0.0
    truncate_rate: float = 0.0
    nan_rate: float = 0.0
    out_of_range_every: int = 0
    out_of_range_temp_c: float = 150.0
    gap_s_at: tuple[tuple[float, float], ...] = ()
    drop_port_at_s: tuple[float, ...] = ()
    restart_clock_at_s: tuple[float, ...] = ()
    seed: int = 0

    def __post_init__(self) -> None:
        rates = (self.garbage_rate, self.corrupt_rate, self.truncate_rate, self.nan_rate)
        if any(not 0.0 <= r <= 1.0 for r in rates) or self.corrupt_rate + self.truncate_rate + self.nan_rate > 1.0:
            raise ValueError(f"fault rates must be in [0, 1] and corrupt + truncate + nan <= 1, got {rates}")
        object.__setattr__(self, "gap_s_at", tuple((float(a), float(b)) for a, b in self.gap_s_at))
        object.__setattr__(self, "drop_port_at_s", tuple(sorted(float(t) for t in self.drop_port_at_s)))
        object.__setattr__(self, "restart_clock_at_s", tuple(sorted(float(t) for t in self.restart_clock_at_s)))


@dataclass
class Event:
    """Bytes due at a recording time, or (``drop``) the port disappearing at that time."""

    time_s: float
    data: bytes = b""
    drop: bool = False


@dataclass
class StreamPlan:
    """What to send, what to send after every (re)connection, and the log of what was injected."""

    events: list[Event]
    preamble: bytes
    log: dict = field(default_factory=dict)


class _Framer:
    """Frames rows in one protocol and builds each kind of damaged frame."""

    def __init__(self, protocol: str, columns: Sequence[str], layout: LpBusLayout | None):
        self.protocol, self.columns, self.layout = protocol, list(columns), layout

    def frame(self, row: Mapping[str, float]) -> bytes:
        if self.protocol == "lpbus":
            return encode_lpbus(row, self.layout, sensor_id=self.layout.sensor_id or 1)
        return encode_csv_line(row, self.columns)

    def garbage(self, rng: np.random.Generator, max_bytes: int) -> bytes:
        n = int(rng.integers(1, max_bytes + 1))
        if self.protocol == "lpbus":
            values = rng.integers(0, 255, n)
            return bytes(int(v) + (v >= HEADER_BYTE) for v in values)  # 0..255 without 0x3A
        return bytes(int(v) for v in rng.integers(0x80, 0x100, n)) + b"\n"

    def corrupt(self, frame: bytes, rng: np.random.Generator) -> bytes:
        if self.protocol == "lpbus":
            damaged = bytearray(frame)
            damaged[-4] ^= int(rng.integers(1, 256))  # low byte of the LRC
            return bytes(damaged)
        cells = frame.decode().rstrip("\n").split(",")
        column = int(rng.integers(0, len(cells)))
        cells[column] = "x" + cells[column]
        return (",".join(cells) + "\n").encode()

    def truncate(self, frame: bytes, rng: np.random.Generator) -> bytes:
        if self.protocol == "lpbus":
            return frame[:int(rng.integers(HEADER_LEN, len(frame)))]
        cells = frame.decode().rstrip("\n").split(",")
        keep = int(rng.integers(1, len(cells)))
        return (",".join(cells[:keep]) + "\n").encode()


def plan_stream(columns: Mapping[str, np.ndarray], protocol: str = "lpbus", faults: FaultPlan | None = None,
                layout: LpBusLayout | None = None, csv_columns: Sequence[str] | None = None) -> StreamPlan:
    """Frame a recording, inject faults, and log what was injected.

    Parameters
    ----------
    columns
        The recording: ``time_s`` and the other columns, arrays (n,).
    protocol
        ``"lpbus"`` or ``"csv"``.
    faults
        What to inject; default none.
    layout
        LP-BUS layout (default ``LpBusLayout()``); its columns must be in ``columns``.
    csv_columns
        Columns of the CSV lines (default all of ``columns``, ``time_s`` first).

    Returns
    -------
    StreamPlan
        ``log`` has ``n_samples``, ``injected`` (counts by kind), ``expected_faults`` (counts by
        parser reason), ``good_indices`` (rows sent intact, in order) and ``out_of_range_indices``.
    """
    if protocol not in PROTOCOLS:
        raise ValueError(f"protocol must be one of {PROTOCOLS}, got {protocol!r}")
    faults = faults or FaultPlan()
    layout = layout or LpBusLayout()
    names = layout.columns if protocol == "lpbus" else list(csv_columns or
                                                             ["time_s", *(c for c in columns if c != "time_s")])
    missing = [c for c in names if c not in columns]
    if missing:
        raise ValueError(f"the recording lacks column(s) {missing} that the {protocol} framing needs")
    if protocol == "lpbus" and layout.precision == 16 and faults.nan_rate > 0:
        raise ValueError("16-bit LP-BUS cannot carry NaN: set faults.nan_rate=0")
    framer = _Framer(protocol, names, layout)
    # decisions (two draws a sample, whatever the rates) and content come from separate streams,
    # so which samples are hit does not move when a rate or a garbage length changes
    decide = np.random.default_rng([faults.seed, 0])
    rng = np.random.default_rng([faults.seed, 1])
    time_s = np.asarray(columns["time_s"], dtype=np.float64)
    injected = dict.fromkeys(["garbage", "corrupt", "truncate", "nan", "out_of_range", "gap", "port_drop", "new_clock"], 0)
    events: list[Event] = []
    good, out_of_range = [], []
    drops = list(faults.drop_port_at_s)
    restarts, clock_offsets, offset_s = list(faults.restart_clock_at_s), [], 0.0
    confirming: int | None = None  # the samples of a restarted clock the reader has seen, until it confirms it
    last_s: float | None = None  # the last time the reader took
    reopened = False  # the port was lost since: the reader takes a new clock at once
    previous_cut = False
    for index in range(len(time_s)):
        t_rel = float(time_s[index] - time_s[0])
        while drops and t_rel >= drops[0]:
            drops.pop(0)
            events.append(Event(float(time_s[index]), drop=True))
            injected["port_drop"] += 1
            reopened, confirming = True, None
        if restarts and t_rel >= restarts[0]:  # a replug: the port goes, the clock starts again
            while restarts and t_rel >= restarts[0]:
                restarts.pop(0)
            events.append(Event(float(time_s[index]), drop=True))
            injected["port_drop"] += 1
            reopened, confirming = True, None
            offset_s = -float(time_s[index])
            clock_offsets.append([index, offset_s])
        u_garbage, u_damage = decide.random(2)
        if any(start <= t_rel < start + length for start, length in faults.gap_s_at):
            injected["gap"] += 1
            continue
        row = {c: float(columns[c][index]) for c in names}
        row["time_s"] += offset_s
        is_oor = faults.out_of_range_every > 0 and (index + 1) % faults.out_of_range_every == 0
        if is_oor:
            row["temp_c"] = faults.out_of_range_temp_c
        if u_garbage < faults.garbage_rate and not previous_cut:
            events.append(Event(float(time_s[index]), framer.garbage(rng, faults.garbage_max_bytes)))
            injected["garbage"] += 1
        kind = _damage_kind(u_damage, faults)
        if kind == "nan":
            row["gyro_x_dps"] = math.nan
        frame = framer.frame(row)
        if kind == "corrupt":
            frame = framer.corrupt(frame, rng)
        elif kind == "truncate":
            frame = framer.truncate(frame, rng)
        previous_cut = kind == "truncate"
        events.append(Event(float(time_s[index]), frame))
        if kind is None:  # a sample the time check sees: a new clock (a replug, or the recording's own) is confirmed
            step_s = math.nan if last_s is None else row["time_s"] - last_s
            if confirming is None and (step_s < -RESTART_BACK_S or step_s > RESTART_JUMP_S) and not reopened:
                confirming = 0
            if confirming is not None:
                confirming += 1
                if confirming < CONFIRM_SAMPLES:
                    injected["new_clock"] += 1
                    continue
                confirming = None
            last_s, reopened = row["time_s"], False
        if kind is None:
            good.append(index)
            if is_oor:
                out_of_range.append(index)
                injected["out_of_range"] += 1
        else:
            injected[kind] += 1
    preamble = encode_csv_header(names) if protocol == "csv" else b""
    expected = {reason: injected[kind] for kind, reason in EXPECTED_REASON[protocol].items() if injected[kind]}
    log = {"protocol": protocol, "columns": names, "n_samples": int(len(time_s)), "seed": faults.seed,
           "injected": injected, "expected_faults": dict(sorted(expected.items())),
           "good_indices": good, "out_of_range_indices": out_of_range, "clock_offsets_s": clock_offsets}
    return StreamPlan(events, preamble, log)


def _damage_kind(u: float, faults: FaultPlan) -> str | None:
    """Which damage (if any) a uniform draw ``u`` picks: corrupt, truncate and nan are exclusive."""
    edges = np.cumsum([faults.corrupt_rate, faults.truncate_rate, faults.nan_rate])
    for kind, edge in zip(("corrupt", "truncate", "nan"), edges):
        if u < edge:
            return kind
    return None
