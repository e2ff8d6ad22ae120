"""A run of back-to-back LP-BUS sensor-data frames decoded at once with numpy: the flood's fast path.

In a flood a read holds hundreds of frames, and decoding them one by one (a ``struct`` unpack, a
dict, a ``SampleCheck`` call and a ``Sample`` each) was most of the stream's CPU. Here the frames
that follow one another with nothing between them, all of the layout's length, are viewed as one
array of records: header, LRC and footer are checked, the values decoded and checked (finite,
time strictly increasing, no clock restart) for all of them at once, into a ``SampleBlock`` of
columns. The run stops before the first frame that fails any check: the per-frame parser takes
it from there, so faults, resynchronisation and new segments are what the per-frame path makes.
The arithmetic is the per-frame decode's, element by element (int or float32 to float64, one
division by the scale, one product by 180/pi), so the values are the same to the bit.
"""
from __future__ import annotations

import math

import numpy as np

from gyronet.deploy.stream.events import SampleBlock, SampleCheck, leading
from gyronet.deploy.stream.lpbus_layout import LpBusLayout

# the frame as in gyronet.deploy.stream.lpbus (which imports this module, so it cannot import them from there)
HEADER_BYTE = 0x3A
GET_SENSOR_DATA = 9
FOOTER_U16 = 0x0A0D  # b"\r\n" read as a little-endian u16
HEADER_LEN, TRAILER_LEN = 7, 4
# fewer complete frames than this in the buffer (a lone frame at 1 kHz) go frame by frame: below it the arrays'
# fixed cost is more than the per-frame decode saves
MIN_RUN_FRAMES = 16
# math.degrees(x) is x * (180 / pi) in CPython: the same product here keeps the values bit for bit
RAD_TO_DEG = 180.0 / math.pi


class FrameRun:
    """The vectorised decode of one layout's sensor-data frames (built once per layout)."""

    def __init__(self, layout: LpBusLayout):
        self.layout = layout
        self.data_length = layout.data_length
        self.frame_bytes = HEADER_LEN + self.data_length + TRAILER_LEN
        self.names = layout.columns[1:]
        value_type = "<f4" if layout.precision == 32 else "<i2"
        self.dtype = np.dtype([("start", "u1"), ("sensor_id", "<u2"), ("command", "<u2"), ("length", "<u2"),
                               ("time", "<u4" if layout.timestamp == "count" else "<f4"),
                               ("values", value_type, (len(self.names),)), ("lrc", "<u2"), ("footer", "<u2")])
        assert self.dtype.itemsize == self.frame_bytes
        plan = layout._plan  # type: ignore[attr-defined]  # (column, scale or None, to degrees)
        # x / 1.0 and x * 1.0 are x exactly, so one division and one product per column serve every column
        self.divisors = np.array([[1.0 if scale is None else float(scale)] for _, scale, _ in plan])
        self.multipliers = np.array([[RAD_TO_DEG if to_degrees else 1.0] for _, _, to_degrees in plan])
        self.unscaled = all(scale is None for _, scale, _ in plan)
        self.in_degrees = not any(to_degrees for *_, to_degrees in plan)

    def decode(self, buffer: bytearray, position: int, check: SampleCheck) -> tuple[SampleBlock | None, int]:
        """The good frames from ``position`` on, up to the first that is not (a block, or None), and their bytes.

        ``check.took`` the last good frame's time, as ``SampleCheck.check`` does.
        """
        n_frames = (len(buffer) - position) // self.frame_bytes
        if n_frames < MIN_RUN_FRAMES:
            return None, 0
        frames = np.frombuffer(buffer, dtype=self.dtype, count=n_frames, offset=position)
        ok = ((frames["start"] == HEADER_BYTE) & (frames["command"] == GET_SENSOR_DATA)
              & (frames["length"] == self.data_length) & (frames["footer"] == FOOTER_U16))
        if self.layout.sensor_id is not None:
            ok &= frames["sensor_id"] == self.layout.sensor_id
        n_good = leading(ok)  # the sums and decoding below only on these: a fault costs what precedes it
        if n_good == 0:
            return None, 0
        frames = frames[:n_good]
        raw = np.frombuffer(buffer, dtype=np.uint8, count=n_good * self.frame_bytes, offset=position)
        data = raw.reshape(n_good, self.frame_bytes)[:, HEADER_LEN:HEADER_LEN + self.data_length]
        # LRC = (id + command + length + sum of the data bytes) mod 2**16
        lrc = (frames["sensor_id"].astype(np.uint32) + (GET_SENSOR_DATA + self.data_length)
               + data.sum(axis=1, dtype=np.uint32)) & 0xFFFF
        n_good = leading(lrc == frames["lrc"])
        if n_good == 0:
            return None, 0
        frames = frames[:n_good]
        time_s = frames["time"].astype(np.float64)
        if self.layout.timestamp == "count":
            time_s /= self.layout.timestamp_hz
        values = frames["values"].T.astype(np.float64, order="C")  # one contiguous row a column
        if not self.unscaled:
            values /= self.divisors
        if not self.in_degrees:
            values *= self.multipliers
        n_good = min(n_good, leading(np.isfinite(time_s) & np.isfinite(values).all(axis=0)))
        n_good = min(n_good, leading(check.times_ok(time_s)))
        if n_good == 0:
            return None, 0
        columns = {"time_s": time_s[:n_good], **{name: values[i, :n_good] for i, name in enumerate(self.names)}}
        check.took(time_s[n_good - 1])
        return SampleBlock(columns), n_good * self.frame_bytes

