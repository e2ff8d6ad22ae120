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

With an emulated sensor (:class:`~gyronet.deploy.stream.lpbus_device.EmulatedLpms`,
:func:`gyronet.deploy.stream.pty_device.play_device`) the pty also answers the host's commands before it
streams: the plan is then framed in the layout the host left the sensor in. A host that sends
nothing within ``command_wait_s`` gets the sensor's power-on layout (a passive reader).
"""
from __future__ import annotations

import fcntl
import logging
import os
import struct
import termios
import time
import tty
from pathlib import Path
from typing import Callable

from gyronet.atomic import write_text
from gyronet.errors import ConfigError
from gyronet.deploy.stream.emulator import StreamPlan

log = logging.getLogger(__name__)

_MARKER_SPEED = termios.B50
_POLL_S = 0.01
_QUIET_POLLS = 10  # drain: this many polls in a row find nothing unread
PTY_PREFIXES = ("/dev/pts/", "/dev/ttys", "/dev/ttyp")  # where os.openpty's slaves live (Linux, macOS, BSD)


class PtySensor:
    """One pty at a time, with an optional symlink and port file naming its slave.

    Parameters
    ----------
    link
        Symlink re-pointed to the current slave device: a path that is missing or a symlink to a pty
        (an earlier emulator's), else refused (:func:`check_link`).
    port_file
        File that holds the current slave path (written atomically).
    """

    def __init__(self, link: str | os.PathLike | None = None, port_file: str | os.PathLike | None = None):
        self.link = Path(link) if link else None
        if self.link is not None:
            check_link(self.link)
        self.port_file = Path(port_file) if port_file else None
        if self.port_file is not None:
            check_port_file(self.port_file)
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
            write_text(self.port_file, self.path + "\n")
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
        after a write proves nothing: it must stay empty for ``quiet_s``, seen so by consecutive polls
        (a poll late by more than ``quiet_s``, this thread starved on a loaded machine, is not a quiet window).
        """
        deadline = time.monotonic() + timeout_s
        quiet_since, empty_polls = time.monotonic(), 0
        while empty_polls < _QUIET_POLLS or time.monotonic() - quiet_since < quiet_s:
            if self.unread_bytes() > 0:
                quiet_since, empty_polls = time.monotonic(), 0
                if quiet_since > deadline:
                    log.warning("reader left %d bytes unread on %s", self.unread_bytes(), self.path)
                    return False
            else:
                empty_polls += 1
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


def check_link(link: Path) -> None:
    """Refuse a ``link`` that the emulator would replace and remove at exit, were it a file or a device node, or
    that it cannot create: only a missing path or a symlink to a pty (and the same for its ``.tmp``) is its own."""
    if not link.parent.is_dir():
        raise ConfigError(f"link={link}: its folder {link.parent} does not exist")
    for path in (link, link.with_name(link.name + ".tmp")):
        if path.is_symlink():
            target = os.readlink(path)
            if not target.startswith(PTY_PREFIXES):
                raise ConfigError(f"link={link}: {path} is a symlink to {target}, not to a pty; the emulator would "
                                  "replace it: give link= a path that does not exist")
        elif os.path.lexists(path):
            raise ConfigError(f"link={link}: {path} exists and is not a symlink; the emulator would replace it and "
                              "remove it at exit: give link= a path that does not exist")


def check_port_file(path: Path) -> None:
    """Refuse a ``port_file`` that holds anything but an earlier emulator's pty path: it is rewritten at every (re)open."""
    if os.path.lexists(path):
        text = path.read_bytes()[:200] if path.is_file() else b""
        if not (len(text) < 200 and text.decode("latin-1").strip().startswith(PTY_PREFIXES)):
            raise ConfigError(f"port_file={path} exists and holds no pty path; the emulator would replace it: give "
                              "port_file= a path that does not exist")


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


def _drop(sensor: PtySensor, plan: StreamPlan, reader_timeout_s: float, port_down_s: float,
          drain_timeout_s: float, sleep: Callable[[float], None]) -> None:
    sensor.drain(drain_timeout_s)
    sensor.close()
    log.info("port dropped for %.2f s", port_down_s)
    sleep(port_down_s)
    sensor.open()
    sensor.wait_for_reader(reader_timeout_s)
    sensor.write(plan.preamble)
