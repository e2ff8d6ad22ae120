"""``record.py``: a calibration run straight from an LP-BUS sensor, set up first, into a recording CSV.

The sensor is configured as for ``stream.py`` (:func:`~gyronet.deploy.stream.lpbus_setup.start_lpbus`:
outputs, rate, 32-bit, gyro auto-calibration off), so a chamber run starts from a known state;
what the sensor reported is written as the CSV's ``#`` metadata (``fs_hz``, ``sensor``,
``firmware``, ``gyro_source=raw``, ``gyro_autocalibration``, ``lpbus``). Rows are the decoded
frames (CONTRACT.md section 1), each value as the shortest text that reads back to the same
number, one ``os.write`` per line, so a kill leaves whole lines. A sensor clock that restarts (a
replug) keeps ``time_s`` increasing: the new segment starts as long after the last sample as the
host's clock says passed between them (a 20-minute unplug is a 20-minute break, not a 1 s jump),
and at least one interval plus ``restart_gap_s`` after it, a break in the record. A sensor that
comes back after the port was lost is set up again (or its first frames checked again) before its
rows are written, and refused if it is not the one set up at the start.
"""
from __future__ import annotations

import contextlib
import logging
import os
import time
from collections import Counter
from pathlib import Path
from typing import Callable, Mapping

from gyronet.errors import ConfigError
from gyronet.recordings.data import FS_TOLERANCE
from gyronet.deploy.stream.events import FaultCounter, Sample, SampleCheck
from gyronet.deploy.stream.limits import check_run_limits
from gyronet.deploy.stream.lpbus_link import SensorError
from gyronet.deploy.stream.lpbus_probe import LayoutError
from gyronet.deploy.stream.lpbus_setup import LpBusSetup, start_lpbus
from gyronet.deploy.stream.summary import OutputError, refuse_gzip_name, write_summary
from gyronet.deploy.stream.reader import open_port_or_fail, read_samples
from gyronet.deploy.stream.signals import stop_on_signals

log = logging.getLogger(__name__)

REQUIRED = ("time_s", "temp_c", "gyro_x_dps", "gyro_y_dps", "gyro_z_dps")
PROGRESS_S = 60.0  # how often a recording says how far it is
FS_SLOT = 16  # characters kept for the ``# fs_hz=`` value, so that the rate the stamps show can replace it at the end


def record_stream(port: str, output: str | Path, baud: int = 921600, lpbus: LpBusSetup | None = None,
                  max_samples: int | None = None, duration_s: float | None = None, read_timeout_s: float = 0.05,
                  reconnect: Mapping[str, float | None] | None = None, clock: Mapping[str, float | None] | None = None,
                  summary_path: str | Path | None = None, restart_gap_s: float = 1.0,
                  stop: Callable[[], bool] | None = None, overwrite: bool = False) -> dict:
    """Set the sensor up, record it into ``output`` until told to stop; return the summary.

    ``stop`` is polled between reads; without one, SIGINT and SIGTERM stop the recording there
    (:func:`~gyronet.deploy.stream.signals.stop_on_signals`), so what was read is written. An existing
    ``output`` is refused before the port opens unless ``overwrite`` (a chamber run is hours).

    Raises
    ------
    ConfigError, OutputError
        Before the port opens: a limit that is not positive (:func:`.limits.check_run_limits`);
        ``output`` exists (without ``overwrite``) or is ``summary_path``.
    PortError, SensorError, ConfigError
        Before any row: a port that cannot be opened, a sensor that does not answer or cannot be
        set up, a layout without gyro and temperature.
    SensorError, LayoutError
        After a replug: the sensor that came back is another one, or (listening) its first frames
        do not fit; the rows so far stay whole and the summary (``stopped: refused``) is written.
    OutputError
        When the output cannot be written.
    """
    lpbus = lpbus or LpBusSetup()
    check_run_limits(baud, max_samples, duration_s, read_timeout_s)
    _refuse_output(Path(output), summary_path, overwrite)
    opened = open_port_or_fail(port, baud, read_timeout_s)
    try:
        start = start_lpbus(opened, port, lpbus)
        missing = [c for c in REQUIRED if c not in start.layout.columns]
        if missing:
            raise ConfigError(f"{port}: the frames ({start.layout.describe()}) lack {', '.join(missing)}: a "
                              "recording needs the gyro and the temperature (lpbus.fields)")
        out = _RecordingFile(output, start.layout.columns, _metadata(start), overwrite)
    except Exception:
        opened.close()
        raise
    counter, started = FaultCounter(), time.monotonic()
    signals = contextlib.ExitStack()  # without ``stop``, Ctrl-C is polled too: the chunk in flight is written
    external_stop = stop or signals.enter_context(stop_on_signals())

    def should_stop() -> bool:
        return external_stop() or (duration_s is not None and time.monotonic() - started >= duration_s)

    parser = start.parser(SampleCheck(**dict(clock or {})))
    items = read_samples(opened, parser, url=port, baud=baud, timeout_s=read_timeout_s, should_stop=should_stop,
                         on_reopen=start.reopen_hook(parser, port), **dict(reconnect or {}))
    stopped, offset_s, last_s, interval_s, restarts, last_host_s = "port_gone", 0.0, None, 0.0, 0, 0.0
    intervals = Counter()  # sample intervals to 4 digits: their median is the rate the file's reader will see
    refusal: Exception | None = None
    progress_at = started + PROGRESS_S  # a line a minute: a chamber run is hours of otherwise silent recording
    try:
        for item in items:
            counter.add(item)
            if not isinstance(item, Sample):
                log.log(logging.WARNING if counter.counts[item.reason] == 1 else logging.DEBUG, "fault: %s", item)
                continue
            if item.new_segment and last_s is not None:
                restarts += 1
                # the outage as the host timed it: the sensor's restarted clock cannot say how long it was
                gap_s = max(interval_s + restart_gap_s, _host_s() - last_host_s)
                offset_s = last_s + gap_s - item.time_s
            row = item.row()
            time_s = row["time_s"] + offset_s
            if last_s is not None and not item.new_segment:
                interval_s = time_s - last_s
                intervals[float(f"{interval_s:.4g}")] += 1
            out.write([time_s, *(row[c] for c in start.layout.columns[1:])])
            last_s, last_host_s = time_s, _host_s()
            if time.monotonic() >= progress_at:
                progress_at += PROGRESS_S
                log.info("recorded %d samples, up to time_s=%.0f, %.2f degC now; %s", out.n_rows, time_s,
                         row["temp_c"], counter.summary())
            if max_samples is not None and out.n_rows >= max_samples:
                stopped = "max_samples"
                break
        else:
            stopped = "interrupted" if external_stop() else "duration" if should_stop() else "port_gone"
    except KeyboardInterrupt:
        stopped = "interrupted"
    except (SensorError, LayoutError) as err:  # after a replug: another sensor, or frames that do not fit
        stopped, refusal = "refused", err
    except OutputError as err:  # a full disk: the file ends with its last whole row, and the summary says so
        stopped, refusal = "output_failed", err
    finally:
        items.close()
        stamped_hz = _rate_the_stamps_show(out, intervals)
        out.close()
        signals.close()
    summary = {"stopped": stopped, "n_samples": out.n_rows, "faults": counter.as_dict(), "n_faults": counter.n_faults,
               "clock_restarts": restarts, "output": str(out.path), "sensor": start.as_dict(),
               **({"fs_hz_from_stamps": stamped_hz} if stamped_hz is not None else {}),
               **({"refused" if stopped == "refused" else "error": str(refusal)} if refusal is not None else {})}
    log.info("recorded %d samples into %s (%s); %s", out.n_rows, out.path, stopped, counter.summary())
    if summary_path is not None:
        try:
            write_summary(summary_path, summary)
        except OutputError as err:
            if stopped != "output_failed":
                raise
            raise OutputError(f"{refusal}; {err}") from None
        log.info("summary (samples, faults by reason, the sensor's account): %s", summary_path)
    if isinstance(refusal, OutputError):
        raise OutputError(f"{refusal}" + (f"; summary in {summary_path}" if summary_path is not None else "")) from None
    if refusal is not None:
        raise refusal
    return summary


def _host_s() -> float:
    """The host's clock for an outage, s: Linux's boot time counts a suspended laptop's sleep, which monotonic skips."""
    return time.clock_gettime(time.CLOCK_BOOTTIME) if hasattr(time, "CLOCK_BOOTTIME") else time.monotonic()


def _rate_the_stamps_show(out: "_RecordingFile", intervals: Counter) -> float | None:
    """Where the sensor's reported rate is not its stamps' (a loader would refuse the file), write the stamps' rate
    as ``# fs_hz=`` instead, with a warning; that rate, else None."""
    if out.fs_hz is None or not intervals:
        return None
    half, seen = sum(intervals.values()) / 2.0, 0
    for median_s, count in sorted(intervals.items()):
        seen += count
        if seen >= half:
            break
    if not median_s > 0 or abs(out.fs_hz * median_s - 1.0) <= FS_TOLERANCE:
        return None
    stamped_hz = float(f"{1.0 / median_s:.4g}")
    log.warning("the sensor reported %g Hz, but its time stamps are %g Hz apart (median interval %g s): "
                "# fs_hz=%g written, as the stamps show", out.fs_hz, stamped_hz, median_s, stamped_hz)
    out.set_fs_hz(stamped_hz)
    return stamped_hz


def _refuse_output(output: Path, summary_path: str | Path | None, overwrite: bool) -> None:
    """Refuse, before the sensor is touched, an output that would replace a recording or be replaced by the summary."""
    refuse_gzip_name(output)
    if summary_path is not None and os.path.realpath(summary_path) == os.path.realpath(output):
        raise OutputError(f"{output}: summary= names the recording itself, which the summary would replace; "
                          "give summary= another path")
    if output.is_dir():
        raise OutputError(f"{output}: is a folder; give output= a file name")
    if os.path.lexists(output) and not overwrite:
        raise OutputError(f"{output}: exists; a recording is not replaced unless overwrite=true (or give "
                          "another output=)")


def _metadata(start) -> dict[str, str]:
    meta = {"gyro_source": "raw", "lpbus": start.layout.describe()}
    if start.sensor is not None:
        info = start.sensor
        meta.update(fs_hz=f"{info.rate_hz:g}", sensor=info.model, firmware=info.firmware,
                    gyro_autocalibration="on" if info.gyro_autocalibration else "off")
    else:
        meta["gyro_autocalibration"] = "unknown (lpbus.configure=false)"
    return meta


class _RecordingFile:
    """The recording CSV: metadata and header first, then one whole line per ``write``."""

    def __init__(self, path: str | Path, columns: list[str], meta: Mapping[str, str], overwrite: bool = False):
        self.path, self.n_rows, self._size_bytes = Path(path), 0, 0
        self.fs_hz = float(meta["fs_hz"]) if "fs_hz" in meta else None
        refuse_gzip_name(self.path)
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            # O_EXCL: a file that appeared while the sensor was set up is not replaced either
            replace = os.O_TRUNC if overwrite else os.O_EXCL
            self._fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | replace, 0o644)
        except FileExistsError:
            raise OutputError(f"{self.path}: exists; a recording is not replaced unless overwrite=true") from None
        except OSError as err:
            raise OutputError(f"{self.path}: cannot write the recording ({err.strerror})") from None
        head, self._fs_at = b"", None
        for key, value in meta.items():
            if key == "fs_hz":
                self._fs_at, value = len(head) + len(b"# fs_hz="), f"{value:<{FS_SLOT}}"  # read back stripped
            head += f"# {key}={value}\n".encode()
        try:
            self._write(head.decode() + ",".join(columns) + "\n")
        except OutputError:  # not even the header fits: no file rather than an empty one
            os.close(self._fd)
            self.path.unlink(missing_ok=True)
            raise

    def set_fs_hz(self, fs_hz: float) -> None:
        """Overwrite the ``# fs_hz=`` value in place (its slot is :data:`FS_SLOT` characters wide)."""
        try:
            os.pwrite(self._fd, f"{fs_hz:<{FS_SLOT}g}".encode(), self._fs_at)
        except OSError as err:  # the rows are whole; the loader then refuses the file's rate by name
            log.error("%s: could not write # fs_hz=%g (%s)", self.path, fs_hz, err.strerror or err)
            return
        self.fs_hz = fs_hz

    def write(self, values: list[float]) -> None:
        self._write(",".join(repr(float(v)) for v in values) + "\n")
        self.n_rows += 1

    def _write(self, text: str) -> None:
        data, done = text.encode(), 0
        try:
            while done < len(data):
                done += os.write(self._fd, data[done:])
        except OSError as err:  # a full disk: cut the part-written line off, so the file ends with a whole row
            with contextlib.suppress(OSError):
                os.ftruncate(self._fd, self._size_bytes)
            raise OutputError(f"{self.path}: cannot write the recording ({err.strerror or err}) after {self.n_rows} "
                              "rows; the file ends with the last whole row") from None
        self._size_bytes += len(data)

    def close(self) -> None:
        os.close(self._fd)
