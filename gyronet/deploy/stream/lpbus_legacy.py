"""The legacy LP-BUS generation (LPMS-B, -CU, -USBAL and their "2" successors): commands, register, fields.

Every number here was read in LP-Research's own code (none of it copied):

- Command ids: OpenMAT ``LpSensor/LpmsRegisterDefinitions.h`` (``GET_CONFIG`` 4, ``GOTO_COMMAND_MODE``
  6, ``GOTO_STREAM_MODE`` 7, ``SET_TRANSMIT_DATA`` 10, ``SET_STREAM_FREQ`` 11, ``WRITE_REGISTERS`` 15,
  ``GET_IMU_ID`` 21, ``ENABLE_GYR_AUTOCAL`` 23, ``GET_FIRMWARE_VERSION`` 47, ``SET_LPBUS_DATA_MODE``
  75, ``GET_DEVICE_NAME`` 91), the same ids as OpenZen ``src/InternalTypes.h`` ``EDevicePropertyV0``.
- Configuration register (the reply to ``GET_CONFIG``): output bits and their order in a data
  frame from OpenMAT ``LpmsIoInterface.cpp`` ``parseSensorData`` and OpenZen
  ``LegacyImuProperties.cpp``; bit 22 (16-bit mode), bit 30 (gyro auto-calibration) and the stream
  rate in bits 0-2 (5, 10, 25, 50, 100, 200, 400, 800 Hz) from the same two files and
  ``LpmsRegisterDefinitions.h`` (``LPMS_STREAM_FREQ_*_ENABLED``, ``LPMS_STREAM_FREQ_MASK``).
- Values of ``SET_STREAM_FREQ`` are in Hz (``LpmsDefinitions.h`` ``SELECT_STREAM_FREQ_*``); of
  ``SET_LPBUS_DATA_MODE`` 0 = 32-bit, 1 = 16-bit (``SELECT_LPMS_LPBUS_DATA_MODE_*``).
- Units: gyro, angular velocity and Euler angles in rad/s (rad); 16-bit scales (1000, 100, 10000...)
  from ``parseSensorData``'s int16 branch (firmware >= 1.3.5, ``quaternionPrecisionFix``).
- Timestamp: a uint32 count, ``* 0.0025`` s, or ``* 0.00125`` s when the stream runs above 400 Hz
  (OpenZen ``src/components/ImuComponent.cpp``, ``timestampMultiplier``); a float32 in seconds on
  firmware before 1.3.5 (OpenMAT ``parseSensorData``'s firmware-version test).
- ``GET_FIRMWARE_VERSION`` answers three int32, patch first (OpenMAT ``LpmsIoInterface.cpp``, case
  ``GET_FIRMWARE_VERSION``: version string is i2.i1.i0); ``GET_DEVICE_NAME`` 16 characters.
"""
from __future__ import annotations

from gyronet.deploy.stream.lpbus_fields import LpBusField

ACK, NACK = 0, 1
GET_CONFIG = 4
GOTO_COMMAND_MODE, GOTO_STREAM_MODE = 6, 7
GET_SENSOR_DATA = 9
SET_TRANSMIT_DATA, SET_STREAM_FREQ = 10, 11
WRITE_REGISTERS = 15
GET_IMU_ID = 21
ENABLE_GYR_AUTOCAL = 23
GET_FIRMWARE_VERSION = 47
SET_LPBUS_DATA_MODE = 75
GET_DEVICE_NAME = 91

BIT_16BIT_MODE = 22
BIT_GYRO_AUTOCALIBRATION = 30
RATE_MASK = 0x7
RATES_HZ = (5, 10, 25, 50, 100, 200, 400, 800)  # the value of register bits 0-2 indexes this
DEVICE_NAME_BYTES = 16

# In the order the sensor sends them; (name, register bit, columns, angular, 16-bit scale).
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
OUTPUT_BITS = sum(1 << f.bit for f in FIELDS)


def rate_hz(register: int) -> int:
    """The stream rate that register bits 0-2 select, Hz."""
    return RATES_HZ[register & RATE_MASK]


def rate_bits(rate: float) -> int:
    """Register bits 0-2 for a stream rate, Hz (ValueError when the sensor has no such rate)."""
    for index, value in enumerate(RATES_HZ):
        if abs(value - rate) < 1e-9:
            return index
    raise ValueError(f"legacy LPMS sensors stream at {', '.join(map(str, RATES_HZ))} Hz, not {rate:g} Hz")


def timestamp_hz(stream_rate_hz: float) -> float:
    """The timestamp counter's rate: 400 Hz, or 800 Hz for a stream above 400 Hz (OpenZen)."""
    return 800.0 if stream_rate_hz > 400 else 400.0


def counts_time(firmware: tuple[int, int, int]) -> bool:
    """True when firmware (major, minor, patch) sends a uint32 count, False for a float32 in s.

    OpenMAT's own test, digit by digit: a float when patch <= 4 and minor <= 3 and major <= 1
    (so 1.3.4 sends a float and 1.3.5 a count).
    """
    major, minor, patch = firmware
    return not (patch <= 4 and minor <= 3 and major <= 1)
