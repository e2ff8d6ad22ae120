"""The start of an LP-BUS run: configure the sensor (or plan the passive check), return the layout.

One call, :func:`start_lpbus`, before the sample loop of ``stream.py`` and ``record.py``. With
``configure`` on it talks to the sensor (:mod:`.lpbus_config`): the frame layout then comes from
what the sensor reports, the stream rate is set to the bundle's ``fs_hz`` (or ``rate_hz``), and a
sensor that cannot run at that rate is refused unless ``resample`` is on. Off, the layout is the
configured one and the first frames are checked against it (:mod:`.lpbus_probe`). A bundle
trained on the host-corrected gyro of an LPMS-Control log is refused: LP-BUS carries the raw one.

A sensor unplugged and plugged back in may come back power-cycled (its power-on outputs, rate
and gyro auto-calibration, unless they were saved to its flash). :meth:`LpBusStart.reopen_hook`
is what the reader calls on the reopened port: the same set-up again, refused if the sensor now
differs from the one set up at the start; listening, the first-frames check again.
"""
from __future__ import annotations

import functools
import logging
import os
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping

from gyronet.errors import BundleError, ConfigError
from gyronet.deploy.stream.lpbus import LpBusParser
from gyronet.deploy.stream.lpbus_config import SensorInfo, Wanted, configure_sensor
from gyronet.deploy.stream.lpbus_layout import DEFAULT_FIELDS, LpBusLayout
from gyronet.deploy.stream.lpbus_link import SensorError
from gyronet.deploy.stream.lpbus_probe import FirstFrames

log = logging.getLogger(__name__)

RATE_TOLERANCE = 0.05  # as the live rate check (gyronet.deploy.stream.live.RateGate)


@dataclass(frozen=True)
class LpBusSetup:
    """``lpbus:`` of ``stream.yaml`` and ``record.yaml``: what to set on the sensor, or what it sends.

    Parameters
    ----------
    configure
        ``true``: talk to the sensor; ``false``: only listen (a shared port, a replay);
        ``auto``: true for a serial device, false for a pseudo-terminal or a pyserial URL.
    fields
        Outputs to set (configure) or that the frames carry (listen); null (configure): keep.
    precision
        32 or 16 bits per value; configure sets it (null: keep).
    rate_hz
        Stream rate to set; null: the bundle's ``fs_hz`` (``stream.py``) or keep (``record.py``).
    gyro_autocalibration
        The sensor's own gyro re-zeroing: false switches it off (null: keep).
    save
        Write the settings to the sensor's flash (``WRITE_REGISTERS``) so they survive a power cycle.
    timeout_s
        Wait for each answer, s.
    timestamp, timestamp_hz, sensor_id, generation, radians, primary_gyro
        The passive layout (:class:`LpBusLayout`); configure derives them from the sensor
        (``timestamp_hz`` set there overrides the generation's clock; ``sensor_id`` filters).
    check_frames
        Listening: check the layout against this many first frames (0: no check).
    """

    configure: bool | str = "auto"
    fields: tuple[str, ...] | None = DEFAULT_FIELDS
    precision: int | None = 32
    rate_hz: float | None = None
    gyro_autocalibration: bool | None = False
    save: bool = False
    timeout_s: float = 1.0
    timestamp: str = "count"
    timestamp_hz: float | None = None
    sensor_id: int | None = None
    generation: str = "legacy"
    radians: bool | None = None
    primary_gyro: int = 0
    check_frames: int = 20

    def __post_init__(self) -> None:
        if self.configure not in (True, False, "auto"):
            raise ConfigError(f"lpbus.configure is true, false or auto, not {self.configure!r}")
        if self.fields is not None:
            object.__setattr__(self, "fields", tuple(self.fields))

    def wants_configure(self, port: str) -> bool:
        """Whether to talk to the sensor on ``port``."""
        if self.configure != "auto":
            return bool(self.configure)
        return is_serial_device(port)

    def passive_layout(self) -> LpBusLayout:
        """The layout when only listening."""
        try:
            return LpBusLayout(self.fields or DEFAULT_FIELDS, self.precision or 32, self.timestamp,
                               self.timestamp_hz, self.sensor_id, self.generation, self.radians, self.primary_gyro)
        except ValueError as err:
            raise ConfigError(f"lpbus: {err}") from None


@dataclass
class LpBusStart:
    """What the run's sample loop needs: the layout, the sensor's own account, the first-frame check."""

    layout: LpBusLayout
    sensor: SensorInfo | None = None
    probe: FirstFrames | None = None
    configure_again: Callable[[Any], SensorInfo] | None = field(default=None, repr=False)  # the set-up, on a port

    def parser(self, check=None) -> LpBusParser:
        parser = LpBusParser(self.layout, check=check)
        parser.probe = self.probe
        if self.sensor is not None:
            parser.prime(self.sensor.leftover)
        return parser

    def reopen_hook(self, parser: LpBusParser, port_name: str) -> Callable[[Any], None]:
        """``on_reopen`` for :func:`~gyronet.deploy.stream.reader.read_chunks`: set up again, or check again, ``parser``'s sensor.

        Raises (from the hook) ``SensorError`` when the sensor that came back differs from the
        one set up at the start, or ``BundleError`` as at the start.
        """

        def on_reopen(port) -> None:
            if self.sensor is None:
                parser.probe = self.probe.again() if self.probe is not None else None
                log.warning("%s: reopened; only listening, %s", port_name,
                            f"checking its first {parser.probe.n_frames} frames again" if parser.probe is not None
                            else "its frames are not checked (lpbus.check_frames=0)")
                return
            try:
                info = self.configure_again(port)
            except SensorError as err:
                raise SensorError(f"{err} (set-up again after the port was lost and reopened)") from None
            _refuse_another_sensor(port_name, self.sensor, info)
            parser.prime(info.leftover)
            log.warning("%s: reopened; %s set up again: %s", port_name, info.model,
                        "; ".join(info.changed) or "it had kept its settings")

        return on_reopen

    def as_dict(self) -> dict[str, Any]:
        if self.sensor is not None:
            return {"configured": True, **self.sensor.as_dict()}
        return {"configured": False, "layout": self.layout.describe(), "gyro_source": "raw"}


def is_serial_device(port: str) -> bool:
    """True for a device path that is not a pseudo-terminal (and not a pyserial URL)."""
    if "://" in port:
        return False
    return not os.path.realpath(port).startswith(("/dev/pts/", "/dev/ptmx"))


def start_lpbus(port, port_name: str, setup: LpBusSetup, meta: Mapping[str, Any] | None = None,
                resample: bool = False) -> LpBusStart:
    """Configure the sensor on ``port`` (open) or plan the passive check; refuse what cannot work.

    ``meta``: the bundle's ``meta.json`` (``stream.py``), for its ``fs_hz`` and ``gyro_source``;
    None when recording.
    """
    trained = (meta or {}).get("gyro_source")
    if trained is not None and trained != "raw":
        raise BundleError(f"the bundle was trained on the {trained} gyro (gyro_source in meta.json: an LPMS-Control "
                          "log, with OpenMAT's alignment and bias applied on the host), but LP-BUS carries the raw "
                          "gyro; train on a recording of the raw stream (scripts/record.py)")
    fs_hz = float(meta["fs_hz"]) if meta is not None else None
    if port is None and setup.configure is True:
        raise ConfigError(f"{port_name}: lpbus.configure=true needs the port open at the start; drop "
                          "reconnect.wait_at_start=true or set lpbus.configure=false")
    if port is None or not setup.wants_configure(port_name):
        layout = setup.passive_layout()
        expected_hz = None if resample else fs_hz  # with resample, another rate is no sign of a wrong clock
        probe = FirstFrames(layout, setup.check_frames, port_name, expected_hz, setup.timestamp_hz is not None) \
            if setup.check_frames > 0 else None
        log.info("%s: listening only (lpbus.configure=%s): %s", port_name, setup.configure, layout.describe())
        return LpBusStart(layout, None, probe)

    info = _set_up(port, port_name, setup, fs_hz, resample, report=True)
    return LpBusStart(info.layout, info, None,
                      functools.partial(_set_up, port_name=port_name, setup=setup, fs_hz=fs_hz, resample=resample))


def _set_up(port, port_name: str, setup: LpBusSetup, fs_hz: float | None, resample: bool,
            report: bool = False) -> SensorInfo:
    """Configure the sensor on ``port``; refuse a rate the bundle cannot take; log it all (``report``)."""
    rate = setup.rate_hz if setup.rate_hz is not None else fs_hz
    wanted = Wanted(setup.fields, rate, setup.precision, setup.gyro_autocalibration, setup.save,
                    setup.timestamp_hz, setup.sensor_id, any_rate=resample,
                    rate_option=None if fs_hz is None else "resample=true")  # record.py has no resample
    try:
        info = configure_sensor(port, wanted, setup.timeout_s)
    except SensorError as err:
        raise SensorError(f"{port_name}: {err}") from None
    if report:
        _report(port_name, info)
    if fs_hz is not None and abs(info.rate_hz - fs_hz) > RATE_TOLERANCE * fs_hz:
        message = (f"{port_name}: {info.model} streams at {info.rate_hz:g} Hz, but the bundle was trained at "
                   f"{fs_hz:g} Hz")
        if not resample:
            raise BundleError(message + "; pass resample=true to run the feature filters at the sensor's rate")
        if report:
            log.warning("%s; resample=true", message)
    return info


def _refuse_another_sensor(port_name: str, before: SensorInfo, now: SensorInfo) -> None:
    """Refuse a sensor that came back as another one: identity, rate, frame layout, gyro auto-calibration."""

    def account(info: SensorInfo) -> dict[str, str]:
        register = "GET_CONFIG" if info.generation == "legacy" else "GET_IMU_TRANSMIT_DATA"
        return {"sensor": f"{info.generation} {info.model}, firmware {info.firmware}", "rate": f"{info.rate_hz:g} Hz",
                "frames": f"{info.layout.describe()} ({register} 0x{info.register:08x})",
                "gyro auto-calibration": "on" if info.gyro_autocalibration else "off"}

    old, new = account(before), account(now)
    if now.layout == before.layout:
        old["frames"] = new["frames"]  # the same frames; other register bits (the rate) are named above
    differences = [f"{key} {new[key]}, not {old[key]}" for key in new if new[key] != old[key]]
    if differences:
        raise SensorError(f"{port_name}: the sensor that came back after the port was lost is not the one set up "
                          f"at the start: {'; '.join(differences)}; the run stops (start it again for this sensor)")


def _report(port_name: str, info: SensorInfo) -> None:
    log.info("%s: %s, firmware %s, %g Hz: %s", port_name, info.model, info.firmware, info.rate_hz,
             info.layout.describe())
    if info.changed:
        saved = "saved to the sensor's flash" in info.changed
        log.warning("%s: set %s; the sensor keeps these settings after gyronet stops (%s): other software that "
                    "relies on them (gyro auto-calibration, other outputs) needs them set back in LPMS-Control",
                    port_name, "; ".join(info.changed),
                    "for good" if saved else "until it is powered off; lpbus.save=true keeps them for good")
    if info.gyro_autocalibration:
        log.warning("%s: the sensor's gyro auto-calibration is ON: it re-zeroes the gyro when still and removes "
                    "the drift a thermal calibration must learn", port_name)
    else:
        log.info("%s: the sensor's gyro auto-calibration is off", port_name)
