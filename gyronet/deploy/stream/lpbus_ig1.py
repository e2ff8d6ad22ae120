"""The IG1 LP-BUS generation (LPMS-IG1, IG1P, BE1, ME1 and relatives): commands, output register, fields.

Every number here was read in LP-Research's own code (none of it copied):

- Command ids: OpenZen ``src/InternalTypes.h`` ``EDevicePropertyV1`` and ``LpmsIG1Registers.h`` of
  the IG1 library (``KHLau96/lpmsig1opensourcelib``): ``GOTO_COMMAND_MODE`` 6, ``GOTO_STREAM_MODE``
  7, ``WRITE_REGISTERS`` 4 (not ``GET_CONFIG``, as on legacy sensors), ``GET_SENSOR_MODEL`` 20,
  ``GET_FIRMWARE_INFO`` 21, ``SET/GET_IMU_TRANSMIT_DATA`` 30/31, ``SET/GET_STREAM_FREQ`` 34/35,
  ``SET/GET_DEGRAD_OUTPUT`` 36/37, ``SET/GET_ENABLE_GYR_AUTOCALIBRATION`` 64/65,
  ``SET/GET_LPBUS_DATA_PRECISION`` 136/137.
- Which generation: OpenZen ``src/communication/ConnectionNegotiator.cpp`` sends command 21 in
  command mode; a legacy sensor answers 4 bytes (its ``GET_IMU_ID``), an IG1 a 24-character firmware
  string, then ``GET_SENSOR_MODEL`` names it (``LPMS-BE1``: its only gyro is the second one,
  ``SpecialOptions_SecondGyroIsPrimary``).
- Output register bits 0-16 and the frame order (acc raw, acc calibrated, gyro 0 raw, gyro 1 raw,
  their bias- and alignment-calibrated values, mag raw and calibrated, angular velocity,
  quaternion, Euler, linear acc, pressure, altitude, temperature): ``LpmsIG1Registers.h``
  (``TDR_*``), ``SensorData.h`` ``setData``, OpenZen ``Ig1ImuProperties.cpp`` (``OutputDataFlag``)
  and ``ImuIg1Component.cpp`` ``parseSensorData``.
- Units: gyro and angles in deg/s (deg) unless ``GET_DEGRAD_OUTPUT`` says 1 (radians); OpenZen
  converts with ``radToDegreesIfNeededVector3``. 16-bit (``LPBUS_DATA_PRECISION`` 0 = fixed point,
  1 = float, ``LPMS_UART_DATA_PRECISION_*``) scales from ``SensorData.h`` ``setData16bit``: acc 1000,
  gyro 10 (deg) or 100 (rad), mag 100, angular velocity 100, quaternion 10000, Euler 100 (deg) or
  10000 (rad), linear acc 1000, pressure 100, altitude 10, temperature 100.
- Timestamp: a uint32 count ``* 0.002`` s, 500 Hz ("according to the IG1 User Manual",
  ``ImuIg1Component.cpp``). Stream rates 5, 10, 50, 100, 250, 500, 1000 Hz
  (``DATA_STREAM_FREQ_*``), the value sent in Hz.
"""
from __future__ import annotations

from gyronet.deploy.stream.lpbus_fields import LpBusField

ACK, NACK = 0, 1
WRITE_REGISTERS = 4
GOTO_COMMAND_MODE, GOTO_STREAM_MODE = 6, 7
GET_SENSOR_DATA = 9
GET_SENSOR_MODEL, GET_FIRMWARE_INFO = 20, 21
SET_TRANSMIT_DATA, GET_TRANSMIT_DATA = 30, 31
SET_STREAM_FREQ, GET_STREAM_FREQ = 34, 35
SET_DEGRAD_OUTPUT, GET_DEGRAD_OUTPUT = 36, 37
SET_GYR_AUTOCAL, GET_GYR_AUTOCAL = 64, 65
SET_LPBUS_DATA_PRECISION, GET_LPBUS_DATA_PRECISION = 136, 137
PRECISION_FIXED_16BIT, PRECISION_FLOAT_32BIT = 0, 1

RATES_HZ = (5, 10, 50, 100, 250, 500, 1000)
TIMESTAMP_HZ = 500.0
STRING_BYTES = 24
SECOND_GYRO_PRIMARY = ("LPMS-BE1",)  # OpenZen ConnectionNegotiator: these models' gyro is gyro 1


def _gyro(name: str, bit: int, stem: str) -> LpBusField:
    return LpBusField(name, bit, tuple(f"{stem}_{a}_dps" for a in "xyz"), True, 10.0, 100.0)


def fields(primary_gyro: int = 0) -> tuple[LpBusField, ...]:
    """The IG1 output fields in frame order; ``gyro`` is the raw rate of gyro ``primary_gyro`` (0 or 1)."""
    if primary_gyro not in (0, 1):
        raise ValueError(f"an IG1 sensor has gyro 0 and gyro 1, not {primary_gyro}")
    own, other = ("", "_second") if primary_gyro == 0 else ("_second", "")
    return (
        LpBusField("acc", 0, ("acc_x_g", "acc_y_g", "acc_z_g"), False, 1000.0),
        LpBusField("acc_calibrated", 1, ("acccal_x_g", "acccal_y_g", "acccal_z_g"), False, 1000.0),
        _gyro("gyro" + own, 2, "gyro" + own.replace("_", "")),
        _gyro("gyro" + other, 3, "gyro" + other.replace("_", "")),
        _gyro("gyro" + own + "_bias_calibrated", 4, "gyro" + own.replace("_", "") + "bias"),
        _gyro("gyro" + other + "_bias_calibrated", 5, "gyro" + other.replace("_", "") + "bias"),
        _gyro("gyro" + own + "_aligned", 6, "gyro" + own.replace("_", "") + "align"),
        _gyro("gyro" + other + "_aligned", 7, "gyro" + other.replace("_", "") + "align"),
        LpBusField("mag", 8, ("mag_x_ut", "mag_y_ut", "mag_z_ut"), False, 100.0),
        LpBusField("mag_calibrated", 9, ("magcal_x_ut", "magcal_y_ut", "magcal_z_ut"), False, 100.0),
        LpBusField("angular_velocity", 10, ("angvel_x_dps", "angvel_y_dps", "angvel_z_dps"), True, 100.0),
        LpBusField("quaternion", 11, ("quat_w", "quat_x", "quat_y", "quat_z"), False, 10000.0),
        LpBusField("euler", 12, ("euler_x_deg", "euler_y_deg", "euler_z_deg"), True, 100.0, 10000.0),
        LpBusField("linear_acc", 13, ("linacc_x_g", "linacc_y_g", "linacc_z_g"), False, 1000.0),
        LpBusField("pressure", 14, ("pressure_kpa",), False, 100.0),
        LpBusField("altitude", 15, ("altitude_m",), False, 10.0),
        LpBusField("temperature", 16, ("temp_c",), False, 100.0),
    )


OUTPUT_BITS = (1 << 17) - 1
