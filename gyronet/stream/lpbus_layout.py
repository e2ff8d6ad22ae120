"""What an LP-BUS sensor-data frame holds (LP-Research LPMS sensors, the paper's LPMS-USBAL2).

The frame itself is described in :mod:`gyronet.stream.lpbus`. A streaming sensor sends command 9
(GET_SENSOR_DATA). Its data is a timestamp followed by the channels its configuration register
enables, always in this order (bit of the register in brackets): raw gyro (12), raw acc (11), raw mag (10), angular velocity (16), quaternion (18),
Euler angles (17), linear acceleration (21), pressure (9), altitude (19), temperature (13), heave
(14). In the default 32-bit mode every value is a float32; with bit 22 set (16-bit mode) every value
is an int16 scaled by a fixed factor (``LpBusField.scale_16bit``; quaternion, Euler and heave use
the finer scales of firmware >= 1.3.5, LpSensor's ``quaternionPrecisionFix``).

Units on the wire: gyro, angular velocity and Euler angles in rad/s (rad), converted here to deg/s
(deg); acceleration in g; magnetic field in uT; temperature in degC. The timestamp is a uint32 count
of a 400 Hz clock (firmware 1.3.5 and later; ``timestamp="count"``) or, on older firmware, a float32
in seconds (``timestamp="float"``).

Sources (LP-Research's own code, read for the layout, none of it copied):

- OpenMAT ``LpSensor/LpmsIoInterface.cpp``, ``parseSensorData`` (github.com/xkh500/openmat, a copy
  of LP-Research's OpenMAT): field order, rad -> deg (``r2d``), the 16-bit scales, and the
  firmware >= 1.3.5 timestamp counter divided by 400.
- OpenMAT ``LpSensorForAndroid/LpmsB2.java``: the frame, the LRC and its 16-bit mask, the
  configuration-register bits, 400 Hz timestamp ticks (``* 0.0025f``).
- Public copies of OpenMAT's C client (``LpmsIoInterfaceC.c``: ``lpmsSendModbusData`` builds the
  frame, ``lpmsParseModbusByte`` checks it) and of the LPMS firmware (``getSensorData``: the
  sender's side of the same order).
- OpenZen ``src/components/ImuComponent.cpp`` and ``LegacyImuProperties.cpp``
  (github.com/witted-research/openzen): the same order and bits for the legacy (LP-BUS) sensors.

Assumptions not verified against a physical LPMS-USBAL2: that its firmware is >= 1.3.5 (else set
``timestamp="float"``); that pressure is in kPa and heave/altitude in m (only their order matters
here); that the raw gyro channel is what the temperature model needs. Gyro auto-calibration
(register bit 30) must be off, or the sensor itself removes part of the drift.
"""
from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from typing import Mapping

BIT_16BIT_MODE = 22
TICKS_PER_S = 400.0


@dataclass(frozen=True)
class LpBusField:
    """One channel group of GET_SENSOR_DATA."""

    name: str
    bit: int  # bit of the configuration register that enables it
    columns: tuple[str, ...]
    radians: bool  # sent in rad or rad/s, given here in deg or deg/s
    scale_16bit: float  # int16 / scale = value in 16-bit mode


# In the order the sensor sends them.
FIELDS: tuple[LpBusField, ...] = (
    LpBusField("gyro", 12, ("gyro_x_dps", "gyro_y_dps", "gyro_z_dps"), True, 1000.0),
    LpBusField("acc", 11, ("acc_x_g", "acc_y_g", "acc_z_g"), False, 1000.0),
    LpBusField("mag", 10, ("mag_x_ut", "mag_y_ut", "mag_z_ut"), False, 100.0),
    LpBusField("angular_velocity", 16, ("angvel_x_dps", "angvel_y_dps", "angvel_z_dps"), True, 1000.0),
    LpBusField("quaternion", 18, ("quat_w", "quat_x", "quat_y", "quat_z"), False, 10000.0),
    LpBusField("euler", 17, ("euler_x_deg", "euler_y_deg", "euler_z_deg"), True, 10000.0),
    LpBusField("linear_acc", 21, ("linacc_x_g", "linacc_y_g", "linacc_z_g"), False, 1000.0),
    LpBusField("pressure", 9, ("pressure_kpa",), False, 100.0),
    LpBusField("altitude", 19, ("altitude_m",), False, 10.0),
    LpBusField("temperature", 13, ("temp_c",), False, 100.0),
    LpBusField("heave", 14, ("heave_m",), False, 1000.0),
)
FIELDS_BY_NAME = {f.name: f for f in FIELDS}
DEFAULT_FIELDS = ("gyro", "acc", "temperature")


@dataclass(frozen=True)
class LpBusLayout:
    """What a GET_SENSOR_DATA frame holds.

    Parameters
    ----------
    fields
        Enabled channel groups, names of ``FIELDS`` (any order: the protocol fixes the order).
    precision
        32 (float32 values) or 16 (scaled int16 values, register bit 22).
    timestamp
        ``"count"``: uint32 ticks of ``timestamp_hz`` (firmware >= 1.3.5); ``"float"``: float32 s.
    timestamp_hz
        Tick rate of the ``"count"`` timestamp, Hz.
    sensor_id
        Accept only frames of this sensor id; None accepts any.
    """

    fields: tuple[str, ...] = DEFAULT_FIELDS
    precision: int = 32
    timestamp: str = "count"
    timestamp_hz: float = TICKS_PER_S
    sensor_id: int | None = None

    def __post_init__(self) -> None:
        unknown = [f for f in self.fields if f not in FIELDS_BY_NAME]
        if unknown:
            raise ValueError(f"unknown LP-BUS field(s) {unknown}; known: {list(FIELDS_BY_NAME)}")
        if self.precision not in (16, 32):
            raise ValueError(f"LP-BUS precision is 16 or 32, got {self.precision}")
        if self.timestamp not in ("count", "float"):
            raise ValueError(f"LP-BUS timestamp is 'count' or 'float', got {self.timestamp!r}")
        ordered = tuple(f.name for f in FIELDS if f.name in self.fields)
        object.__setattr__(self, "fields", ordered)

    @classmethod
    def from_config_register(cls, register: int, **kwargs) -> "LpBusLayout":
        """The layout a sensor with this configuration register (GET_CONFIG) sends."""
        fields = tuple(f.name for f in FIELDS if register >> f.bit & 1)
        precision = 16 if register >> BIT_16BIT_MODE & 1 else 32
        return cls(fields=fields, precision=precision, **kwargs)

    @property
    def config_register(self) -> int:
        """The output bits of the configuration register (stream-rate bits left at 0)."""
        bits = sum(1 << FIELDS_BY_NAME[name].bit for name in self.fields)
        return bits | ((1 << BIT_16BIT_MODE) if self.precision == 16 else 0)

    @property
    def columns(self) -> list[str]:
        """The CONTRACT.md columns a frame gives, ``time_s`` first."""
        return ["time_s", *(c for name in self.fields for c in FIELDS_BY_NAME[name].columns)]

    @property
    def _value_format(self) -> str:
        n_values = len(self.columns) - 1
        return "<" + ("I" if self.timestamp == "count" else "f") + ("f" if self.precision == 32 else "h") * n_values

    @property
    def data_length(self) -> int:
        """Bytes of GET_SENSOR_DATA data."""
        return struct.calcsize(self._value_format)

    def encode(self, row: Mapping[str, float]) -> bytes:
        """The data of a GET_SENSOR_DATA frame for one sample (``row`` maps columns to values)."""
        missing = [c for c in self.columns if c not in row]
        if missing:
            raise KeyError(f"LP-BUS fields {list(self.fields)} need column(s) {missing}")
        values = [self._encode_time(float(row["time_s"]))]
        for name in self.fields:
            spec = FIELDS_BY_NAME[name]
            for column in spec.columns:
                value = float(row[column])
                value = math.radians(value) if spec.radians else value
                values.append(value if self.precision == 32 else _to_int16(value * spec.scale_16bit, column))
        return struct.pack(self._value_format, *values)

    def decode(self, data: bytes) -> tuple[float, dict[str, float]]:
        """Time, s, and the other columns of one GET_SENSOR_DATA data block."""
        raw = struct.unpack(self._value_format, data)
        time_s = raw[0] / self.timestamp_hz if self.timestamp == "count" else float(raw[0])
        values: dict[str, float] = {}
        position = 1
        for name in self.fields:
            spec = FIELDS_BY_NAME[name]
            for column in spec.columns:
                value = float(raw[position]) if self.precision == 32 else raw[position] / spec.scale_16bit
                values[column] = math.degrees(value) if spec.radians else value
                position += 1
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


