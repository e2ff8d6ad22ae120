"""An emulated LPMS sensor's command side: it answers LP-BUS commands as the reference host code expects.

Pure (bytes in, reply frames out), so tests can drive it directly; :mod:`.pty_sensor` puts it
behind a pseudo-terminal. Both generations: a model name starting with one of ``IG1_MODELS``
answers as an IG1-family sensor (:mod:`.lpbus_ig1`), any other as a legacy one
(:mod:`.lpbus_legacy`). What it answers, per command, is what the reference parsers read: a legacy
``GET_IMU_ID`` is 4 bytes and an IG1 ``GET_FIRMWARE_INFO`` 24 characters (OpenZen
``ConnectionNegotiator.cpp`` tells them apart by that), a legacy ``GET_FIRMWARE_VERSION`` three
int32 patch first, names padded with NUL to 16 (legacy) or 24 (IG1) bytes; a set is answered by
ACK, an unknown command or a rate the sensor lacks by NACK. Like a real sensor it keeps its
settings in RAM (``saved`` tells whether ``WRITE_REGISTERS`` was sent).
"""
from __future__ import annotations

import struct
from dataclasses import dataclass, field

from gyronet.deploy.stream import lpbus_ig1 as ig1
from gyronet.deploy.stream import lpbus_legacy as legacy
from gyronet.deploy.stream.lpbus import lpbus_frame
from gyronet.deploy.stream.lpbus_layout import DEFAULT_FIELDS, LpBusLayout
from gyronet.deploy.stream.lpbus_link import FrameReader

IG1_MODELS = ("LPMS-IG1", "LPMS-BE1", "LPMS-ME1")  # emulator only: real sensors are told apart by command 21
LEGACY_MODELS = ("LPMS-CU2", "LPMS-B2", "LPMS-USBAL2")  # the legacy sensors it plays (an unknown name was one silently)


@dataclass
class EmulatedLpms:
    """The state of one emulated sensor; ``feed`` the host's bytes, write back what it returns.

    Parameters
    ----------
    model
        Its name (``LPMS-CU2``, ``LPMS-B2``, ``LPMS-IG1-RS232``, ``LPMS-BE1``...).
    firmware
        Legacy: (major, minor, patch); IG1: shown in its firmware string.
    rate_hz, fields, precision, gyro_autocalibration, radians
        Its settings at power-on (``radians``: IG1 only).
    sensor_id
        The id in the frames it sends.
    """

    model: str | None = "LPMS-CU2"
    firmware: tuple[int, int, int] = (2, 0, 5)
    rate_hz: int = 100
    fields: tuple[str, ...] = ("quaternion", "euler")
    precision: int = 16
    gyro_autocalibration: bool = True
    radians: bool = False
    sensor_id: int = 1
    streaming: bool = True
    saved: bool = False
    commands: list[int] = field(default_factory=list)

    def __post_init__(self) -> None:
        if not self.model:
            raise ValueError("an emulated LPMS needs a model name (LPMS-CU2, LPMS-IG1-RS232, ...)")
        if self.model not in LEGACY_MODELS and not self.model.startswith(IG1_MODELS):
            raise ValueError(f"no emulated sensor {self.model!r}; known: {', '.join(LEGACY_MODELS)} (legacy), names "
                             f"starting {', '.join(IG1_MODELS)} (IG1 family)")
        self.fields = tuple(self.fields) if self.fields is not None else DEFAULT_FIELDS
        self._reader = FrameReader()
        self.layout()  # the settings must make a layout

    @property
    def generation(self) -> str:
        return "ig1" if self.model.startswith(IG1_MODELS) else "legacy"

    @property
    def primary_gyro(self) -> int:
        return 1 if self.model in ig1.SECOND_GYRO_PRIMARY else 0

    def layout(self) -> LpBusLayout:
        """What its sensor-data frames hold now."""
        if self.generation == "legacy":
            timestamp = "count" if legacy.counts_time(self.firmware) else "float"
            return LpBusLayout(self.fields, self.precision, timestamp, legacy.timestamp_hz(self.rate_hz),
                               self.sensor_id)
        return LpBusLayout(self.fields, self.precision, "count", ig1.TIMESTAMP_HZ, self.sensor_id, "ig1",
                           self.radians, self.primary_gyro)

    def feed(self, data: bytes) -> list[bytes]:
        """The reply frames to the commands ``data`` completes."""
        replies = []
        for _, command, payload in self._reader.feed(data):
            self.commands.append(command)
            handler = self._legacy if self.generation == "legacy" else self._ig1
            reply = handler(command, payload)
            replies.append(self._nack() if reply is None else reply)
        return replies

    # ------------------------------------------------------------------ answers
    def _frame(self, command: int, data: bytes = b"") -> bytes:
        return lpbus_frame(self.sensor_id, command, data)

    def _ack(self) -> bytes:
        return self._frame(legacy.ACK)

    def _nack(self) -> bytes:
        return self._frame(legacy.NACK)

    def _common(self, command: int) -> bytes | None:
        if command == legacy.GOTO_COMMAND_MODE:
            self.streaming = False
            return self._ack()
        if command == legacy.GOTO_STREAM_MODE:
            self.streaming = True
            return self._ack()
        return None

    def _legacy(self, command: int, payload: bytes) -> bytes | None:
        common = self._common(command)
        if common is not None:
            return common
        value = struct.unpack("<I", payload)[0] if len(payload) == 4 else None
        if command == legacy.GET_IMU_ID:
            return self._frame(command, struct.pack("<I", self.sensor_id))
        if command == legacy.GET_DEVICE_NAME:
            return self._frame(command, _padded(self.model, legacy.DEVICE_NAME_BYTES))
        if command == legacy.GET_FIRMWARE_VERSION:
            major, minor, patch = self.firmware
            return self._frame(command, struct.pack("<3i", patch, minor, major))
        if command == legacy.GET_CONFIG:
            return self._frame(command, struct.pack("<I", self._legacy_register()))
        if value is None and command != legacy.WRITE_REGISTERS:
            return None
        if command == legacy.SET_TRANSMIT_DATA:
            self.fields = LpBusLayout.from_config_register(value & legacy.OUTPUT_BITS).fields
        elif command == legacy.SET_STREAM_FREQ:
            if value not in legacy.RATES_HZ:
                return None
            self.rate_hz = value
        elif command == legacy.SET_LPBUS_DATA_MODE:
            self.precision = 16 if value else 32
        elif command == legacy.ENABLE_GYR_AUTOCAL:
            self.gyro_autocalibration = bool(value)
        elif command == legacy.WRITE_REGISTERS:
            self.saved = True
        else:
            return None
        return self._ack()

    def _legacy_register(self) -> int:
        register = LpBusLayout(self.fields, self.precision).config_register | legacy.rate_bits(self.rate_hz)
        return register | (int(self.gyro_autocalibration) << legacy.BIT_GYRO_AUTOCALIBRATION)

    def _ig1(self, command: int, payload: bytes) -> bytes | None:
        common = self._common(command)
        if common is not None:
            return common
        text = {ig1.GET_SENSOR_MODEL: self.model, ig1.GET_FIRMWARE_INFO: "v%d.%d.%d" % self.firmware}
        if command in text:
            return self._frame(command, _padded(text[command], ig1.STRING_BYTES))
        gets = {ig1.GET_TRANSMIT_DATA: lambda: self.layout().config_register,
                ig1.GET_STREAM_FREQ: lambda: self.rate_hz,
                ig1.GET_DEGRAD_OUTPUT: lambda: int(self.radians),
                ig1.GET_GYR_AUTOCAL: lambda: int(self.gyro_autocalibration),
                ig1.GET_LPBUS_DATA_PRECISION: lambda: (ig1.PRECISION_FIXED_16BIT if self.precision == 16
                                                       else ig1.PRECISION_FLOAT_32BIT)}
        if command in gets:
            return self._frame(command, struct.pack("<I", gets[command]()))
        if command == ig1.WRITE_REGISTERS:
            self.saved = True
            return self._ack()
        if len(payload) != 4:
            return None
        (value,) = struct.unpack("<I", payload)
        if command == ig1.SET_TRANSMIT_DATA:
            try:
                self.fields = LpBusLayout.from_transmit_register(value, primary_gyro=self.primary_gyro).fields
            except ValueError:
                return None
        elif command == ig1.SET_STREAM_FREQ:
            if value not in ig1.RATES_HZ:
                return None
            self.rate_hz = value
        elif command == ig1.SET_LPBUS_DATA_PRECISION:
            self.precision = 16 if value == ig1.PRECISION_FIXED_16BIT else 32
        elif command == ig1.SET_GYR_AUTOCAL:
            self.gyro_autocalibration = bool(value)
        elif command == ig1.SET_DEGRAD_OUTPUT:
            self.radians = bool(value)
        else:
            return None
        return self._ack()


def _padded(text: str, n_bytes: int) -> bytes:
    """``text`` in ASCII, cut or padded with NUL to ``n_bytes`` (how the sensors send names)."""
    return text.encode()[:n_bytes].ljust(n_bytes, b"\0")
