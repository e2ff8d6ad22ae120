"""Commands to an LP-BUS sensor and its replies: the request/answer half of the protocol.

A command is a frame like any other (:func:`gyronet.deploy.stream.lpbus.lpbus_frame`), sent to address 0
as OpenZen's ``LpFrameFactory::makeFrame`` and the IG1 library's ``sendCommand`` do. The sensor
answers a get with a frame of the same command id and the value, a set with an ACK (command 0)
or NACK (command 1) without data (OpenMAT ``LpmsIoInterface.cpp``, ``REPLY_ACK``/``REPLY_NACK``).
Sensor-data frames still in flight while the sensor leaves streaming are skipped.

An ACK carries no command id, so one that comes after its command timed out could pass for the
answer to the next set. The sensor answers in order, so after a timeout the link first asks
``SYNC`` (command 21, answered in both generations by a frame of its own id): every late reply
arrives before that answer and is skipped. Only the same command sent again (command mode, retried)
takes any ACK, since each attempt's ACK means the same.
"""
from __future__ import annotations

import logging
import struct
import time
from typing import Callable, Iterator

from gyronet.errors import GyronetError
from gyronet.deploy.stream.lpbus import FOOTER, HEADER_BYTE, HEADER_LEN, TRAILER_LEN, lpbus_frame, lrc

log = logging.getLogger(__name__)

ACK, NACK = 0, 1
SENSOR_DATA = 9
SYNC = 21  # legacy GET_IMU_ID, IG1 GET_FIRMWARE_INFO: a get either generation answers
MAX_REPLY_BYTES = 512


class SensorError(GyronetError):
    """A sensor that does not answer, refuses a command, or answers what gyronet cannot use."""


class FrameReader:
    """Whole LP-BUS frames of any command out of a byte stream (bytes that frame nothing are skipped)."""

    def __init__(self) -> None:
        self._buffer = bytearray()

    def rest(self) -> bytes:
        """The bytes not yet framed (the start of what follows the last frame taken)."""
        return bytes(self._buffer)

    def feed(self, data: bytes) -> Iterator[tuple[int, int, bytes]]:
        """Yield ``(sensor_id, command, data)`` for every complete frame ``data`` finishes."""
        self._buffer += data
        buffer = self._buffer
        while True:
            start = buffer.find(HEADER_BYTE)
            if start < 0:
                buffer.clear()
                return
            del buffer[:start]
            if len(buffer) < HEADER_LEN:
                return
            _, sensor_id, command, length = struct.unpack_from("<BHHH", buffer)
            if length > MAX_REPLY_BYTES:
                del buffer[:1]
                continue
            total = HEADER_LEN + length + TRAILER_LEN
            if len(buffer) < total:
                return
            payload = bytes(buffer[HEADER_LEN:HEADER_LEN + length])
            (received,) = struct.unpack_from("<H", buffer, HEADER_LEN + length)
            if received != lrc(sensor_id, command, payload) or bytes(buffer[total - 2:total]) != FOOTER:
                del buffer[:1]  # a 0x3A inside other bytes: look for the next one
                continue
            del buffer[:total]
            yield sensor_id, command, payload


class LpBusLink:
    """Send commands to a sensor on an open port and wait for their answers.

    Parameters
    ----------
    port
        An open serial-like port (``read``, ``write``, ``in_waiting``).
    timeout_s
        How long to wait for one answer, s.
    address
        The sensor address commands go to (0, as OpenZen sends them).
    """

    def __init__(self, port, timeout_s: float = 1.0, address: int = 0,
                 clock: Callable[[], float] = time.monotonic):
        self.port, self.timeout_s, self.address, self.clock = port, float(timeout_s), int(address), clock
        self.reader = FrameReader()
        self.skipped_data_frames = 0
        self.unanswered = 0  # commands that timed out: their replies may still come, before any later one

    def send(self, command: int, data: bytes = b"") -> None:
        self.port.write(lpbus_frame(self.address, command, data))
        flush = getattr(self.port, "flush", None)
        if flush is not None:
            flush()

    def ask(self, command: int, name: str, data: bytes = b"") -> bytes:
        """Send a get and return the data of its answer (a frame of the same command)."""
        if self.unanswered and command != SYNC:
            self.ask(SYNC, "GET_IMU_ID / GET_FIRMWARE_INFO (to pass late replies)")
        self.send(command, data)
        return self._wait(command, name)

    def ask_int(self, command: int, name: str) -> int:
        """A get whose answer is one uint32."""
        reply = self.ask(command, name)
        if len(reply) != 4:
            raise SensorError(f"the sensor answered {name} (command {command}) with {len(reply)} bytes, not 4")
        return struct.unpack("<I", reply)[0]

    def set(self, command: int, name: str, data: bytes = b"", again: bool = False) -> None:
        """Send a set (or a mode change) and wait for its ACK.

        ``again``: the same command, sent again after its timeout; an ACK to either attempt will do.
        """
        if self.unanswered and not again:
            self.ask(SYNC, "GET_IMU_ID / GET_FIRMWARE_INFO (to pass late replies)")
        self.send(command, data)
        self._wait(ACK, name, sent=command)

    def set_int(self, command: int, name: str, value: int) -> None:
        self.set(command, name, struct.pack("<I", int(value)))

    def _wait(self, command: int, name: str, sent: int | None = None) -> bytes:
        sent = command if sent is None else sent
        deadline = self.clock() + self.timeout_s
        while self.clock() < deadline:
            data = self.port.read(max(1, min(self.port.in_waiting, 4096)))
            for _, got, payload in self.reader.feed(data):
                if got == SENSOR_DATA:
                    self.skipped_data_frames += 1
                elif got == command:
                    if command != ACK:
                        self.unanswered = 0  # a get's answer comes after every earlier reply
                    return payload
                elif got in (ACK, NACK) and self.unanswered and command != ACK:
                    self.unanswered -= 1
                    log.debug("skipped a late %s while waiting for %s", "ACK" if got == ACK else "NACK", name)
                elif got == NACK:
                    raise SensorError(f"the sensor refused {name} (command {sent}, NACK)")
                else:
                    log.debug("skipped a reply to command %d while waiting for %s", got, name)
        self.unanswered += 1
        raise SensorError(f"no answer to {name} (command {sent}) within {self.timeout_s:g} s: is this an "
                          "LP-Research LPMS sensor, at this baud rate? (lpbus.configure=false only listens)")
