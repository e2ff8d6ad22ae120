"""The live path: a sensor stream's good samples through a compensator bundle into a CSV.

Every read of the port is one chunk: the good samples it completed go through
``Compensator.process`` together, the same causal code the offline path runs on a whole file, so
the output equals ``compensate.py`` on the good samples (to rounding: a chunk of a few samples
runs in plain floats, not TorchScript), and a lone frame is answered at once (:mod:`.chunk`). The output has the offline columns (``time_s``, compensated ``gyro_*_dps``,
``temp_c``, ``out_of_range``) and a chunk's lines are on disk before the next read
(:mod:`.output`). Faults are counted by reason; the Allan terms of the compensated rate (N and B
per axis) go to TensorBoard every ``allan_every_s`` of data, computed in a worker thread so that
no frame waits for one, and the Allan curves as a figure when the run stops (:mod:`.live_allan`).

A sensor clock that restarts (a replug: time goes back, or jumps far ahead) starts a new segment:
the compensator restarts from its power-on state, as the sensor did, and the output keeps the
sensor's own times, so each segment equals ``compensate.py`` on that segment's samples.
"""
from __future__ import annotations

import contextlib
import gc
import importlib
import logging
import sys
import time
from pathlib import Path
from typing import Any, Callable, Iterator, Mapping

from gyronet.bundle.compensator import Compensator
from gyronet.bundle.offline import log_what_it_rests_on
from gyronet.deploy.stream import Fault, FaultCounter, LpBusLayout, SampleCheck, make_parser
from gyronet.deploy.stream.allocator import fix_mmap_threshold
from gyronet.deploy.stream.chunk import RATE_PROBE_SAMPLES, ChunkWriter, RateGate, n_rows
from gyronet.deploy.stream.events import Sample, SampleBlock
from gyronet.deploy.stream.live_allan import LiveAllan
from gyronet.deploy.stream.limits import check_run_limits
from gyronet.deploy.stream.live_recal import LiveRecalibration
from gyronet.deploy.stream.lpbus_setup import LpBusSetup, LpBusStart, start_lpbus
from gyronet.deploy.stream.output import LiveWriter, OutputError, output_names
from gyronet.deploy.stream.priority import use_realtime
from gyronet.deploy.stream.reader import open_port_or_fail, read_chunks
from gyronet.deploy.stream.signals import stop_on_signals
from gyronet.deploy.stream.summary import write_summary
from gyronet.errors import ConfigError, GyronetError

log = logging.getLogger(__name__)

__all__ = ["LiveAllan", "LiveWriter", "OutputError", "RATE_PROBE_SAMPLES", "RateGate", "output_names", "run_stream",
           "stop_on_signals"]


def run_stream(bundle_dir: str | Path, port: str, output: str | Path, protocol: str = "lpbus",
               baud: int = 921600, layout: LpBusLayout | None = None, max_samples: int | None = None,
               duration_s: float | None = None, allan_every_s: float = 60.0, tb_dir: str | Path | None = None,
               summary_path: str | Path | None = None, read_timeout_s: float = 0.05,
               reconnect: Mapping[str, float | bool | None] | None = None,
               clock: Mapping[str, float | None] | None = None,
               stop: Callable[[], bool] | None = None,
               startup: Mapping[str, Any] | None = None, resample: bool = False,
               lpbus: LpBusSetup | None = None, realtime_priority: int | None = None) -> dict:
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
        stopped, or until the port stays gone for ``reconnect["give_up_s"]``).
    allan_every_s
        Data seconds between live Allan reports (0: none).
    tb_dir, summary_path
        TensorBoard folder and summary JSON (None: not written).
    read_timeout_s
        Serial read timeout, s.
    reconnect
        ``backoff_s``, ``max_backoff_s``, ``give_up_s`` for :func:`read_samples`, and
        ``wait_at_start``: when false (default) a port that cannot be opened at the start is a
        ``PortError``; when true it is waited for like a lost one.
    clock
        ``restart_back_s``, ``restart_jump_s`` for :class:`SampleCheck`: what counts as a
        restarted sensor clock.
    stop
        Polled between reads; True stops the run as Ctrl-C does (``stop_on_signals``).
    startup
        ``Compensator.use_startup`` options (``still_s``, ``motion_dps``, ``static_rate_dps``).
    resample
        As in ``compensate.py``: the stream's rate, measured over its first ``RATE_PROBE_SAMPLES``
        samples (held until then), must be within 5 % of the bundle's ``fs_hz`` unless true.
    lpbus
        LP-BUS set-up (:class:`~gyronet.deploy.stream.lpbus_setup.LpBusSetup`): configure the sensor, or
        listen and check the first frames; it replaces ``layout``. None: listen with ``layout``.
    realtime_priority
        Run the sample loop under ``SCHED_FIFO`` at this priority (1-99, Linux, root or
        ``CAP_SYS_NICE``; :mod:`.priority`), checked before the port opens; None: the normal scheduler.

    Raises
    ------
    PortError, BundleError, ConfigError
        Before any sample is written: a baud, limit or timeout that is not positive, a port that cannot be
        opened, a bundle that does not fit (its columns, or its rate against the stream's), a real-time
        priority the OS refuses.
    OutputError
        When the output cannot be written (a full disk): after the port is closed and the
        summary written (or logged as impossible); the output ends with a complete line.
    """
    check_run_limits(baud, max_samples, duration_s, read_timeout_s)
    if protocol not in ("lpbus", "csv"):  # make_parser's ValueError came after the bundle loaded, as a traceback
        raise ConfigError(f"protocol must be lpbus or csv, got {protocol!r}")
    options = dict(reconnect or {})
    wait_at_start = bool(options.pop("wait_at_start", False))
    use_realtime(realtime_priority)()  # refused now, before the port opens, rather than after the set-up
    compensator = Compensator.load(bundle_dir)
    compensator.use_small_chunks()  # a lone frame in plain floats, not ~30 TorchScript ops
    compensator.use_startup(**dict(startup or {}))
    log_what_it_rests_on(compensator)
    compensator.reset()
    check = SampleCheck(**dict(clock or {}))
    parser = make_parser(protocol, layout, required=compensator.input_columns, check=check)
    if protocol == "lpbus" and lpbus is None:
        compensator.check_columns(dict.fromkeys(parser.columns), source=f"LP-BUS fields {list(parser.layout.fields)}")
    if tb_dir is not None and allan_every_s > 0:
        # seconds of imports: done before the port opens, when the sensor's first frames would wait for them
        importlib.import_module("torch.utils.tensorboard")
    # the set-up's objects (torch, the bundle: hundreds of thousands) out of the garbage collector, whose full
    # passes over them took milliseconds in the sample loop; collected first, before the port opens (~0.1 s)
    gc.collect()
    gc.freeze()
    opened = out = None
    try:
        opened = None if wait_at_start else open_port_or_fail(
            port, baud, read_timeout_s, hint="; pass reconnect.wait_at_start=true to wait for it")
        sensor = None
        if protocol == "lpbus" and lpbus is not None:  # issue 13: set the sensor up before the sample loop
            sensor, parser = _start_lpbus(opened, port, lpbus, compensator, resample, check)
        # a flood's frames (or lines) as columns, decoded at once: the chunk writer takes them as they are
        parser.blocks = True
        startup_offset = compensator.startup
        out = LiveWriter(output, bundle_dir, 0.0 if startup_offset is None else startup_offset.still_s,
                         None if startup_offset is None else startup_offset.static_rate_dps)
        writer = _tb_writer(tb_dir) if tb_dir is not None and allan_every_s > 0 else None
        allan = LiveAllan(writer, allan_every_s, float(compensator.meta["fs_hz"]), background=True) \
            if allan_every_s > 0 else None
        # a still sensor, as the Allan monitor assumes: its 60 s means held against their error bar
        recalibration = LiveRecalibration(float((startup or {}).get("still_s") or 0.0), writer) \
            if allan is not None and compensator.error_bar is not None else None
    except BaseException:  # a refused set-up leaves the process as it found it: collector, port, output
        gc.unfreeze()
        for opened_thing in (out, opened):
            if opened_thing is not None:
                opened_thing.close()
        raise
    counter = FaultCounter()
    started = time.monotonic()
    stopped, failure = "port_gone", None
    external_stop = stop or (lambda: False)

    def should_stop() -> bool:
        return external_stop() or (duration_s is not None and time.monotonic() - started >= duration_s)

    log.info("streaming %s (%s, %d baud) through %s into %s", port, protocol, baud, bundle_dir, output)
    chunks = read_chunks(opened, parser, url=port, baud=baud, timeout_s=read_timeout_s, should_stop=should_stop,
                         on_reopen=sensor.reopen_hook(parser, port) if sensor is not None else None, **options)
    gate = RateGate(compensator, resample, f"{port}: the stream",
                    RATE_PROBE_SAMPLES if max_samples is None else min(RATE_PROBE_SAMPLES, max_samples))
    sink = ChunkWriter(compensator, out, allan, port, max_samples, recalibration)
    try:
        try:
            with _steady_runtime(realtime_priority):
                for chunk in chunks:
                    if sink.write(_good_samples(chunk, counter, gate, sink)):
                        stopped = "max_samples"
                        break
                else:
                    stopped = "interrupted" if external_stop() else "duration" if should_stop() else "port_gone"
        except KeyboardInterrupt:
            stopped = "interrupted"
        sink.write(gate.flush())  # the samples held while the rate was measured
    except OutputError as err:
        stopped, failure = "output_failed", err
    except GyronetError as err:  # a rate change, motion in the start-up window, another sensor: the run ends here
        stopped, failure = "error", err
    finally:
        chunks.close()  # closes the port
        out.close()
    recalibration_figures = recalibration.finish() if recalibration is not None else {}  # before the writer closes
    _finish_allan(allan, writer)
    summary = _summary(counter, compensator, out, allan, stopped, time.monotonic() - started, sink, sensor)
    summary["recalibration"] = recalibration_figures
    if failure is not None:
        summary["error"] = str(failure)
    log.info("stopped (%s): %s; %d out of the trained temperature range; %d clock restart(s)", stopped,
             counter.summary(), summary["n_out_of_range"], summary["clock_restarts"])
    summary_note = ""
    if summary_path is not None:
        try:
            write_summary(summary_path, summary)
            summary_note = f"; summary in {summary_path}"
        except OutputError as err:
            log.error("%s", err)
            summary_note = f"; {err}"
    if isinstance(failure, OutputError):
        raise OutputError(f"{failure}{summary_note}")
    if failure is not None:
        raise failure
    return summary


def _good_samples(chunk: list, counter: FaultCounter, gate: RateGate, sink: ChunkWriter) -> list[Sample | SampleBlock]:
    """Count a chunk's items, log its faults, and return its samples that are ready (up to ``max_samples``)."""
    ready: list[Sample | SampleBlock] = []
    room = None if sink.max_samples is None else sink.max_samples - sink.out.n_rows
    for item in chunk:
        if isinstance(item, Fault):
            counter.add(item)
            log.log(logging.WARNING if counter.counts[item.reason] == 1 else logging.DEBUG, "fault: %s", item)
            continue
        if room is not None and isinstance(item, SampleBlock):
            # the samples one by one would stop once ready and held reach the room: the rest is not read, nor counted
            item = item.cut(max(1, room - n_rows(ready) - len(gate.held or ())))
        counter.add(item)
        ready += gate.push(item)
        if room is not None and n_rows(ready) >= room:
            break  # what follows is not read, as when the run stopped right after this sample
    return ready


@contextlib.contextmanager
def _steady_runtime(realtime_priority: int | None = None, switch_interval_s: float = 2e-4) -> Iterator[None]:
    """The sample loop with a short GIL switch interval, so that a frame waits at most that long for the Allan
    worker thread (5 ms by default), malloc's mmap threshold fixed, so that the RSS stays flat over hours
    (:mod:`.allocator`), and the real-time priority asked for (:mod:`.priority`); on exit, the scheduler
    and the switch interval as they were, and the objects ``run_stream`` froze back to the collector."""
    fix_mmap_threshold()
    previous_s = sys.getswitchinterval()
    sys.setswitchinterval(switch_interval_s)
    restore_scheduler = use_realtime(realtime_priority)
    try:
        yield
    finally:
        restore_scheduler()
        sys.setswitchinterval(previous_s)
        gc.unfreeze()


def _start_lpbus(opened, port: str, lpbus: LpBusSetup, compensator: Compensator, resample: bool,
                 check: SampleCheck) -> tuple[LpBusStart, Any]:
    """Configure the sensor (or plan the passive check) and make its parser; the port is closed on a refusal."""
    try:
        start = start_lpbus(opened, port, lpbus, compensator.meta, resample)
        compensator.check_columns(dict.fromkeys(start.layout.columns), source=f"{port}: {start.layout.describe()}")
    except Exception:
        if opened is not None:
            opened.close()
        raise
    return start, start.parser(check)


def _tb_writer(tb_dir: str | Path):
    from gyronet.figures.tb import make_writer

    return make_writer(tb_dir)


def _finish_allan(allan: LiveAllan | None, writer) -> None:
    try:
        if allan is not None:
            allan.finish()
        if writer is not None:
            writer.close()
    except OSError as err:  # TensorBoard on a full disk: the summary still comes
        log.error("TensorBoard: cannot finish writing (%s)", err)


def _summary(counter: FaultCounter, compensator: Compensator, out: LiveWriter, allan: LiveAllan | None,
             stopped: str, elapsed_s: float, sink: ChunkWriter,
             sensor: LpBusStart | None = None) -> dict:
    return {"stopped": stopped, "n_samples": out.n_rows, "faults": counter.as_dict(),
            "n_faults": counter.n_faults, "n_out_of_range": int(sink.n_out_of_range),
            "clock_restarts": int(sink.clock_restarts),
            "temp_range_c": list(compensator.temp_range_c), "elapsed_s": round(elapsed_s, 3),
            "output": str(out.path), "allan": allan.last if allan is not None else {},
            "allan_bins": allan.bins if allan is not None else {},
            **({"sensor": sensor.as_dict()} if sensor is not None else {})}
