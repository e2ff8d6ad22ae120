"""Read a serial port into a framing parser; survive the port going away. The only importer of ``serial``.

Ports are opened with ``serial.serial_for_url``, so a device path (``/dev/ttyUSB0``, a pty or a
symlink to one) and pyserial's URLs (``loop://``, ``socket://``) all work.
"""
from __future__ import annotations

import logging
import os
import select
import time
from typing import Callable, Iterator, Protocol

import serial

try:
    from serial.serialposix import Serial as PosixSerial
except ImportError:  # no termios (Windows): every port goes through pyserial's read
    PosixSerial = None

from gyronet.errors import GyronetError
from gyronet.deploy.stream.events import Fault, Sample

log = logging.getLogger(__name__)

PORT_ERRORS = (serial.SerialException, OSError)
DEFAULT_BAUD = 921600  # LPMS USB sensors' factory setting (LP-Research's C client opens at 921600)


class PortError(GyronetError):
    """A serial port that cannot be opened when a run starts (a typo, a sensor not plugged in)."""


class Parser(Protocol):
    """What ``read_samples`` needs of a framing parser."""

    def feed(self, data: bytes) -> list[Sample | Fault]: ...

    def flush(self) -> list[Sample | Fault]: ...


def open_port(url: str, baud: int = DEFAULT_BAUD, timeout_s: float = 0.05) -> serial.SerialBase:
    """Open a port (device path or pyserial URL) for reading with a short timeout.

    Raises
    ------
    serial.SerialException
        When it cannot be opened.
    """
    return serial.serial_for_url(url, baudrate=baud, timeout=timeout_s)


def open_port_or_fail(url: str, baud: int = DEFAULT_BAUD, timeout_s: float = 0.05,
                      hint: str = "") -> serial.SerialBase:
    """``open_port``, with a failure as a ``PortError`` of one line (plus ``hint``)."""
    try:
        return open_port(url, baud, timeout_s)
    except PORT_ERRORS as err:
        code = getattr(err, "errno", None)  # pyserial keeps the OSError's errno
        reason = os.strerror(code) if isinstance(code, int) else str(err)
        raise PortError(f"port {url}: cannot open it ({reason}){hint}") from None


def read_samples(port: serial.SerialBase | None, parser: Parser, **options) -> Iterator[Sample | Fault]:
    """Yield the samples and faults that the bytes arriving on ``port`` make, in order, one at a time.

    :func:`read_chunks` with its chunks taken apart; the same parameters.
    """
    for chunk in read_chunks(port, parser, **options):
        yield from chunk


def read_chunks(port: serial.SerialBase | None, parser: Parser, *, url: str | None = None,
                baud: int = DEFAULT_BAUD, timeout_s: float = 0.05,
                should_stop: Callable[[], bool] | None = None, backoff_s: float = 0.1,
                max_backoff_s: float = 2.0, give_up_s: float | None = None, chunk_bytes: int = 65536,
                sleep: Callable[[float], None] = time.sleep,
                on_reopen: Callable[[serial.SerialBase], None] | None = None) -> Iterator[list[Sample | Fault]]:
    """Yield, read by read, the samples and faults that the bytes arriving on ``port`` make, in order.

    Each read takes what is waiting (at least one byte, or nothing after ``timeout_s``; then,
    without waiting, whatever else has arrived, up to ``chunk_bytes``), and the list it yields
    holds every item those bytes complete (nothing is yielded for none). So a single frame is
    yielded as soon as its last byte arrives, and a flood comes in chunks of every complete frame
    already read, which a consumer can process in one go. When the port fails (``SerialException``
    or ``OSError``), a chunk of ``Fault("port_lost")`` and what flushing the parser gives (a frame
    cut by the loss is a ``truncated`` fault) is yielded, and the port is reopened from ``url``
    with exponential backoff. The parser keeps its state (CSV header, last time) across the gap.
    A device that comes back may have been power-cycled: ``on_reopen`` sets it up (or checks it)
    again before anything is read from the new port.

    Parameters
    ----------
    port
        An open serial-like port (``read``, ``in_waiting``, ``close``), or None to open ``url``.
        The reader owns it from here on and closes it when it stops.
    parser
        A framing parser (``LpBusParser``, ``CsvLineParser``).
    url
        Where to (re)open the port; default ``port.port``. Without one, a lost port ends the
        iteration.
    baud, timeout_s
        Settings for (re)opening.
    should_stop
        Polled between reads and between reconnection attempts; True ends the iteration
        (without flushing the parser: a frame in flight is not a fault).
    backoff_s, max_backoff_s
        First and longest wait between reconnection attempts, s.
    give_up_s
        Stop after the port has been gone this long, s; None retries until ``should_stop``.
    chunk_bytes
        Most bytes taken in one read (64 KiB: more than a pty or a USB serial driver buffers).
    sleep
        Waits between attempts (a test passes a fake).
    on_reopen
        Called with the port reopened after a loss (not the first one), before it is read; an
        exception it raises ends the iteration (the port closed) and reaches the consumer.
    """
    stop = should_stop or (lambda: False)
    url = url or getattr(port, "port", None)
    lost = False
    try:
        while not stop():
            if port is None:
                port = _reopen(url, baud, timeout_s, stop, backoff_s, max_backoff_s, give_up_s, sleep)
                if port is None:
                    return
                if lost and on_reopen is not None:
                    on_reopen(port)
            try:
                data = _read_waiting(port, chunk_bytes)
            except PORT_ERRORS as err:
                log.warning("port %s lost: %s", url, err)
                yield [Fault("port_lost", detail=str(err)[:80]), *parser.flush()]
                if getattr(parser, "check", None) is not None:
                    parser.check.reopened()  # a replugged sensor's clock may start again
                _close_quietly(port)
                port, lost = None, True
                if url is None:
                    return
                continue
            if data:
                items = parser.feed(data)
                if items:
                    yield items
    finally:
        if port is not None:
            _close_quietly(port)


def _read_waiting(port: serial.SerialBase, chunk_bytes: int) -> bytes:
    """At least one byte, or nothing after the port's timeout; then whatever else already waits, never more.

    A POSIX serial port is read on its descriptor (one ``select`` and one ``read`` for a lone frame,
    where pyserial's ``read`` and ``in_waiting`` cost five system calls and most of a frame's CPU at
    1 kHz); any other port (``loop://``, ``socket://``, another platform) through pyserial.
    """
    fd = getattr(port, "fd", None) if PosixSerial is not None and isinstance(port, PosixSerial) else None
    if fd is None:
        data = port.read(min(max(1, port.in_waiting), chunk_bytes))
        # and whatever else already waits (a pty hands over 4 KiB a read), never waiting for more
        while data and len(data) < chunk_bytes and port.in_waiting:
            data += port.read(min(port.in_waiting, chunk_bytes - len(data)))
        return data
    if not select.select([fd], [], [], port.timeout)[0]:
        return b""
    data = _read_fd(fd, chunk_bytes)
    if data == b"":  # ready but empty: pyserial's sign of a device gone
        raise serial.SerialException("device reports readiness to read but returned no data (device disconnected?)")
    data = data or b""
    while len(data) < chunk_bytes and select.select([fd], [], [], 0)[0]:
        more = _read_fd(fd, chunk_bytes - len(data))
        if not more:
            break
        data += more
    return data


def _read_fd(fd: int, size: int) -> bytes | None:
    """``os.read`` on a non-blocking descriptor: what is there, up to ``size``; None on EAGAIN (a spurious wake-up)."""
    try:
        return os.read(fd, size)
    except BlockingIOError:
        return None


def _reopen(url: str | None, baud: int, timeout_s: float, stop: Callable[[], bool], backoff_s: float,
            max_backoff_s: float, give_up_s: float | None, sleep: Callable[[float], None],
            ) -> serial.SerialBase | None:
    """Open ``url``, retrying with exponential backoff; None when stopped or given up."""
    if url is None:
        return None
    delay, waited_s, attempt = backoff_s, 0.0, 0
    while not stop():
        try:
            port = open_port(url, baud, timeout_s)
        except PORT_ERRORS as err:
            attempt += 1
            if attempt == 1:
                log.info("waiting for port %s (%s)", url, err)
        else:
            log.info("port %s open", url)
            return port
        if give_up_s is not None and waited_s >= give_up_s:
            log.error("port %s still gone after %.1f s: giving up", url, waited_s)
            return None
        sleep(delay)
        waited_s += delay
        delay = min(2.0 * delay, max_backoff_s)
    return None


def _close_quietly(port: serial.SerialBase) -> None:
    try:
        port.close()
    except PORT_ERRORS:  # closing a port that is already gone
        pass
