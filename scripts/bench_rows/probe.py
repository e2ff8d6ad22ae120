"""Run scripts/stream.py or scripts/emulate_sensor.py with timing hooks; the ``stream_pty`` row starts it.

    python scripts/bench_rows/probe.py stream OUT.npz scripts/stream.py model=... port=... ...
    python scripts/bench_rows/probe.py stream_per_sample OUT.npz scripts/stream.py model=... port=... ...
    python scripts/bench_rows/probe.py emulate OUT.npz scripts/emulate_sensor.py input=... ...

The library has no per-sample timing hook, so this wraps methods from outside (the library is not
changed) and then runs the script as ``__main__``. Times are ``time.perf_counter()``, which on
Linux is CLOCK_MONOTONIC, one clock for both processes.

stream: ``parser.feed`` (the bytes of a read were just taken: its samples are stamped with that
time, and the first one starts the CPU clock), ``Compensator.process`` (and ``process_row``, a lone
frame), ``LiveWriter.write`` (and ``write_rows``: the output rows are written and flushed: the
latency of each sample in them ends; the last one stops the CPU clock, which gives the CPU time the
stream used whatever else ran on its core), ``LiveAllan.add_many`` (and ``add``) and ``LiveAllan.report`` (the last report, which ``finish`` makes after the
stream stopped, is kept apart); RSS every 1000 rows. The per-sample arrays are allocated and
touched before the script starts (``max_samples=`` sizes them), so the probe's own memory does not
show up as growth of the stream's RSS.
stream_per_sample: the same, with every read's chunk split into chunks of one sample, so each
sample has its own ``Compensator.process`` call and write: the loop as it was before chunks, the
reference that the chunked loop is compared with.
stream_per_line: the same as stream, with the CSV flood path off (``LineRun.decode`` finds no run), so
every CSV line goes through the per-line parser: the reference the CSV flood path is compared with.
emulate: ``PtySensor.write`` (the frame's last byte is in the kernel).
"""
from __future__ import annotations

import collections
import itertools
import json
import os
import runpy
import sys
import time
from array import array
from typing import Any, Callable

import numpy as np

RSS_EVERY = 1000


def _rss_mb() -> float:
    with open("/proc/self/statm") as handle:
        return int(handle.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 1e6


def _wrap(owner: Any, name: str, around: Callable) -> None:
    original = getattr(owner, name)
    setattr(owner, name, lambda *args, **kwargs: around(original, *args, **kwargs))


class StreamProbe:
    """Per-sample read and write times, time per stage, Allan report durations, RSS."""

    def __init__(self, capacity: int, per_sample: bool = False) -> None:
        import gyronet.deploy.stream.live as live
        from gyronet.bundle.compensator import Compensator
        from gyronet.deploy.stream import lpbus_setup
        from gyronet.deploy.stream.events import Fault, n_samples

        self.read_at: collections.deque[float] = collections.deque()
        # reports: LiveAllan.report durations between samples; final_report: the one finish() makes
        # np.full writes every element: the pages are resident now, not as the samples arrive
        self.latency, self.written_at = np.full(capacity, np.nan), np.full(capacity, np.nan)
        self.n_written = 0
        self.reports = array("d")
        self.chunk_rows = array("l")  # rows per LiveWriter.write: the chunk sizes
        self.final_report = float("nan")
        self.finishing = False
        self.stage = dict.fromkeys(["parse", "process", "write", "allan_add"], 0.0)
        self.rss: list[tuple[int, float, float]] = [(0, time.perf_counter(), _rss_mb())]
        self.first_read: float | None = None
        self.first_read_cpu = self.last_write_cpu = float("nan")  # process CPU time, s: the load-free cost
        perf = time.perf_counter

        def make_parser(original, *args, **kwargs):
            parser = original(*args, **kwargs)
            feed = parser.feed

            def timed_feed(data: bytes):
                start = perf()
                if self.first_read is None:
                    self.first_read, self.first_read_cpu = start, time.process_time()
                items = feed(data)
                self.stage["parse"] += perf() - start
                for item in items:  # a block (the LP-BUS flood path) stands for its samples
                    if not isinstance(item, Fault):
                        self.read_at.extend(itertools.repeat(start, n_samples(item)))
                return items

            parser.feed = timed_feed
            return parser

        def timed(key: str) -> Callable:
            def around(original, *args, **kwargs):
                start = perf()
                result = original(*args, **kwargs)
                self.stage[key] += perf() - start
                return result
            return around

        def write(original, writer, *args, **kwargs):
            before = writer.n_rows
            start = perf()
            original(writer, *args, **kwargs)
            done = perf()
            self.stage["write"] += done - start
            self.chunk_rows.append(writer.n_rows - before)
            self.last_write_cpu = time.process_time()
            for _ in range(writer.n_rows - before):
                i, self.n_written = self.n_written, self.n_written + 1
                self.written_at[i] = done
                self.latency[i] = done - self.read_at.popleft() if self.read_at else float("nan")
            if before == 0 or writer.n_rows // RSS_EVERY > before // RSS_EVERY:
                self.rss.append((writer.n_rows, done, _rss_mb()))

        def report(original, *args, **kwargs):
            start = perf()
            result = original(*args, **kwargs)
            if self.finishing:
                self.final_report = perf() - start
            else:
                self.reports.append(perf() - start)
            return result

        def finish(original, *args, **kwargs):
            self.finishing = True
            return original(*args, **kwargs)

        _wrap(live, "make_parser", make_parser)
        _wrap(lpbus_setup.LpBusStart, "parser", make_parser)  # the LP-BUS parser once the set-up has run
        _wrap(Compensator, "process", timed("process"))
        _wrap(Compensator, "process_row", timed("process"))  # a lone frame in plain floats
        _wrap(live.LiveWriter, "write", write)
        _wrap(live.LiveWriter, "write_rows", write)
        _wrap(live.LiveAllan, "add_many", timed("allan_add"))
        _wrap(live.LiveAllan, "add", timed("allan_add"))
        if per_sample:
            _wrap(live, "read_chunks", _one_item_chunks)
        _wrap(live.LiveAllan, "report", report)
        _wrap(live.LiveAllan, "finish", finish)

    def save(self, path: str) -> None:
        meta = {"stage_s": self.stage, "first_read": self.first_read, "unwritten": len(self.read_at),
                "cpu_s": self.last_write_cpu - self.first_read_cpu,
                "final_report_s": self.final_report}
        n = self.n_written
        np.savez(path, latency=self.latency[:n], written_at=self.written_at[:n],
                 reports=np.asarray(self.reports), rss=np.asarray(self.rss), chunk_rows=np.asarray(self.chunk_rows),
                 meta=np.array(json.dumps(meta)))


def _one_item_chunks(original, *args, **kwargs):
    from gyronet.deploy.stream.events import as_samples

    chunks = original(*args, **kwargs)
    try:
        for chunk in chunks:
            for item in as_samples(chunk):
                yield [item]
    finally:
        chunks.close()  # closes the port


class EmulateProbe:
    """The time each non-empty write to the pty returned."""

    def __init__(self) -> None:
        from gyronet.deploy.stream.pty_sensor import PtySensor

        self.sent_at, self.sizes = array("d"), array("l")

        def write(original, sensor, data: bytes):
            original(sensor, data)
            if data:
                self.sent_at.append(time.perf_counter())
                self.sizes.append(len(data))

        _wrap(PtySensor, "write", write)

    def save(self, path: str) -> None:
        np.savez(path, sent_at=np.asarray(self.sent_at), sizes=np.asarray(self.sizes))


def main() -> int:
    mode, out_path, script, *overrides = sys.argv[1:]
    sys.path.pop(0)  # this folder: its modules must not shadow anything the script imports
    sizes = [int(o.split("=", 1)[1]) for o in overrides if o.startswith("max_samples=")]
    capacity = sizes[-1] if sizes else 10_000_000
    probe = StreamProbe(capacity, mode == "stream_per_sample") if mode.startswith("stream") else EmulateProbe()
    if mode == "stream_per_line":
        from gyronet.deploy.stream.csv_run import LineRun

        LineRun.decode = lambda run, buffer, position, check: (None, 0, len(buffer))
    sys.argv = [script, *overrides]
    code: Any = 0
    try:
        runpy.run_path(script, run_name="__main__")
    except SystemExit as stop:
        code = stop.code or 0
    finally:
        probe.save(out_path)
    return code if isinstance(code, int) else 1


if __name__ == "__main__":
    sys.exit(main())
