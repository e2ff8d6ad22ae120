"""Set up an LP-BUS sensor before streaming: identify it, read and set its outputs, rate and precision.

The conversation follows LP-Research's own host code (OpenZen ``ConnectionNegotiator.cpp`` for the
start, ``LegacyImuProperties.cpp`` and ``Ig1ImuProperties.cpp`` for the registers; the command ids
and their sources are in :mod:`.lpbus_legacy` and :mod:`.lpbus_ig1`):

1. command mode (command 6, ACK awaited; sent up to three times, as OpenZen retries);
2. command 21: a legacy sensor answers 4 bytes (its IMU id), an IG1-family sensor a 24-character
   firmware string; then the name (legacy 91, IG1 20) and the legacy firmware version (47);
3. the output register (legacy 4, IG1 31), stream rate (legacy register bits 0-2, IG1 35),
   precision (legacy bit 22, IG1 137), units (IG1 37) and gyro auto-calibration (legacy bit 30,
   IG1 65);
4. every wanted setting checked (a rate the sensor has, a precision it takes) before any is sent,
   so a refusal leaves the sensor as it was found; then, where they differ from what is asked,
   the sets (legacy 10, 11, 75, 23; IG1 30, 34, 136, 64), each acknowledged, then the registers
   read again: what the sensor reports, not what was asked, makes the layout;
5. optionally ``WRITE_REGISTERS`` (legacy 15, IG1 4) to keep it over a power cycle; stream mode (7).

Gyro auto-calibration is switched off unless asked to stay: the sensor re-zeroes its gyro when
it believes itself still, which removes the very drift a thermal calibration must learn.
"""
from __future__ import annotations

import logging
import struct
from dataclasses import asdict, dataclass, field, replace
from typing import Any

from gyronet.deploy.stream import lpbus_ig1 as ig1
from gyronet.deploy.stream import lpbus_legacy as legacy
from gyronet.deploy.stream.lpbus_layout import LpBusLayout
from gyronet.deploy.stream.lpbus_link import LpBusLink, SensorError

log = logging.getLogger(__name__)

COMMAND_MODE_ATTEMPTS = 3


@dataclass
class SensorInfo:
    """What a sensor said about itself, and what was changed (for the log, summary and CSV metadata)."""

    generation: str
    model: str
    firmware: str
    rate_hz: float
    layout: LpBusLayout
    gyro_autocalibration: bool
    register: int
    changed: list[str] = field(default_factory=list)
    gyro_source: str = "raw"
    leftover: bytes = b""  # bytes read after the last answer: the first sensor-data frames


    def as_dict(self) -> dict[str, Any]:
        out = asdict(self)
        del out["leftover"]
        out["layout"] = self.layout.describe()
        out["register"] = f"0x{self.register:08x}"
        return out


@dataclass(frozen=True)
class Wanted:
    """What to set; None leaves the sensor's own setting."""

    fields: tuple[str, ...] | None = None
    rate_hz: float | None = None
    precision: int | None = 32
    gyro_autocalibration: bool | None = False
    save: bool = False
    timestamp_hz: float | None = None  # overrides the generation's clock (firmware the references do not cover)
    sensor_id: int | None = None
    any_rate: bool = False  # a rate the sensor lacks: keep its own (true) or refuse (false)
    rate_option: str | None = "resample=true"  # the command's option that keeps the sensor's rate; None: it has none


def configure_sensor(port, wanted: Wanted, timeout_s: float = 1.0) -> SensorInfo:
    """Talk to the sensor on ``port`` (open): identify it, set it up, leave it streaming.

    Raises
    ------
    SensorError
        The sensor does not answer, refuses a setting, or reports a configuration that gyronet
        cannot decode (named by its register bits).
    """
    link = LpBusLink(port, timeout_s)
    _command_mode(link)
    try:
        first = link.ask(21, "GET_IMU_ID / GET_FIRMWARE_INFO")
        info = _legacy(link, wanted) if len(first) == 4 else _ig1(link, wanted, _text(first))
    except SensorError:
        link.send(legacy.GOTO_STREAM_MODE)  # leave it streaming, as it was found
        raise
    if wanted.save and info.changed:
        link.set(legacy.WRITE_REGISTERS if info.generation == "legacy" else ig1.WRITE_REGISTERS, "WRITE_REGISTERS")
        info.changed.append("saved to the sensor's flash")
    link.set(legacy.GOTO_STREAM_MODE, "GOTO_STREAM_MODE")
    info.leftover = bytes(link.reader.rest())
    if link.skipped_data_frames:
        log.debug("%d sensor-data frames skipped while configuring", link.skipped_data_frames)
    return info


def _command_mode(link: LpBusLink) -> None:
    for attempt in range(1, COMMAND_MODE_ATTEMPTS + 1):
        try:
            link.set(legacy.GOTO_COMMAND_MODE, "GOTO_COMMAND_MODE", again=attempt > 1)
            return
        except SensorError:
            if attempt == COMMAND_MODE_ATTEMPTS:
                raise
            link.reader = type(link.reader)()  # as OpenZen resets its parser between attempts


def _legacy(link: LpBusLink, wanted: Wanted) -> SensorInfo:
    name = _text(link.ask(legacy.GET_DEVICE_NAME, "GET_DEVICE_NAME")) or "legacy LPMS"
    version = link.ask(legacy.GET_FIRMWARE_VERSION, "GET_FIRMWARE_VERSION")
    if len(version) != 12:
        raise SensorError(f"{name}: GET_FIRMWARE_VERSION answered {len(version)} bytes, not 3 int32")
    patch, minor, major = struct.unpack("<3i", version)
    register = link.ask_int(legacy.GET_CONFIG, "GET_CONFIG")
    changed: list[str] = []
    # every setting checked before the first is sent: a refusal leaves the sensor as it was
    asked = None if wanted.fields is None else _check(lambda: LpBusLayout(fields=wanted.fields), name)
    rate = _rate_to_set(legacy.RATES_HZ, wanted, legacy.rate_hz(register), name)
    _check_precision(wanted, name)
    if asked is not None:
        bits = asked.config_register & legacy.OUTPUT_BITS
        if register & legacy.OUTPUT_BITS != bits:
            link.set_int(legacy.SET_TRANSMIT_DATA, "SET_TRANSMIT_DATA", bits)
            changed.append(f"outputs {list(asked.fields)}")
    if rate is not None:
        link.set_int(legacy.SET_STREAM_FREQ, "SET_STREAM_FREQ", rate)
        changed.append(f"stream rate {rate} Hz")
    if wanted.precision is not None and (16 if register >> legacy.BIT_16BIT_MODE & 1 else 32) != wanted.precision:
        link.set_int(legacy.SET_LPBUS_DATA_MODE, "SET_LPBUS_DATA_MODE", 1 if wanted.precision == 16 else 0)
        changed.append(f"{wanted.precision}-bit mode")
    autocal = bool(register >> legacy.BIT_GYRO_AUTOCALIBRATION & 1)
    if wanted.gyro_autocalibration is not None and autocal != wanted.gyro_autocalibration:
        link.set_int(legacy.ENABLE_GYR_AUTOCAL, "ENABLE_GYR_AUTOCAL", int(wanted.gyro_autocalibration))
        changed.append(f"gyro auto-calibration {'on' if wanted.gyro_autocalibration else 'off'}")
    if changed:
        register = link.ask_int(legacy.GET_CONFIG, "GET_CONFIG")
    rate = legacy.rate_hz(register)
    firmware = (major, minor, patch)
    layout = _check(lambda: LpBusLayout.from_config_register(
        register, timestamp="count" if legacy.counts_time(firmware) else "float",
        timestamp_hz=wanted.timestamp_hz or legacy.timestamp_hz(rate), sensor_id=wanted.sensor_id), name)
    info = SensorInfo("legacy", name, f"{major}.{minor}.{patch}", float(rate), layout,
                      bool(register >> legacy.BIT_GYRO_AUTOCALIBRATION & 1), register, changed)
    _verify(info, wanted, f"GET_CONFIG 0x{register:08x}")
    return info


def _ig1(link: LpBusLink, wanted: Wanted, firmware: str) -> SensorInfo:
    model = _text(link.ask(ig1.GET_SENSOR_MODEL, "GET_SENSOR_MODEL")) or "IG1-family LPMS"
    primary = 1 if model in ig1.SECOND_GYRO_PRIMARY else 0
    changed: list[str] = []
    register = link.ask_int(ig1.GET_TRANSMIT_DATA, "GET_IMU_TRANSMIT_DATA")
    # every setting checked before the first is sent: a refusal leaves the sensor as it was
    asked = None if wanted.fields is None else _check(
        lambda: LpBusLayout(fields=wanted.fields, generation="ig1", primary_gyro=primary), model)
    current_hz = link.ask_int(ig1.GET_STREAM_FREQ, "GET_STREAM_FREQ")
    rate = _rate_to_set(ig1.RATES_HZ, wanted, current_hz, model)
    _check_precision(wanted, model)
    ticks_hz = wanted.timestamp_hz or ig1.TIMESTAMP_HZ
    if (rate or current_hz) > ticks_hz:  # the rate it would stream at, set or kept
        raise _above_clock(model, rate or current_hz, ticks_hz, "would stream")
    if asked is not None and register != asked.config_register:
        link.set_int(ig1.SET_TRANSMIT_DATA, "SET_IMU_TRANSMIT_DATA", asked.config_register)
        changed.append(f"outputs {list(asked.fields)}")
    if rate is not None:
        link.set_int(ig1.SET_STREAM_FREQ, "SET_STREAM_FREQ", rate)
        changed.append(f"stream rate {rate} Hz")
    precision_code = {16: ig1.PRECISION_FIXED_16BIT, 32: ig1.PRECISION_FLOAT_32BIT}
    if wanted.precision is not None and link.ask_int(ig1.GET_LPBUS_DATA_PRECISION, "GET_LPBUS_DATA_PRECISION") \
            != precision_code[wanted.precision]:
        link.set_int(ig1.SET_LPBUS_DATA_PRECISION, "SET_LPBUS_DATA_PRECISION", precision_code[wanted.precision])
        changed.append(f"{wanted.precision}-bit mode")
    if wanted.gyro_autocalibration is not None and \
            bool(link.ask_int(ig1.GET_GYR_AUTOCAL, "GET_ENABLE_GYR_AUTOCALIBRATION")) != wanted.gyro_autocalibration:
        link.set_int(ig1.SET_GYR_AUTOCAL, "SET_ENABLE_GYR_AUTOCALIBRATION", int(wanted.gyro_autocalibration))
        changed.append(f"gyro auto-calibration {'on' if wanted.gyro_autocalibration else 'off'}")
    # what the sensor reports now, whatever was asked
    register = link.ask_int(ig1.GET_TRANSMIT_DATA, "GET_IMU_TRANSMIT_DATA")
    rate = link.ask_int(ig1.GET_STREAM_FREQ, "GET_STREAM_FREQ")
    code = link.ask_int(ig1.GET_LPBUS_DATA_PRECISION, "GET_LPBUS_DATA_PRECISION")
    radians = link.ask_int(ig1.GET_DEGRAD_OUTPUT, "GET_DEGRAD_OUTPUT")
    autocal = bool(link.ask_int(ig1.GET_GYR_AUTOCAL, "GET_ENABLE_GYR_AUTOCALIBRATION"))
    if code not in precision_code.values():
        raise SensorError(f"{model}: GET_LPBUS_DATA_PRECISION is {code}; known: 0 (16-bit fixed point), "
                          "1 (32-bit float) (LpmsIG1Registers.h)")
    if radians not in (0, 1):
        raise SensorError(f"{model}: GET_DEGRAD_OUTPUT is {radians}; known: 0 (deg), 1 (rad) (LpmsIG1.cpp)")
    if rate > ticks_hz:
        raise _above_clock(model, rate, ticks_hz)
    layout = _check(lambda: LpBusLayout.from_transmit_register(
        register, precision=16 if code == ig1.PRECISION_FIXED_16BIT else 32, primary_gyro=primary,
        radians=bool(radians), timestamp_hz=ticks_hz, sensor_id=wanted.sensor_id), model)
    info = SensorInfo("ig1", model, firmware, float(rate), layout, autocal, register, changed)
    _verify(info, wanted, f"GET_IMU_TRANSMIT_DATA 0x{register:08x}")
    return info


def _rate_to_set(rates_hz: tuple[int, ...], wanted: Wanted, current_hz: float, model: str) -> int | None:
    """The rate to send (None: nothing to set); refuse a rate the sensor lacks unless ``any_rate``."""
    if wanted.rate_hz is None or current_hz == wanted.rate_hz:
        return None
    for rate in rates_hz:
        if abs(rate - wanted.rate_hz) < 1e-9:
            return rate
    message = f"{model} streams at {', '.join(map(str, rates_hz))} Hz, not {wanted.rate_hz:g} Hz"
    if wanted.rate_option is None:
        raise SensorError(message + "; choose lpbus.rate_hz from these rates (nothing was changed on the sensor)")
    if not wanted.any_rate:
        raise SensorError(message + f"; pass {wanted.rate_option} to keep the sensor's own rate "
                                    f"({current_hz:g} Hz) and run the feature filters at it")
    log.warning("%s: keeping its own %g Hz (%s)", message, current_hz, wanted.rate_option)
    return None


def _check_precision(wanted: Wanted, model: str) -> None:
    if wanted.precision not in (None, 16, 32):
        raise SensorError(f"{model}: lpbus.precision is 16 or 32 (bits per value), not {wanted.precision!r}")


def _above_clock(model: str, rate: float, ticks_hz: float, verb: str = "streams") -> SensorError:
    return SensorError(f"{model} {verb} at {rate} Hz, above its {ticks_hz:g} Hz timestamp clock (OpenZen "
                       "ImuIg1Component.cpp: count * 0.002 s): frames would share a time; set lpbus.rate_hz "
                       "<= 500, or lpbus.timestamp_hz to the rate your firmware's counter runs at")


def _verify(info: SensorInfo, wanted: Wanted, register_text: str) -> None:
    """Refuse a sensor that acknowledged a setting but does not report it."""
    problems = []
    if wanted.fields is not None:
        asked = replace(info.layout, fields=wanted.fields).fields
        if asked != info.layout.fields:
            problems.append(f"outputs {list(info.layout.fields)}, not {list(asked)}")
    if wanted.rate_hz is not None and info.rate_hz != wanted.rate_hz and not wanted.any_rate:
        problems.append(f"{info.rate_hz:g} Hz, not {wanted.rate_hz:g} Hz")
    if wanted.precision is not None and info.layout.precision != wanted.precision:
        problems.append(f"{info.layout.precision}-bit, not {wanted.precision}-bit")
    if wanted.gyro_autocalibration is not None and info.gyro_autocalibration != wanted.gyro_autocalibration:
        problems.append(f"gyro auto-calibration {'on' if info.gyro_autocalibration else 'off'}")
    if problems:
        raise SensorError(f"{info.model} acknowledged the settings but reports {'; '.join(problems)} "
                          f"({register_text})")


def _check(build, model: str):
    try:
        return build()
    except ValueError as err:
        raise SensorError(f"{model}: {err}") from None


def _text(data: bytes) -> str:
    return data.split(b"\0", 1)[0].decode("ascii", "replace").strip()
