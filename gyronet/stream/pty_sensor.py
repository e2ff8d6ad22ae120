"""A pseudo-terminal that plays an emulated sensor (POSIX only).

A reader opens the pty's slave device like any serial port. A pty cannot be closed and reopened
under the same name, so when the emulator drops the port it opens a new pty and re-points a
symlink (``link``) to it; a reader that (re)opens the symlink, as ``read_samples`` does, follows
the sensor across drops. The current slave path is also written to ``port_file``.

Two details keep the emulation lossless:

- pyserial flushes the input queue when it opens a port, so bytes sent before a reader opened
  would vanish. The emulator marks its pty with an unusual speed (50 baud) and waits until a
  reader's ``tcsetattr`` changes it, then a moment more, before sending.
- Before it drops the port, it waits until the reader has read every byte (``FIONREAD`` on the
  slave stays 0 for a moment).

With an emulated sensor (:class:`~gyronet.stream.lpbus_device.EmulatedLpms`,
:func:`gyronet.stream.pty_device.play_device`) the pty also answers the host's commands before it
streams: the plan is then framed in the layout the host left the sensor in. A host that sends
nothing within ``command_wait_s`` gets the sensor's power-on layout (a passive reader).
"""
from __future__ import annotations

import fcntl
import json
import logging
import os
import struct
import termios
import threading
import time
import tty
from pathlib import Path
from typing import Callable, Mapping, Sequence

import numpy as np

from gyronet.data import load_recording
from gyronet.errors import GyronetError
from gyronet.stream.emulator import FaultPlan, StreamPlan, plan_stream
from gyronet.stream.lpbus_device import EmulatedLpms
from gyronet.stream.lpbus_layout import LpBusLayout

log = logging.getLogger(__name__)

_MARKER_SPEED = termios.B50
_POLL_S = 0.01


class PtySensor:
    """One pty at a time, with an optional symlink and port file naming its slave.

    Parameters
    ----------
    link
        Symlink re-pointed to the current slave device.
    port_file
        File that holds the current slave path (written atomically).
    """

    def __init__(self, link: str | os.PathLike | None = None, port_file: str | os.PathLike | None = None):
        self.link = Path(link) if link else None
        self.port_file = Path(port_file) if port_file else None
        self.master_fd: int | None = None
        self.slave_fd: int | None = None
        self.path: str | None = None

    def open(self) -> str:
        """Open a new pty in raw mode; point the link and port file at it; return the slave path."""
        self.master_fd, self.slave_fd = os.openpty()
        tty.setraw(self.slave_fd)
        attrs = termios.tcgetattr(self.slave_fd)
        attrs[4] = attrs[5] = _MARKER_SPEED
        termios.tcsetattr(self.slave_fd, termios.TCSANOW, attrs)
        self.path = os.ttyname(self.slave_fd)
        if self.link is not None:
            temporary = self.link.with_name(self.link.name + ".tmp")
            temporary.unlink(missing_ok=True)
            os.symlink(self.path, temporary)
            os.replace(temporary, self.link)
        if self.port_file is not None:
            _write_atomic(self.port_file, self.path + "\n")
        log.info("sensor port: %s%s", self.path, f" (link {self.link})" if self.link else "")
        return self.path

    def wait_for_reader(self, timeout_s: float, settle_s: float = 0.2) -> bool:
        """Wait until a reader has opened the port (its settings replaced the marker speed)."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if termios.tcgetattr(self.slave_fd)[5] != _MARKER_SPEED:
                time.sleep(settle_s)  # the reader flushes its input right after configuring
                return True
            time.sleep(_POLL_S)
        log.warning("no reader opened %s within %.1f s; sending anyway", self.path, timeout_s)
        return False

    def write(self, data: bytes) -> None:
        """Write all of ``data`` (blocks while the reader is behind)."""
        view = memoryview(data)
        while view:
            view = view[os.write(self.master_fd, view):]

    def unread_bytes(self) -> int:
        """Bytes sent that the reader has not read yet."""
        return struct.unpack("i", fcntl.ioctl(self.slave_fd, termios.FIONREAD, b"\0\0\0\0"))[0]

    def drain(self, timeout_s: float, quiet_s: float = 0.1) -> bool:
        """Wait until the reader has read everything sent.

        The kernel moves written bytes to the slave's queue asynchronously, so an empty queue right
        after a write proves nothing: it must stay empty for ``quiet_s``.
        """
        deadline = time.monotonic() + timeout_s
        quiet_since = time.monotonic()
        while time.monotonic() - quiet_since < quiet_s:
            if self.unread_bytes() > 0:
                quiet_since = time.monotonic()
                if quiet_since > deadline:
                    log.warning("reader left %d bytes unread on %s", self.unread_bytes(), self.path)
                    return False
            time.sleep(_POLL_S)
        return True

    def close(self) -> None:
        """Close the pty: a reader's next read fails, as when a USB sensor is unplugged, and the link goes with it
        until ``open``: a reader retrying meanwhile must not follow it to the closed device's number, which
        the kernel may give to another program's pty (an extra ``port_lost`` seen under parallel tests)."""
        for fd in (self.master_fd, self.slave_fd):
            if fd is not None:
                os.close(fd)
        self.master_fd = self.slave_fd = None
        self.remove_link()

    def remove_link(self) -> None:
        """Remove the symlink (at the end, so a reader sees the sensor gone)."""
        if self.link is not None:
            self.link.unlink(missing_ok=True)


def play(plan: StreamPlan, sensor: PtySensor, speed: float = 1.0, reader_timeout_s: float = 30.0,
         port_down_s: float = 0.5, drain_timeout_s: float = 10.0,
         clock: Callable[[], float] = time.monotonic, sleep: Callable[[float], None] = time.sleep,
         opened: bool = False, after_drop: Callable[[], object] | None = None) -> int:
    """Send a plan into ``sensor``: in real time divided by ``speed`` (0: as fast as possible).

    ``opened``: the pty is open and its reader there already (``play_device``). ``after_drop``:
    called once the reader is back after each port drop (an emulated sensor answers it again).

    Returns
    -------
    int
        Number of events sent (drops included).
    """
    if not opened:
        sensor.open()
        sensor.wait_for_reader(reader_timeout_s)
    sensor.write(plan.preamble)
    if not plan.events:
        return 0
    start_wall, start_data = clock(), plan.events[0].time_s
    for event in plan.events:
        if speed > 0:
            delay = start_wall + (event.time_s - start_data) / speed - clock()
            if delay > 0:
                sleep(delay)
        if event.drop:
            _drop(sensor, plan, reader_timeout_s, port_down_s, drain_timeout_s, sleep)
            if after_drop is not None:
                after_drop()
        else:
            sensor.write(event.data)
    sensor.drain(drain_timeout_s)
    return len(plan.events)



def play_in_thread(plan: StreamPlan | None, link: str | Path, device: EmulatedLpms | None = None,
                   columns: Mapping[str, np.ndarray] | None = None, faults: FaultPlan | None = None,
                   replugs: Sequence[tuple[EmulatedLpms, Mapping[str, np.ndarray]]] = (),
                   preroll_frames: int = 0, **play_options) -> threading.Thread:
    """Play ``plan`` into a new pseudo-terminal at ``link`` from a daemon thread (tests, in-process
    benchmarks); the port is closed and its link removed when the plan ends.

    With ``device``, the pty answers the host's commands first and then plays ``columns`` (with
    ``faults``) framed in the layout the host left (the thread's ``plan`` attribute holds it).
    ``replugs``: then, for each ``(device, columns)``, the sensor is unplugged and comes back as
    that device (its power-on state), answers the host again and plays those columns (``plans``
    holds every plan). ``preroll_frames``: frames each power-up streams before the host talks.
    """
    from gyronet.stream.pty_device import Plug, fill_columns, play_plugs

    sensor = PtySensor(link)
    options = {"speed": 0, "reader_timeout_s": 20, "port_down_s": 0.2, **play_options}

    def plug(power_on: EmulatedLpms, values: Mapping[str, np.ndarray]) -> Plug:
        first = {c: float(v[0]) for c, v in fill_columns(values, power_on.layout()).items()}
        return Plug(power_on, lambda layout: plan_stream(fill_columns(values, layout), "lpbus", faults, layout),
                    first if preroll_frames else None)

    def emulate() -> None:
        try:
            if device is None:
                play(plan, sensor, **options)
            else:
                thread.plans = play_plugs([plug(device, columns), *(plug(*again) for again in replugs)], sensor,
                                          preroll_frames=preroll_frames, **options)
                thread.plan = thread.plans[0]
        finally:
            sensor.close()
            sensor.remove_link()

    thread = threading.Thread(target=emulate, daemon=True)
    thread.plan, thread.plans = plan, []
    thread.start()
    return thread


def _drop(sensor: PtySensor, plan: StreamPlan, reader_timeout_s: float, port_down_s: float,
          drain_timeout_s: float, sleep: Callable[[float], None]) -> None:
    sensor.drain(drain_timeout_s)
    sensor.close()
    log.info("port dropped for %.2f s", port_down_s)
    sleep(port_down_s)
    sensor.open()
    sensor.wait_for_reader(reader_timeout_s)
    sensor.write(plan.preamble)


def emulate_file(input_path: str | os.PathLike, protocol: str = "lpbus", speed: float = 1.0,
                 faults: FaultPlan | None = None, layout: LpBusLayout | None = None,
                 csv_columns: Sequence[str] | None = None, link: str | None = None, port_file: str | None = None,
                 log_file: str | os.PathLike | None = None, port_down_s: float = 0.5,
                 reader_timeout_s: float = 30.0, device: EmulatedLpms | None = None,
                 command_wait_s: float = 1.0) -> dict:
    """``emulate_sensor.py``: play a recording into a pty as a sensor would; return the log.

    The log (see :func:`gyronet.stream.emulator.plan_stream`) is written to ``log_file`` before
    the first sample is sent, since the plan is fixed by the seed. With ``device`` (LP-BUS only),
    the pty first answers the host's commands (``layout`` is then unused: the frames follow the
    layout the host set), and the log also holds the commands received and the final layout.
    """
    from gyronet.stream.pty_device import fill_columns, play_device

    recording = load_recording(input_path)
    if device is not None and protocol != "lpbus":
        raise GyronetError("an emulated sensor (sensor.model) speaks LP-BUS: set protocol=lpbus or sensor.model=null")

    def make_plan(frame_layout: LpBusLayout | None) -> StreamPlan:
        columns = recording.columns if device is None else fill_columns(recording.columns, frame_layout)
        try:
            plan = plan_stream(columns, protocol, faults, frame_layout, csv_columns)
        except (ValueError, KeyError) as err:
            raise GyronetError(f"{input_path}: {err}") from None
        plan.log.update(input=str(input_path), speed=speed)
        if device is not None:
            plan.log.update(sensor=device.model, layout=frame_layout.describe(), commands=list(device.commands))
        if log_file is not None:
            _write_atomic(Path(log_file), json.dumps(plan.log) + "\n")
        log.info("%d samples to send as %s, %d intact; faults planned: %s", len(recording), protocol,
                 len(plan.log["good_indices"]), plan.log["expected_faults"] or "none")
        return plan

    sensor = PtySensor(link, port_file)
    plan = None
    try:
        if device is None:
            plan = make_plan(layout)
            play(plan, sensor, speed, reader_timeout_s=reader_timeout_s, port_down_s=port_down_s)
        else:
            plan = play_device(device, make_plan, sensor, speed, command_wait_s=command_wait_s,
                               reader_timeout_s=reader_timeout_s, port_down_s=port_down_s)
        log.info("all sent")
    except KeyboardInterrupt:
        log.info("stopped")
    finally:
        sensor.close()
        sensor.remove_link()
    return plan.log if plan is not None else {}


def _write_atomic(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(path.name + ".tmp")
    temporary.write_text(text)
    os.replace(temporary, path)
