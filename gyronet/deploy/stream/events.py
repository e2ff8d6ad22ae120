"""What a framing parser yields: a good ``Sample`` (or a ``SampleBlock`` of them) or a ``Fault``; a ``FaultCounter``.

Both framings (LP-BUS and CSV lines) share the checks that do not depend on the framing: every
value finite, time strictly increasing, a restarted sensor clock seen as a new segment
(``SampleCheck``).
"""
from __future__ import annotations

import logging
import math
from collections import Counter
from dataclasses import dataclass, field
from typing import Iterable, Mapping, NamedTuple

import numpy as np

from gyronet.recordings.guard import CONFIRM_SAMPLES

# Every reason a Fault can carry, with what it means. Parsers and the reader use only these.
FAULT_REASONS: dict[str, str] = {
    "garbage": "bytes that are not part of any frame or line (skipped up to the next header)",
    "bad_checksum": "LP-BUS frame whose LRC does not match its bytes",
    "bad_footer": "LP-BUS frame whose LRC matches but that does not end in 0x0D 0x0A",
    "truncated": "frame or line cut short: the next one starts inside it, or the stream ended in it",
    "bad_length": "LP-BUS sensor-data frame whose length does not fit the configured fields",
    "nan": "a value is NaN or infinite",
    "bad_field_count": "CSV line with more cells than the header",
    "non_numeric": "CSV cell that is not a number",
    "no_header": "CSV line before any header line",
    "bad_header": "CSV header line that lacks a column the consumer needs, or that no sample line fits"
                  " (the previous header stays)",
    "time_not_increasing": "time_s not after the previous good sample's (back by at most the restart threshold)",
    "time_jump": "time_s far from the clock's (a restart not yet confirmed, or one stamp corrupted)",
    "port_lost": "the serial port failed or disappeared (the reader reopens it)",
}

EXCERPT_BYTES = 32
RESTART_BACK_S, RESTART_JUMP_S = 1.0, 3600.0  # SampleCheck's defaults: steps of the clock that are a new clock

log = logging.getLogger(__name__)


class Sample(NamedTuple):
    """One good sample (a named tuple: a live stream makes tens of thousands a second).

    Attributes
    ----------
    time_s
        Sample time, s.
    values
        Every other channel by its CONTRACT.md column name (``temp_c``, ``gyro_x_dps``, ...).
    new_segment
        The sensor clock restarted (or jumped) before this sample: it starts a new segment, and
        a consumer restarts whatever state it keeps across samples.
    """

    time_s: float
    values: Mapping[str, float]
    new_segment: bool = False

    def row(self) -> dict[str, float]:
        """``time_s`` and the values as one dict of columns."""
        return {"time_s": self.time_s, **self.values}


class SampleBlock:
    """Good samples in a row as columns, for a consumer that asked for them (the LP-BUS and CSV flood paths).

    What a run of ``Sample`` objects would hold, without one object per sample; ``samples()``
    gives those objects. A block never starts a new segment (a restart goes sample by sample).

    Attributes
    ----------
    columns
        ``time_s`` and every other channel by column name: float64 arrays of equal length.
    """

    __slots__ = ("columns",)
    new_segment = False

    def __init__(self, columns: dict[str, np.ndarray]):
        self.columns = columns

    def __len__(self) -> int:
        return len(self.columns["time_s"])

    def samples(self) -> list[Sample]:
        """The same samples one ``Sample`` each, as the per-frame path makes them."""
        names = list(self.columns)[1:]
        values = zip(*(self.columns[name].tolist() for name in names))
        return [Sample(time_s, dict(zip(names, row))) for time_s, row in zip(self.columns["time_s"].tolist(), values)]

    def cut(self, stop: int) -> "SampleBlock":
        """The first ``stop`` samples."""
        return SampleBlock({name: values[:stop] for name, values in self.columns.items()})


def n_samples(item: Sample | SampleBlock) -> int:
    """How many samples ``item`` stands for: a block its length, a ``Sample`` one."""
    return len(item) if isinstance(item, SampleBlock) else 1


def as_samples(items: Iterable[Sample | SampleBlock | Fault]) -> list[Sample | Fault]:
    """``items`` with each block taken apart into its samples."""
    out: list[Sample | Fault] = []
    for item in items:
        if isinstance(item, SampleBlock):
            out += item.samples()
        else:
            out.append(item)
    return out


@dataclass(frozen=True)
class Fault:
    """Something in the stream that is not a good sample.

    Attributes
    ----------
    reason
        One of ``FAULT_REASONS``.
    raw
        An excerpt (at most ``EXCERPT_BYTES``) of the offending bytes, for the log.
    detail
        A few words for a person (which cell, which value).
    """

    reason: str
    raw: bytes = b""
    detail: str = ""

    def __post_init__(self) -> None:
        if self.reason not in FAULT_REASONS:
            raise ValueError(f"unknown fault reason {self.reason!r}")
        if len(self.raw) > EXCERPT_BYTES:
            object.__setattr__(self, "raw", bytes(self.raw[:EXCERPT_BYTES]))

    def __str__(self) -> str:
        extra = f" ({self.detail})" if self.detail else ""
        return f"{self.reason}{extra}: {self.raw.hex(' ')}" if self.raw else f"{self.reason}{extra}"


@dataclass
class FaultCounter:
    """Counts faults by reason (and good samples), for the end-of-run summary."""

    counts: Counter = field(default_factory=Counter)
    n_samples: int = 0

    def add(self, item: Sample | SampleBlock | Fault) -> None:
        """Count one parser output."""
        if isinstance(item, Fault):
            self.counts[item.reason] += 1
        else:
            self.n_samples += n_samples(item)

    def update(self, items: Iterable[Sample | Fault]) -> None:
        """Count several parser outputs."""
        for item in items:
            self.add(item)

    @property
    def n_faults(self) -> int:
        return int(sum(self.counts.values()))

    def as_dict(self) -> dict[str, int]:
        """Fault counts by reason, the reasons sorted, zero counts left out."""
        return {reason: int(self.counts[reason]) for reason in sorted(self.counts) if self.counts[reason]}

    def summary(self) -> str:
        """One line: good samples, then faults by reason."""
        faults = ", ".join(f"{k}={v}" for k, v in self.as_dict().items()) or "none"
        return f"{self.n_samples} good samples; faults: {faults}"


class SampleCheck:
    """The framing-independent checks: finite values, strictly increasing time, clock restarts.

    Keeps the time of the last good sample, across reconnections, so a replayed or stale sample
    (time back by at most ``restart_back_s``) is refused. A sensor replugged with its clock
    restarted sends times far before the last one: rather than refusing every sample until the
    new clock passes the old one, a step back of more than ``restart_back_s``, or forward of more
    than ``restart_jump_s``, starts a new segment (``Sample.new_segment``; counted in
    ``n_restarts``) once the new clock is confirmed: ``CONFIRM_SAMPLES`` samples in a row that
    follow one another and not the old clock (as many as the temperature guard needs to confirm a
    step; not its 2 s as well, which would be 2000 samples at 1 kHz). Until then they are
    ``time_jump`` faults, and a sample that continues the old clock drops them: one corrupted stamp
    is one lost sample, not a restart whose start-up window would close on that sample. Right after
    the port was lost and reopened (``reopened``: a replug, a power cycle), the first sample's new
    clock is taken at once.

    Parameters
    ----------
    restart_back_s
        Largest step back in time that is a stale sample, not a restarted clock, s.
    restart_jump_s
        Largest step forward that is a gap in the same clock, s (None: any).
    """

    def __init__(self, restart_back_s: float = RESTART_BACK_S, restart_jump_s: float | None = RESTART_JUMP_S) -> None:
        self.restart_back_s = float(restart_back_s)
        self.restart_jump_s = None if restart_jump_s is None else float(restart_jump_s)
        self.last_time_s: float | None = None
        self.n_restarts = 0
        self._new_clock: list[float] | None = None  # a restart being confirmed: [first time, last time, samples]
        self._reopened = False

    def reopened(self) -> None:
        """The port was lost and reopened: the next sample may start a new clock at once."""
        self._reopened, self._new_clock = True, None

    def check(self, time_s: float, values: Mapping[str, float], raw: bytes = b"") -> Sample | Fault:
        """A ``Sample`` when the values pass, else the ``Fault`` that says why."""
        # one test in the usual case: the sum of finite values is finite, unless it overflows
        if not math.isfinite(time_s + sum(values.values())):
            for name, value in (("time_s", time_s), *values.items()):
                if not math.isfinite(value):
                    return Fault("nan", raw, f"{name}={value}")
        last = self.last_time_s
        new_segment = False
        if last is not None and not (last < time_s and (self.restart_jump_s is None
                                                        or time_s - last <= self.restart_jump_s)):
            if time_s <= last and last - time_s <= self.restart_back_s:  # stale, or a repeat: never a new clock
                return Fault("time_not_increasing", raw, f"time_s={time_s!r} after {last!r}")
            clock = self._new_clock
            if clock is None or not time_s > clock[1]:  # not the clock being confirmed going on: a new candidate
                clock = self._new_clock = [time_s, time_s, 0]
            clock[1], clock[2] = time_s, clock[2] + 1
            if clock[2] < CONFIRM_SAMPLES and not self._reopened:
                return Fault("time_jump", raw, f"time_s={time_s!r} after {last!r} (a new clock? {clock[2]} so far)")
            new_segment = True
            self.n_restarts += 1
            log.warning("sensor clock restarted (time_s from %r after %r): a new segment", clock[0], last)
        self.took(time_s)
        return Sample(float(time_s), dict(values), new_segment)

    def took(self, time_s: float) -> None:
        """A sample of the current clock was taken at ``time_s`` (also by a flood path): no restart is pending."""
        self.last_time_s, self._new_clock, self._reopened = float(time_s), None, False

    def times_ok(self, time_s: np.ndarray) -> np.ndarray:
        """Where ``check`` would take each time of a run as the next of the same clock (a flood path's time check).

        Each time after the one before it (the first after ``last_time_s``), by at most ``restart_jump_s``;
        ``last_time_s`` is not moved.
        """
        if self._new_clock is not None:  # a restart being confirmed: the sample by sample path decides
            return np.zeros(len(time_s), dtype=bool)
        previous = np.empty_like(time_s)
        previous[1:] = time_s[:-1]
        previous[0] = time_s[0] if self.last_time_s is None else self.last_time_s
        ok = time_s > previous
        if self.restart_jump_s is not None:
            ok &= ~(time_s - previous > self.restart_jump_s)
        ok[0] |= self.last_time_s is None  # the first time ever: nothing to compare with
        return ok


def leading(ok: np.ndarray) -> int:
    """How many of ``ok`` are True before the first False."""
    return len(ok) if ok.all() else int(np.argmin(ok))
