"""The live path: a sensor stream's good samples through a compensator bundle into a CSV.

Each good sample goes through ``Compensator.process`` as it arrives, the same causal code the
offline path runs on a whole file, so the output equals ``compensate.py`` on the good samples.
The output has the offline columns (``time_s``, compensated ``gyro_*_dps``, ``temp_c``,
``out_of_range``) and is flushed after every sample. Faults are counted by reason; the Allan terms
of the compensated rate (N and B per axis) go to TensorBoard every ``allan_every_s`` of data, and
the Allan curves as a figure when the run stops.
"""
from __future__ import annotations

import json
import logging
import math
import time
from pathlib import Path
from typing import Any, Mapping, TextIO

import numpy as np

from gyronet.compensator import Compensated, Compensator
from gyronet.data import AXES
from gyronet.errors import GyronetError
from gyronet.offline import output_columns
from gyronet.stream import FaultCounter, LpBusLayout, Sample, make_parser, read_samples

log = logging.getLogger(__name__)


def output_names() -> list[str]:
    """The columns of a compensated file, in the offline writer's order."""
    empty = Compensated(np.empty((0, 3)), np.empty((0, 3)), np.empty(0, dtype=bool))
    return list(output_columns(np.empty(0), np.empty(0), empty))


class LiveWriter:
    """The output CSV, one line per compensated sample, flushed each time."""

    def __init__(self, path: str | Path, bundle_dir: str | Path):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.names = output_names()
        self._file: TextIO = open(self.path, "w", encoding="utf-8", newline="")
        self._file.write(f"# compensated_by={Path(bundle_dir).resolve()}\n" + ",".join(self.names) + "\n")
        self._file.flush()
        self.n_rows = 0

    def write(self, time_s: float, temp_c: float, out: Compensated) -> None:
        """Write the compensated samples of ``out`` (here one) and flush."""
        columns = output_columns(np.atleast_1d(time_s), np.atleast_1d(temp_c), out)
        for row in range(len(columns["time_s"])):
            self._file.write(",".join(repr(_plain(columns[n][row])) for n in self.names) + "\n")
            self.n_rows += 1
        self._file.flush()

    def close(self) -> None:
        self._file.close()


def _plain(value: Any) -> float | int:
    return int(value) if isinstance(value, (np.integer, np.bool_)) else float(value)


class LiveAllan:
    """Allan noise terms of the compensated rate, computed every ``every_s`` seconds of data.

    Parameters
    ----------
    writer
        A TensorBoard ``SummaryWriter`` (None: compute, log, keep the last report only).
    every_s
        Data seconds between reports.
    fs_hz
        Sampling rate of the stream, Hz.
    """

    def __init__(self, writer: Any, every_s: float, fs_hz: float, bin_s: float | None = None,
                 max_history_s: float = 86400.0):
        self.writer, self.every_s, self.fs_hz = writer, float(every_s), float(fs_hz)
        # Samples are averaged into bins of at least 0.1 s, so a 1 kHz stream keeps 10 values a
        # second, not 1000: memory stays flat-ish (~1 MB/h) and a report takes milliseconds. The
        # Allan deviation at taus of whole bins is unchanged in expectation.
        self.bin_s = max(1.0 / self.fs_hz, 0.1) if bin_s is None else float(bin_s)
        self.max_bins = max(16, int(max_history_s / self.bin_s))
        self._time_s = np.empty(1024)
        self._rate_dps = np.empty((1024, 3))
        self._n = 0
        self._start_s: float | None = None
        self._bin = -1
        self._sum = np.zeros(3)
        self._count = 0
        self.next_s: float | None = None
        self.last: dict[str, dict[str, float]] = {}

    @property
    def time_s(self) -> np.ndarray:
        """Mid-times of the completed bins, s."""
        return self._time_s[:self._n]

    @property
    def rate_dps(self) -> np.ndarray:
        """Mean compensated rate of each completed bin, (n, 3), deg/s."""
        return self._rate_dps[:self._n]

    def add(self, time_s: float, rate_dps: np.ndarray) -> None:
        """Add a sample; report when ``every_s`` of data has passed since the last report."""
        if self._start_s is None:
            self._start_s = float(time_s)
            self.next_s = time_s + self.every_s
        # bin edges half a sample before the nominal ones: a sample on a regular grid never falls
        # on an edge, where float rounding would put two samples in one bin and none in the next
        index = int((time_s - self._start_s + 0.5 / self.fs_hz) // self.bin_s)
        if index != self._bin:
            self._close_bin()
            self._bin = index
        self._sum += np.asarray(rate_dps, dtype=np.float64).reshape(3)
        self._count += 1
        if time_s >= self.next_s:
            self.report(step=int(round(time_s - self._start_s)))
            self.next_s = time_s + self.every_s

    def _close_bin(self) -> None:
        if self._count == 0:
            return
        if self._n == len(self._time_s):
            if self._n >= self.max_bins:  # keep the newest half of the history
                keep = self._n // 2
                self._time_s[:keep] = self._time_s[self._n - keep:self._n]
                self._rate_dps[:keep] = self._rate_dps[self._n - keep:self._n]
                self._n = keep
            else:
                self._time_s = np.resize(self._time_s, 2 * self._n)
                self._rate_dps = np.resize(self._rate_dps, (2 * self._n, 3))
        self._time_s[self._n] = self._start_s + (self._bin + 0.5) * self.bin_s
        self._rate_dps[self._n] = self._sum / self._count
        self._n += 1
        self._sum[:] = 0.0
        self._count = 0

    def report(self, step: int, figure: bool = False) -> None:
        """Compute N and B per axis on everything so far and log them (and the curves, if asked)."""
        from gyronet.allan import allan_report, plot_allan

        try:
            report = allan_report(self.time_s, self.rate_dps, 1.0 / self.bin_s)
        except GyronetError as err:  # too short so far
            log.debug("no Allan report yet: %s", err)
            return
        self.last = {axis: {"arw_deg_rthr": _finite_or_none(report[axis]["arw_deg_rthr"]),
                            "bias_instability_deg_hr": _finite_or_none(report[axis]["bias_instability_deg_hr"])}
                     for axis in AXES}
        log.info("Allan at %d s of data: %s", step, ", ".join(
            f"{axis}: N={_number(v['arw_deg_rthr'])} deg/rt-h B={_number(v['bias_instability_deg_hr'])} deg/h"
            for axis, v in self.last.items()))
        if self.writer is None:
            return
        for axis, values in self.last.items():
            for name, tag in (("arw_deg_rthr", "arw"), ("bias_instability_deg_hr", "bias_instability")):
                if values[name] is not None:
                    self.writer.add_scalar(f"allan/{tag}_{axis}", values[name], step)
        if figure:  # drawing takes a second or more: once, at the end, not between samples
            from gyronet.tb import log_figure

            log_figure(self.writer, "allan/curves", plot_allan(report, title=f"live, {step} s of data"), step)
        self.writer.flush()

    def finish(self) -> None:
        """The last report, with the Allan curves as a figure."""
        self._close_bin()
        if self._n >= 3:
            self.report(step=int(round(self.time_s[-1] - self._start_s)), figure=True)


def _number(value: float | None) -> str:
    return "n/a" if value is None else f"{value:.4g}"


def _finite_or_none(value: float) -> float | None:
    return float(value) if math.isfinite(value) else None


def run_stream(bundle_dir: str | Path, port: str, output: str | Path, protocol: str = "lpbus",
               baud: int = 921600, layout: LpBusLayout | None = None, max_samples: int | None = None,
               duration_s: float | None = None, allan_every_s: float = 60.0, tb_dir: str | Path | None = None,
               summary_path: str | Path | None = None, read_timeout_s: float = 0.05,
               reconnect: Mapping[str, float | None] | None = None, startup: Mapping[str, Any] | None = None) -> dict:
    """``stream.py``: compensate a live stream until told to stop; return the summary.

    Parameters
    ----------
    bundle_dir
        Compensator bundle (CONTRACT.md section 2).
    port
        Serial device, symlink or pyserial URL.
    output
        Compensated CSV.
    protocol, baud, layout
        Framing (``"lpbus"`` or ``"csv"``), speed, LP-BUS layout.
    max_samples, duration_s
        Stop after this many good samples, or this many wall-clock seconds (None: run until
        Ctrl-C, or until the port stays gone for ``reconnect["give_up_s"]``).
    allan_every_s
        Data seconds between live Allan reports (0: none).
    tb_dir, summary_path
        TensorBoard folder and summary JSON (None: not written).
    read_timeout_s
        Serial read timeout, s.
    reconnect
        ``backoff_s``, ``max_backoff_s``, ``give_up_s`` for :func:`read_samples`.
    startup
        ``Compensator.use_startup`` options (``still_s``, ``motion_dps``, ``static_rate_dps``).
    """
    compensator = Compensator.load(bundle_dir)
    compensator.use_startup(**dict(startup or {}))
    compensator.reset()
    parser = make_parser(protocol, layout)
    if protocol == "lpbus":
        compensator.check_columns(dict.fromkeys(parser.columns), source=f"LP-BUS fields {list(parser.layout.fields)}")
    writer = _tb_writer(tb_dir) if tb_dir is not None and allan_every_s > 0 else None
    allan = LiveAllan(writer, allan_every_s, float(compensator.meta["fs_hz"])) if allan_every_s > 0 else None
    out = LiveWriter(output, bundle_dir)
    counter = FaultCounter()
    started = time.monotonic()
    stopped = "port_gone"

    def should_stop() -> bool:
        return duration_s is not None and time.monotonic() - started >= duration_s

    log.info("streaming %s (%s, %d baud) through %s into %s", port, protocol, baud, bundle_dir, output)
    items = read_samples(None, parser, url=port, baud=baud, timeout_s=read_timeout_s, should_stop=should_stop,
                         **dict(reconnect or {}))
    try:
        for item in items:
            counter.add(item)
            if not isinstance(item, Sample):
                log.log(logging.WARNING if counter.counts[item.reason] == 1 else logging.DEBUG, "fault: %s", item)
                continue
            _compensate(compensator, item, out, allan, port)
            if max_samples is not None and out.n_rows >= max_samples:
                stopped = "max_samples"
                break
        else:
            stopped = "duration" if should_stop() else "port_gone"
    except KeyboardInterrupt:
        stopped = "interrupted"
    finally:
        items.close()  # closes the port
        out.close()
    if allan is not None:
        allan.finish()
    if writer is not None:
        writer.close()
    summary = _summary(counter, compensator, out, allan, stopped, time.monotonic() - started)
    log.info("stopped (%s): %s; %d out of the trained temperature range", stopped, counter.summary(),
             summary["n_out_of_range"])
    if summary_path is not None:
        Path(summary_path).parent.mkdir(parents=True, exist_ok=True)
        Path(summary_path).write_text(json.dumps(summary, indent=2) + "\n")
    return summary


def _compensate(compensator: Compensator, sample: Sample, out: LiveWriter, allan: LiveAllan | None,
                port: str) -> None:
    row = sample.row()
    if out.n_rows == 0:
        compensator.check_columns(row, source=f"{port}: the stream")
    result = compensator.process({name: np.array([row[name]]) for name in compensator.input_columns})
    out.write(sample.time_s, row["temp_c"], result)
    if result.out_of_range[0]:
        log.debug("temp_c=%.3f at %.3f s outside the trained range", row["temp_c"], sample.time_s)
    if allan is not None:
        allan.add(sample.time_s, result.rate_dps[0])


def interrupt_on_sigterm() -> None:
    """Make SIGTERM stop a run the way Ctrl-C does (summary written, files closed)."""
    import signal

    def _raise(signum, frame):
        raise KeyboardInterrupt

    signal.signal(signal.SIGTERM, _raise)


def _tb_writer(tb_dir: str | Path):
    from gyronet.tb import make_writer

    return make_writer(tb_dir)


def _summary(counter: FaultCounter, compensator: Compensator, out: LiveWriter, allan: LiveAllan | None,
             stopped: str, elapsed_s: float) -> dict:
    return {"stopped": stopped, "n_samples": out.n_rows, "faults": counter.as_dict(),
            "n_faults": counter.n_faults, "n_out_of_range": int(compensator.n_out_of_range),
            "temp_range_c": list(compensator.temp_range_c), "elapsed_s": round(elapsed_s, 3),
            "output": str(out.path), "allan": allan.last if allan is not None else {}}
