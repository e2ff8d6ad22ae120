"""What an LP-BUS sensor-data frame holds, for both LP-BUS generations (LP-Research LPMS sensors).

The frame itself is described in :mod:`gyronet.deploy.stream.lpbus`. A streaming sensor sends command 9
(GET_SENSOR_DATA). Its data is a timestamp followed by the channels its output register enables,
always in the generation's own order: legacy sensors (LPMS-B/CU/USBAL and B2/CU2/USBAL2, the
paper's LPMS-USBAL2; :mod:`.lpbus_legacy`) send raw gyro (bit 12), raw acc (11), raw mag (10),
angular velocity (16), quaternion (18), Euler angles (17), linear acceleration (21), pressure (9),
altitude (19), temperature (13), heave (14); IG1-family sensors (IG1, BE1, ME1; :mod:`.lpbus_ig1`)
send the accelerometer first and use other bits. In 32-bit mode every value is a float32; in
16-bit mode an int16 scaled by a fixed factor (``LpBusField.scale``).

Units on the wire: legacy gyro, angular velocity and Euler angles in rad/s (rad); IG1 in deg/s
(deg) unless set to radians; all given here in deg/s (deg). Acceleration in g, magnetic field in
uT, temperature in degC. The timestamp is a uint32 count of a clock whose rate depends on the
generation and the stream rate (legacy 400 Hz, 800 Hz above a 400 Hz stream; IG1 500 Hz;
``timestamp="count"``) or, on legacy firmware before 1.3.5, a float32 in seconds (``"float"``).
Each rule names the reference file it was checked against in its generation's module.

Assumptions not verified against a physical sensor: that pressure is in kPa and heave/altitude in
m (only their order matters here); that the raw gyro channel is what the temperature model needs.
Gyro auto-calibration (legacy register bit 30, IG1 command 64) must be off, or the sensor itself
removes part of the drift: :mod:`.lpbus_config` switches it off.
"""
from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from typing import Mapping

from gyronet.deploy.stream import lpbus_ig1, lpbus_legacy
from gyronet.deploy.stream.lpbus_fields import LpBusField

GENERATIONS = ("legacy", "ig1")
BIT_16BIT_MODE = lpbus_legacy.BIT_16BIT_MODE
TICKS_PER_S = 400.0
FIELDS: tuple[LpBusField, ...] = lpbus_legacy.FIELDS  # the legacy table (kept for old callers)
DEFAULT_FIELDS = ("gyro", "acc", "temperature")


def generation_fields(generation: str, primary_gyro: int = 0) -> tuple[LpBusField, ...]:
    """The fields of a generation, in the order its frames carry them."""
    if generation == "legacy":
        return lpbus_legacy.FIELDS
    if generation == "ig1":
        return lpbus_ig1.fields(primary_gyro)
    raise ValueError(f"LP-BUS generation is one of {GENERATIONS}, got {generation!r}")


@dataclass(frozen=True)
class LpBusLayout:
    """What a GET_SENSOR_DATA frame holds.

    Parameters
    ----------
    fields
        Enabled channel groups, names of the generation's fields (any order: the protocol fixes it).
    precision
        32 (float32 values) or 16 (scaled int16 values).
    timestamp
        ``"count"``: uint32 ticks of ``timestamp_hz``; ``"float"``: float32 s (legacy firmware < 1.3.5).
    timestamp_hz
        Tick rate of the ``"count"`` timestamp, Hz (None: the generation's, 400 or 500 Hz).
    sensor_id
        Accept only frames of this sensor id; None accepts any.
    generation
        ``"legacy"`` (LPMS-B/CU/USBAL, B2/CU2/USBAL2) or ``"ig1"`` (IG1, BE1, ME1...).
    radians
        The sensor sends rates and angles in rad/s (rad); None: the generation's default (legacy
        always radians, IG1 degrees).
    primary_gyro
        IG1 only: which of its two gyros is ``gyro`` (``gyro_*_dps``); 1 on an LPMS-BE1.
    """

    fields: tuple[str, ...] = DEFAULT_FIELDS
    precision: int = 32
    timestamp: str = "count"
    timestamp_hz: float | None = None
    sensor_id: int | None = None
    generation: str = "legacy"
    radians: bool | None = None
    primary_gyro: int = 0

    def __post_init__(self) -> None:
        table = generation_fields(self.generation, self.primary_gyro)
        known = [f.name for f in table]
        unknown = [f for f in self.fields if f not in known]
        if unknown:
            raise ValueError(f"unknown LP-BUS field(s) {unknown} for {self.generation} sensors; known: {known}")
        if self.precision not in (16, 32):
            raise ValueError(f"LP-BUS precision is 16 or 32, got {self.precision}")
        if self.timestamp not in ("count", "float"):
            raise ValueError(f"LP-BUS timestamp is 'count' or 'float', got {self.timestamp!r}")
        if self.generation == "legacy" and self.radians is False:
            raise ValueError("legacy LPMS sensors always send radians (radians=false is IG1 only)")
        if self.generation == "ig1" and self.timestamp == "float":
            raise ValueError("IG1 sensors send a uint32 timestamp count (timestamp=float is legacy firmware only)")
        object.__setattr__(self, "fields", tuple(f.name for f in table if f.name in self.fields))
        if self.timestamp_hz is None:
            object.__setattr__(self, "timestamp_hz", TICKS_PER_S if self.generation == "legacy"
                               else lpbus_ig1.TIMESTAMP_HZ)
        if self.radians is None:
            object.__setattr__(self, "radians", self.generation == "legacy")
        object.__setattr__(self, "_specs", tuple(f for f in table if f.name in self.fields))
        # built once: a frame's decode is then one unpack and one pass (10 us -> 2 us a frame)
        object.__setattr__(self, "_struct", struct.Struct(self._value_format))
        object.__setattr__(self, "_plan", tuple(
            (column, None if self.precision == 32 else spec.scale(self.radians), spec.angular and self.radians)
            for spec in self._specs for column in spec.columns))

    @classmethod
    def from_config_register(cls, register: int, **kwargs) -> "LpBusLayout":
        """The layout a legacy sensor with this configuration register (GET_CONFIG) sends."""
        fields = tuple(f.name for f in FIELDS if register >> f.bit & 1)
        precision = 16 if register >> BIT_16BIT_MODE & 1 else 32
        return cls(fields=fields, precision=precision, **kwargs)

    @classmethod
    def from_transmit_register(cls, register: int, precision: int = 32, primary_gyro: int = 0,
                               **kwargs) -> "LpBusLayout":
        """The layout an IG1 sensor with this output register (GET_IMU_TRANSMIT_DATA) sends.

        Raises ValueError naming the bits when the register enables outputs the IG1 references
        do not list (bits above 16): their size and place in the frame are unknown.
        """
        unknown = [b for b in range(32) if register >> b & 1 and not lpbus_ig1.OUTPUT_BITS >> b & 1]
        if unknown:
            raise ValueError(f"IG1 output register 0x{register:08x} sets bit(s) {unknown}, which no reference "
                             "lists (OpenZen Ig1ImuProperties.cpp, LpmsIG1Registers.h: bits 0-16)")
        table = lpbus_ig1.fields(primary_gyro)
        fields = tuple(f.name for f in table if register >> f.bit & 1)
        return cls(fields=fields, precision=precision, generation="ig1", primary_gyro=primary_gyro, **kwargs)

    @property
    def specs(self) -> tuple[LpBusField, ...]:
        """The enabled fields, in frame order."""
        return self._specs  # type: ignore[attr-defined]

    @property
    def config_register(self) -> int:
        """The output bits of the register (legacy: with bit 22 in 16-bit mode; stream-rate bits at 0)."""
        bits = sum(1 << spec.bit for spec in self.specs)
        if self.generation == "legacy" and self.precision == 16:
            bits |= 1 << BIT_16BIT_MODE
        return bits

    @property
    def columns(self) -> list[str]:
        """The CONTRACT.md columns a frame gives, ``time_s`` first."""
        return ["time_s", *(c for spec in self.specs for c in spec.columns)]

    @property
    def _value_format(self) -> str:
        n_values = len(self.columns) - 1
        return "<" + ("I" if self.timestamp == "count" else "f") + ("f" if self.precision == 32 else "h") * n_values

    @property
    def data_length(self) -> int:
        """Bytes of GET_SENSOR_DATA data."""
        return self._struct.size  # type: ignore[attr-defined]

    def describe(self) -> str:
        """One line: generation, fields, precision, timestamp."""
        clock = f"{self.timestamp_hz:g} Hz ticks" if self.timestamp == "count" else "float s"
        unit = "rad" if self.radians else "deg"
        return (f"{self.generation} LP-BUS, fields {list(self.fields)}, {self.precision}-bit, {unit}, "
                f"timestamp {clock}, {self.data_length} data bytes")

    def encode(self, row: Mapping[str, float]) -> bytes:
        """The data of a GET_SENSOR_DATA frame for one sample (``row`` maps columns to values)."""
        missing = [c for c in self.columns if c not in row]
        if missing:
            raise KeyError(f"LP-BUS fields {list(self.fields)} need column(s) {missing}")
        values = [self._encode_time(float(row["time_s"]))]
        for spec in self.specs:
            scale = spec.scale(self.radians)
            for column in spec.columns:
                value = float(row[column])
                value = math.radians(value) if spec.angular and self.radians else value
                values.append(value if self.precision == 32 else _to_int16(value * scale, column))
        return self._struct.pack(*values)  # type: ignore[attr-defined]

    def decode(self, data: bytes) -> tuple[float, dict[str, float]]:
        """Time, s, and the other columns of one GET_SENSOR_DATA data block."""
        raw = self._struct.unpack(data)  # type: ignore[attr-defined]
        time_s = raw[0] / self.timestamp_hz if self.timestamp == "count" else float(raw[0])
        values: dict[str, float] = {}
        for (column, scale, to_degrees), number in zip(self._plan, raw[1:]):  # type: ignore[attr-defined]
            value = float(number) if scale is None else number / scale
            values[column] = math.degrees(value) if to_degrees else value
        return time_s, values

    def _encode_time(self, time_s: float) -> float | int:
        if self.timestamp == "float":
            return time_s
        ticks = round(time_s * self.timestamp_hz)
        if not 0 <= ticks < 2 ** 32:
            raise ValueError(f"time_s={time_s} does not fit the uint32 LP-BUS timestamp")
        return ticks

    def quantize(self, row: Mapping[str, float]) -> dict[str, float]:
        """``row`` as it reads after a trip through LP-BUS (float32 or int16 rounding)."""
        time_s, values = self.decode(self.encode(row))
        return {"time_s": time_s, **values}


def _to_int16(value: float, column: str) -> int:
    scaled = round(value)
    if not -32768 <= scaled <= 32767:
        raise ValueError(f"{column}: {value} does not fit LP-BUS 16-bit mode")
    return scaled
