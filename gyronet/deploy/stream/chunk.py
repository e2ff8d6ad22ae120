"""The live loop's compute and write step: good samples through the compensator a chunk at a time.

A chunk is every good sample that one read of the port completed (one sample when frames arrive
one by one, hundreds in a flood). It goes through ``Compensator.process`` in one call, is written
in one ``os.write`` and enters the live Allan monitor in one step, so a flood costs one model
call per read instead of one per sample, and a lone frame is still answered at once. A chunk of
at most ``SMALL_ROWS`` samples (a lone frame at 1 kHz, a short backlog) goes sample by sample in
plain floats instead (``Compensator.process_row``, ``gyronet.model.small_model``): there the fixed cost
of each array and TorchScript call, not the arithmetic, was the time (343 us of CPU a frame). The
compensator keeps its state across calls, so the numbers equal ``compensate.py`` on the same
samples however they were chunked. A chunk is split where the sensor clock restarted (the filters
restart there) and where the start-up window ends (so that motion in the window stops the run
after the window's rows are written, as when each sample went on its own). A flood's frames come
as blocks of columns (``SampleBlock``, the LP-BUS and CSV parsers' fast paths), which go to the
compensator without a ``Sample`` object each.
"""
from __future__ import annotations

import logging
from typing import Sequence

import numpy as np

from gyronet.bundle.compensator import Compensator
from gyronet.model.small_model import SMALL_ROWS
from gyronet.deploy.stream.events import Sample, SampleBlock, as_samples, n_samples
from gyronet.deploy.stream.live_allan import LiveAllan
from gyronet.deploy.stream.live_recal import LiveRecalibration
from gyronet.deploy.stream.output import LiveWriter

log = logging.getLogger(__name__)

RATE_PROBE_SAMPLES = 20  # samples held at the start to measure the stream's rate (a median of their intervals)


class RateGate:
    """Hold a stream's first samples until its rate is known, then check it against the bundle's.

    ``compensate.py`` checks a file's rate before its first sample; the live path cannot know the
    rate before it has seen a few, so it holds them (``n_samples``: a 2 s delay at 10 Hz, once) and
    then releases them in order. The median interval ignores lost frames and clock restarts.
    """

    def __init__(self, compensator: Compensator, resample: bool, source: str, n_samples: int = RATE_PROBE_SAMPLES):
        self.compensator, self.resample, self.source = compensator, bool(resample), source
        self.n_samples = max(1, int(n_samples))
        self.held: list[Sample] | None = []  # None once the rate is checked

    def push(self, sample: Sample | SampleBlock) -> list[Sample | SampleBlock]:
        """The samples ready to compensate after ``sample`` (or a block of them) arrived."""
        if self.held is None:
            return [sample]
        if isinstance(sample, SampleBlock):
            return [ready for one in sample.samples() for ready in self.push(one)]
        self.held.append(sample)
        return self.flush() if len(self.held) >= self.n_samples else []

    def flush(self) -> list[Sample]:
        """Check the rate on what is held (if two samples or more) and release them."""
        held, self.held = self.held or [], None
        intervals_s = [b.time_s - a.time_s for a, b in zip(held, held[1:]) if not b.new_segment and b.time_s > a.time_s]
        if intervals_s:
            fs_hz = 1.0 / float(np.median(intervals_s))
            self.compensator.use_input_rate(fs_hz, self.resample, f"{self.source} (over its first {len(held)} samples)")
            self.compensator.rate_source = self.source  # what a later rate change is said of: the whole stream
        return held


class ChunkWriter:
    """Compensate good samples in chunks and write them; counts what the run summary reports.

    Parameters
    ----------
    compensator
        The bundle's compensator, reset for the stream's start.
    out
        The output CSV.
    allan
        The live Allan monitor (None: none).
    recalibration
        The live recalibration check (None: none).
    port
        The port's name, for messages.
    max_samples
        Rows after which the run stops (None: no limit); a chunk is cut there.
    """

    def __init__(self, compensator: Compensator, out: LiveWriter, allan: LiveAllan | None, port: str,
                 max_samples: int | None = None, recalibration: LiveRecalibration | None = None):
        self.compensator, self.out, self.allan, self.port = compensator, out, allan, port
        self.recalibration = recalibration
        self.max_samples = max_samples
        self.columns = list(dict.fromkeys(["time_s", "temp_c", *compensator.input_columns]))
        self.n_out_of_range = 0
        self._outside_s: float | None = None  # the last sample outside the trained range
        self.clock_restarts = 0

    @property
    def full(self) -> bool:
        """True once ``max_samples`` rows are out."""
        return self.max_samples is not None and self.out.n_rows >= self.max_samples

    def write(self, samples: Sequence[Sample | SampleBlock]) -> bool:
        """Compensate and write ``samples`` (in stream order); True once ``max_samples`` rows are out."""
        if self.max_samples is not None:
            samples = first_rows(samples, max(0, self.max_samples - self.out.n_rows))
        starts = [i for i, sample in enumerate(samples) if i == 0 or sample.new_segment]
        for start, stop in zip(starts, [*starts[1:], len(samples)]):
            self._segment(samples[start:stop])
        return self.full

    def _segment(self, samples: Sequence[Sample | SampleBlock]) -> None:
        """Samples of one sensor clock: the first may start a new segment, none of the others does."""
        first = samples[0]
        if self.out.n_rows == 0:
            self.compensator.check_columns(first.columns if isinstance(first, SampleBlock) else first.row(),
                                           source=f"{self.port}: the stream")
        if first.new_segment:
            # the sensor restarted: so do the filters (from a clean state, never from the old one)
            self.compensator.reset()
            self.clock_restarts += 1
            if self.allan is not None:
                self.allan.new_segment(first.time_s)
            if self.recalibration is not None:
                self.recalibration.new_segment(first.time_s)
        done = 0
        if n_rows(samples) <= SMALL_ROWS:
            samples = as_samples(samples)
            done = self._in_floats(samples)
            if done == len(samples):
                return
        if len(samples) == 1 and isinstance(samples[0], SampleBlock):  # a flood's chunk: its columns as they are
            columns = {name: samples[0].columns[name] for name in self.columns}
        else:
            columns = self._columns(samples[done:])
        split, n = self._startup_end(columns["time_s"]), len(columns["time_s"])
        for rows in (slice(0, split), slice(split, n)):
            if rows.stop > rows.start:
                self._compensate({name: values[rows] for name, values in columns.items()})

    def _columns(self, samples: Sequence[Sample | SampleBlock]) -> dict[str, np.ndarray]:
        """The compensator's columns of ``samples``, blocks and lone samples in stream order."""
        pieces: list[dict[str, np.ndarray]] = []
        lone: list[Sample] = []
        for sample in [*samples, None]:
            if isinstance(sample, Sample):
                lone.append(sample)
                continue
            if lone:
                pieces.append({"time_s": np.array([one.time_s for one in lone]),
                               **{name: np.array([one.values[name] for one in lone]) for name in self.columns[1:]}})
                lone = []
            if sample is not None:
                pieces.append(sample.columns)
        return {name: np.concatenate([piece[name] for piece in pieces]) for name in self.columns}

    def _in_floats(self, samples: Sequence[Sample]) -> int:
        """A few frames (a lone one, a short backlog) in plain floats (``Compensator.process_row``), written in one
        go; returns how many: it stops at the first where that does not apply (the rest go as arrays)."""
        rows = []
        for sample in samples:  # never in an open start-up window: process_row leaves those to process
            row = self.compensator.process_row(sample.time_s, sample.values)
            if row is None:
                break
            temp_c = sample.values["temp_c"]
            rows.append((sample.time_s, row.rate_dps, temp_c, row.out_of_range, row.bad_input, row.drift_sigma_dps))
            if row.out_of_range:
                self._out_of_range([temp_c], [sample.time_s])
        if rows:
            self.out.write_rows(rows)
            if self.allan is not None:
                for time_s, rate_dps, *_ in rows:
                    self.allan.add(time_s, rate_dps)
            if self.recalibration is not None:
                for time_s, rate_dps, _, out_of_range, _, sigma_dps in rows:
                    self.recalibration.add(time_s, rate_dps, sigma_dps, out_of_range)
        return len(rows)

    def _startup_end(self, time_s: np.ndarray) -> int:
        """How many of these samples fall in a start-up window still open (0 when none is)."""
        startup = self.compensator.startup
        if startup is None or startup.done:
            return 0
        start_s = startup.start_time_s if startup.start_time_s is not None else time_s[0]
        return int(np.count_nonzero(time_s - start_s < startup.still_s))

    def _compensate(self, columns: dict[str, np.ndarray]) -> None:
        in_window = self._startup_end(columns["time_s"])  # before process, which may close the window
        result = self.compensator.process(columns)
        self.out.write(columns["time_s"], columns["temp_c"], result)
        flagged = np.flatnonzero(result.out_of_range)
        if len(flagged):
            self._out_of_range(columns["temp_c"][flagged].tolist(), columns["time_s"][flagged].tolist())
        if self.allan is not None:
            self.allan.add_many(columns["time_s"][in_window:], result.rate_dps[in_window:])
        if self.recalibration is not None:
            self.recalibration.add_many(columns["time_s"], result.rate_dps, result.drift_sigma_dps, result.out_of_range)

    def _out_of_range(self, temp_c: Sequence[float], time_s: Sequence[float]) -> None:
        """Count the samples outside the trained range; warn once an excursion (a minute apart), each at debug level."""
        self.n_out_of_range += len(temp_c)
        debug = log.isEnabledFor(logging.DEBUG)
        for temp, time in zip(temp_c, time_s):
            if self._outside_s is None or not 0.0 <= time - self._outside_s < 60.0:  # a new excursion (or clock)
                low, high = self.compensator.temp_range_c
                log.warning("%s: temp_c=%.3f degC at %.3f s is outside the trained range (%.2f .. %.2f degC): flagged "
                            "out_of_range, the model holds its edge value; the rest of this excursion is counted in "
                            "the summary", self.port, temp, time, low, high)
            elif debug:
                log.debug("temp_c=%.3f at %.3f s outside the trained range", temp, time)
            self._outside_s = time


def n_rows(samples: Sequence[Sample | SampleBlock]) -> int:
    """How many samples ``samples`` holds, a block counting its length."""
    return sum(map(n_samples, samples))


def first_rows(samples: Sequence[Sample | SampleBlock], stop: int) -> list[Sample | SampleBlock]:
    """The first ``stop`` samples of ``samples``, a block cut where they end."""
    out: list[Sample | SampleBlock] = []
    for sample in samples:
        if stop <= 0:
            break
        if isinstance(sample, SampleBlock) and len(sample) > stop:
            sample = sample.cut(stop)
        out.append(sample)
        stop -= n_samples(sample)
    return out
