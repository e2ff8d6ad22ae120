"""LP-BUS frames (LP-Research LPMS sensors): an incremental parser and the encoder.

Frame (all multi-byte integers little-endian)::

    0x3A | sensor id (u16) | command (u16) | data length n (u16) | data (n bytes)
         | LRC (u16) = (id + command + n + sum of the data bytes) mod 2**16 | 0x0D 0x0A

What the data of a GET_SENSOR_DATA (command 9) frame holds, the units, and the sources for both are
in :mod:`gyronet.deploy.stream.lpbus_layout`.
"""
from __future__ import annotations

import struct
from typing import Mapping, NamedTuple, Sequence

from gyronet.deploy.stream.events import Fault, Sample, SampleBlock, SampleCheck
from gyronet.deploy.stream.lpbus_layout import DEFAULT_FIELDS, LpBusLayout
from gyronet.deploy.stream.lpbus_run import FrameRun

HEADER_BYTE = 0x3A
FOOTER = b"\r\n"
GET_SENSOR_DATA = 9
HEADER_LEN = 7  # 0x3A, id, command, length
TRAILER_LEN = 4  # LRC, footer


class Header(NamedTuple):
    """The fields of a frame header."""

    sensor_id: int
    command: int
    length: int


def lrc(sensor_id: int, command: int, data: bytes) -> int:
    """LP-BUS checksum: (id + command + length + sum of data bytes) mod 2**16."""
    return (sensor_id + command + len(data) + sum(data)) & 0xFFFF


def lpbus_frame(sensor_id: int, command: int, data: bytes) -> bytes:
    """A complete LP-BUS frame around ``data``."""
    head = struct.pack("<BHHH", HEADER_BYTE, sensor_id, command, len(data))
    return head + data + struct.pack("<H", lrc(sensor_id, command, data)) + FOOTER


def encode_lpbus(sample: Sample | Mapping[str, float], layout: LpBusLayout | Sequence[str] = DEFAULT_FIELDS,
                 sensor_id: int = 1) -> bytes:
    """One GET_SENSOR_DATA frame for ``sample`` (a ``Sample`` or a row of columns)."""
    layout = layout if isinstance(layout, LpBusLayout) else LpBusLayout(fields=tuple(layout))
    row = sample.row() if isinstance(sample, Sample) else sample
    return lpbus_frame(sensor_id, GET_SENSOR_DATA, layout.encode(row))


class LpBusParser:
    """Incremental LP-BUS parser: feed bytes in any chunks, get samples and faults in stream order.

    Resynchronisation: bytes before a plausible header (see ``_header_at``) are one ``garbage``
    fault per run. A frame that fails its checks is a ``truncated`` fault when another plausible
    header starts inside it (parsing resumes there, so the good frame next to a cut one is kept),
    else a ``bad_checksum`` or ``bad_footer`` fault and parsing resumes after it. A good frame of
    another length than the layout's is a ``bad_length`` fault: the sensor sends other fields
    than ``layout.fields``. While a first-frames check (``probe``) is undecided, what the frames
    make is held back, so a misread the check refuses never reaches the consumer.

    Parameters
    ----------
    layout
        What the sensor-data frames hold.
    max_length
        Longest data block believed, bytes.
    check
        The time and value checks (default ``SampleCheck()``).
    blocks
        Good frames in a row (a flood) come out as one ``SampleBlock`` of columns, decoded at
        once (:mod:`.lpbus_run`), instead of one ``Sample`` each: the same samples, faults and
        order (``events.as_samples`` takes the blocks apart), for a consumer that takes columns.

    Notes
    -----
    The LRC is a 16-bit sum: damage that keeps the sum (two changes that cancel, a byte moved)
    passes it, and such a frame is decoded as a good one. The value checks (finite, time) and
    the fixed length still apply to it.
    """

    def __init__(self, layout: LpBusLayout | None = None, max_length: int = 512, check: SampleCheck | None = None,
                 blocks: bool = False):
        self.layout = layout or LpBusLayout()
        self.blocks = blocks
        self._run = FrameRun(self.layout)
        self.max_length = max(max_length, self.layout.data_length)
        self.check = check or SampleCheck()
        self._buffer = bytearray()
        self._garbage = bytearray()
        self.probe = None  # a first-frames layout check (gyronet.deploy.stream.lpbus_probe.FirstFrames), or None
        self._held: list[Sample | Fault] = []  # what the frames made while the probe was undecided

    @property
    def columns(self) -> list[str]:
        return self.layout.columns

    def prime(self, data: bytes) -> None:
        """Bytes read before the sample loop (what followed the set-up's last answer): parsed with the next feed."""
        self._buffer += data

    def feed(self, data: bytes) -> list[Sample | SampleBlock | Fault]:
        """Parse what ``data`` completes; keep the rest for the next call."""
        self._buffer += data
        out: list[Sample | SampleBlock | Fault] = []
        position = self._consume(out, final=False)
        del self._buffer[:position]
        return self._release(out)

    def flush(self) -> list[Sample | SampleBlock | Fault]:
        """End of stream (or of a connection): parse what can be, report what is left as cut."""
        out: list[Sample | SampleBlock | Fault] = []
        position = self._consume(out, final=True)
        rest = bytes(self._buffer[position:])
        self._buffer.clear()
        self._flush_garbage(out)
        if rest:
            out.append(Fault("truncated", rest, "stream ended inside a frame"))
        return self._release(out, final=True)

    def _release(self, out: list, final: bool = False) -> list[Sample | SampleBlock | Fault]:
        """``out``, or nothing while the probe is undecided; at the end, the probe judges the frames it has."""
        if self.probe is None and not self._held:
            return out
        self._held += out
        if self.probe is not None:
            if not final:
                return []
            probe, self.probe = self.probe, None
            if probe.frames:
                probe.check()  # raises LayoutError: the held frames are misread
        out, self._held = self._held, []
        return out

    def _consume(self, out: list, final: bool) -> int:
        """Parse from the start of the buffer; return how many bytes are done with."""
        buffer, position = self._buffer, 0
        while True:
            start = buffer.find(HEADER_BYTE, position)
            if start < 0:
                self._garbage += buffer[position:]
                return len(buffer)
            self._garbage += buffer[position:start]
            position = start
            if len(buffer) - position < HEADER_LEN:
                return position  # perhaps a header: wait (at the end, a cut frame)
            header = self._header_at(position)
            if header is None:
                self._garbage.append(HEADER_BYTE)
                position += 1
                continue
            self._flush_garbage(out)
            # a first-frames check sees every frame: not while it runs
            if self.blocks and self.probe is None and header.length == self.layout.data_length:
                block, step = self._run.decode(buffer, position, self.check)
                if block is not None:
                    out.append(block)
                    position += step
                    continue
            step = self._frame(position, header, out, final)
            if step is None:
                return position
            position += step

    def _header_at(self, position: int) -> Header | None:
        """The header at ``position`` when it is plausible, else None (also when incomplete).

        Plausible: GET_SENSOR_DATA, the configured sensor id (if any), a length of at most
        ``max_length``. Other commands are not accepted: a streaming sensor sends none, and the
        zeros common in sensor data (0x3A, id, 00 00, 00 00) would pass for an empty ACK.
        """
        if len(self._buffer) - position < HEADER_LEN:
            return None
        _, sensor_id, command, length = struct.unpack_from("<BHHH", self._buffer, position)
        if command != GET_SENSOR_DATA or length > self.max_length:
            return None
        if self.layout.sensor_id not in (None, sensor_id):
            return None
        return Header(sensor_id, command, length)

    def _frame(self, position: int, header: Header, out: list, final: bool) -> int | None:
        """Handle the frame at ``position``; return how far to advance (None: wait for bytes)."""
        total = HEADER_LEN + header.length + TRAILER_LEN
        available = len(self._buffer) - position
        checksum_ok = False
        if available >= total:
            frame = bytes(self._buffer[position:position + total])
            data = frame[HEADER_LEN:HEADER_LEN + header.length]
            (received,) = struct.unpack_from("<H", frame, HEADER_LEN + header.length)
            checksum_ok = received == lrc(header.sensor_id, header.command, data)
            if checksum_ok and frame.endswith(FOOTER):
                out.append(self._good_frame(header, data, frame))
                return total
        elif not final:
            return None  # deciding before the whole frame is in would depend on the chunking
        inner = self._inner_header(position, min(total, available), final)
        if inner is None:
            return None
        if inner:
            out.append(Fault("truncated", bytes(self._buffer[position:position + inner]),
                             "the next frame starts inside it"))
            return inner
        if available < total:
            return None  # flush reports the rest as cut
        out.append(Fault("bad_footer" if checksum_ok else "bad_checksum", frame))
        return total

    def _inner_header(self, position: int, span: int, final: bool) -> int | None:
        """Offset of the first plausible header inside the frame (0: none; None: cannot tell yet)."""
        for offset in range(1, span):
            if self._buffer[position + offset] != HEADER_BYTE:
                continue
            if self._header_at(position + offset) is not None:
                return offset
            if len(self._buffer) - position - offset < HEADER_LEN and not final:
                return None
        return 0

    def _good_frame(self, header: Header, data: bytes, frame: bytes) -> Sample | Fault:
        if header.length != self.layout.data_length:
            return Fault("bad_length", frame, f"{header.length} data bytes, fields {list(self.layout.fields)} "
                                              f"need {self.layout.data_length}")
        time_s, values = self.layout.decode(data)
        if self.probe is not None:
            self.probe.see(time_s, values)  # raises LayoutError when the first frames do not fit the layout
            if self.probe.done:
                self.probe = None  # checked: no cost per frame from here on
        return self.check.check(time_s, values, frame)

    def _flush_garbage(self, out: list) -> None:
        if self._garbage:
            out.append(Fault("garbage", bytes(self._garbage), f"{len(self._garbage)} bytes"))
            self._garbage.clear()
