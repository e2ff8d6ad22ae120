"""Check a passively read LP-BUS stream's layout against its first frames, before any output.

With ``lpbus.configure=false`` nothing asks the sensor what it sends, and two configurations of
the same frame length decode without a fault: an IG1 frame of acc + gyro + temperature read as
the legacy gyro + acc + temperature, or legacy acc + angular velocity + temperature read as gyro +
acc + temperature. Both put a gyro rate (a few deg/s, or rad/s) where the accelerometer should
read about 1 g. A stream faster than the timestamp clock repeats its times. So the first frames
are checked (the parser holds them back until then), where the layout makes it possible:

- times: more than a quarter of the intervals not increasing means ``timestamp_hz`` is wrong; so
  does a rate (median interval) off the bundle's ``fs_hz``, or (without one) off every rate the
  generation streams at, by exactly the ratio of two LPMS timestamp clocks (400, 500, 800 Hz:
  legacy above 400 Hz, or an IG1, read at the wrong one);
- acceleration, when the layout has it: the median of |a| must lie within 0.7-1.5 g (1 g at rest;
  a moving sensor's median stays near it);
- the quaternion, when the layout has it: the median of |q| must lie within 0.95-1.05 (a unit
  quaternion; 16-bit frames carry it to 1e-4);
- temperature: the median must lie within -60-150 degC.

What passes nonetheless: a misread whose gyro, read in the accelerometer's place, turns at
about 1 deg/s (an IG1 read as legacy; its 500 Hz clock read at 400 Hz still fails the live rate
check unless ``resample=true``), a clock misread whose rate is another LPMS rate (an IG1 at 250
Hz read at 400 Hz ticks shows 200 Hz), and the field order of a layout without acceleration or
quaternion: that the check could not be made is logged. A legacy stream at 400 Hz by 400 Hz
ticks may be one at 800 Hz (whose counter ticks at 800 Hz): that is logged too, naming
``lpbus.timestamp_hz``. Configure the sensor (``lpbus.configure=true``) to be sure.
"""
from __future__ import annotations

import logging
import math
import statistics

from gyronet.errors import GyronetError
from gyronet.deploy.stream import lpbus_ig1, lpbus_legacy
from gyronet.deploy.stream.lpbus_layout import LpBusLayout

log = logging.getLogger(__name__)

ACC_RANGE_G = (0.7, 1.5)
TEMP_RANGE_C = (-60.0, 150.0)
QUATERNION_NORM_RANGE = (0.95, 1.05)
STREAM_RATES_HZ = {"legacy": lpbus_legacy.RATES_HZ, "ig1": lpbus_ig1.RATES_HZ}
MAX_NOT_INCREASING = 0.25
CLOCKS_HZ = (400.0, 500.0, 800.0)  # the LPMS timestamp clocks (lpbus_legacy, lpbus_ig1)
RATE_TOLERANCE = 0.05
AFTER_REOPEN = ", reopened"


class LayoutError(GyronetError):
    """Frames that do not read as the layout says: the sensor sends something else."""


class FirstFrames:
    """Collect the first ``n_frames`` decoded frames and refuse the layout if they do not fit it."""

    def __init__(self, layout: LpBusLayout, n_frames: int = 20, source: str = "the stream",
                 expected_hz: float | None = None, clock_given: bool = False):
        self.layout, self.n_frames, self.source = layout, max(2, int(n_frames)), source
        self.expected_hz = expected_hz  # the bundle's fs_hz, if any
        self.clock_given = clock_given  # lpbus.timestamp_hz set by the user: its ticks are not in doubt
        self.frames: list[tuple[float, dict[str, float]]] = []
        self.done = False

    def again(self) -> "FirstFrames":
        """The same check, from the first frame again (a reopened port)."""
        source = self.source.removesuffix(AFTER_REOPEN) + AFTER_REOPEN
        return FirstFrames(self.layout, self.n_frames, source, self.expected_hz, self.clock_given)

    def see(self, time_s: float, values: dict[str, float]) -> None:
        """Note one frame; raise ``LayoutError`` once enough frames show the layout is wrong."""
        if self.done:
            return
        self.frames.append((time_s, values))
        if len(self.frames) >= self.n_frames:
            self.done = True
            self.check()

    def check(self) -> None:
        """The checks of the module docstring on the frames seen so far."""
        layout, n = self.layout, len(self.frames)
        where = (f"{self.source}: the first {n} frames do not read as {layout.describe()} "
                 f"(register bits {_bits(layout)})")
        times = [t for t, _ in self.frames]
        stuck = sum(1 for a, b in zip(times, times[1:]) if not b > a)
        if stuck > MAX_NOT_INCREASING * (n - 1):
            raise LayoutError(f"{where}: {stuck} of {n - 1} times do not increase; the sensor streams faster "
                              f"than the {layout.timestamp_hz:g} Hz timestamp (a legacy sensor above 400 Hz "
                              "counts at 800 Hz, an IG1 at 500 Hz): set lpbus.timestamp_hz, or let gyronet ask "
                              "the sensor (lpbus.configure=true)")
        clock, measured_hz, rate_hz = self._other_clock(times)
        if clock is not None:
            whose = (f"the bundle's fs_hz ({rate_hz:g} Hz)" if self.expected_hz is not None else
                     f"no rate a {layout.generation} sensor streams at, but {rate_hz:g} Hz")
            raise LayoutError(f"{where}: the stream runs at {measured_hz:.4g} Hz by its times, {whose} times "
                              f"{layout.timestamp_hz:g}/{clock:g}: the timestamp counts at {clock:g} Hz (set "
                              f"lpbus.timestamp_hz={clock:g}, or lpbus.configure=true)"
                              + (", unless the sensor streams at another rate than the bundle's (resample=true)"
                                 if self.expected_hz is not None else ""))
        if layout.generation == "legacy" and layout.timestamp == "count" and layout.timestamp_hz == 400 \
                and not self.clock_given and _near(measured_hz, (400.0,)) is not None:
            # one tick a frame: 400 Hz, or 800 Hz whose counter ticks at 800 Hz (OpenZen); the stamps cannot tell
            log.warning("%s: the stamps show 400 Hz at 400 Hz ticks, as a legacy sensor at 800 Hz (its counter ticks "
                        "at 800 Hz) would too: if it streams at 800 Hz, set lpbus.timestamp_hz=800 (or "
                        "lpbus.configure=true), else every time is doubled", self.source)
        if "acc_x_g" in layout.columns:
            norms = [math.sqrt(sum(v[f"acc_{a}_g"] ** 2 for a in "xyz")) for _, v in self.frames]
            median = _median(norms)
            if not ACC_RANGE_G[0] <= median <= ACC_RANGE_G[1]:
                raise LayoutError(f"{where}: the accelerometer reads |a| = {median:.3g} g (median), not about "
                                  "1 g, so these frames carry other outputs in that place (an IG1 sensor sends "
                                  "acc first; angular velocity is bit 16, raw gyro bit 12): set lpbus.generation "
                                  "and lpbus.fields to what the sensor sends, or lpbus.configure=true")
        if "quat_w" in layout.columns:
            median = _median([math.sqrt(sum(v[f"quat_{a}"] ** 2 for a in "wxyz")) for _, v in self.frames])
            if not QUATERNION_NORM_RANGE[0] <= median <= QUATERNION_NORM_RANGE[1]:
                raise LayoutError(f"{where}: the quaternion reads |q| = {median:.3g} (median), not 1, so these "
                                  "frames carry other outputs in that place: set lpbus.generation and lpbus.fields "
                                  "to what the sensor sends, or lpbus.configure=true")
        if "temp_c" in layout.columns:
            median = _median([v["temp_c"] for _, v in self.frames])
            if not TEMP_RANGE_C[0] <= median <= TEMP_RANGE_C[1]:
                raise LayoutError(f"{where}: the temperature reads {median:.4g} degC (median), outside "
                                  f"{TEMP_RANGE_C[0]:g}-{TEMP_RANGE_C[1]:g} degC: the frames carry other outputs, "
                                  "precision or units: set lpbus.fields/precision, or lpbus.configure=true")
        if "acc_x_g" not in layout.columns and "quat_w" not in layout.columns:
            log.warning("%s: the first %d frames fit %s in their times%s, but which output sits where could not be "
                        "checked (no accelerometer or quaternion in the frames): other outputs of the same length "
                        "would pass; lpbus.configure=true makes sure", self.source, n, layout.describe(),
                        " and temperature" if "temp_c" in layout.columns else "")


    def _other_clock(self, times: list[float]) -> tuple[float | None, float, float]:
        """Another LPMS clock that makes the measured rate the bundle's (or, without it, an LPMS rate).

        Returns the clock (None if none), the measured rate and the rate it makes, Hz.
        """
        steps = [b - a for a, b in zip(times, times[1:]) if b > a]
        if self.layout.timestamp != "count" or not steps:
            return None, math.nan, math.nan
        measured_hz = 1.0 / statistics.median(steps)
        rates_hz = (self.expected_hz,) if self.expected_hz is not None else STREAM_RATES_HZ[self.layout.generation]
        if _near(measured_hz, rates_hz) is not None:
            return None, measured_hz, math.nan
        for clock in CLOCKS_HZ:
            if clock != self.layout.timestamp_hz:
                rescaled = _near(measured_hz * clock / self.layout.timestamp_hz,
                                 (self.expected_hz,) if self.expected_hz is not None else
                                 tuple(r for rates in STREAM_RATES_HZ.values() for r in rates))
                if rescaled is not None:
                    return clock, measured_hz, rescaled
        return None, measured_hz, math.nan


def _near(rate_hz: float, rates_hz) -> float | None:
    """The rate of ``rates_hz`` within ``RATE_TOLERANCE`` of ``rate_hz``, or None."""
    for candidate in rates_hz:
        if abs(rate_hz - candidate) <= RATE_TOLERANCE * candidate:
            return float(candidate)
    return None


def _median(values: list[float]) -> float:
    finite = [v for v in values if math.isfinite(v)]
    return statistics.median(finite) if finite else math.nan


def _bits(layout: LpBusLayout) -> str:
    bits = [spec.bit for spec in layout.specs]
    text = ", ".join(map(str, sorted(bits)))
    if layout.generation == "legacy" and layout.precision == 16:
        text += ", 22 (16-bit)"
    return f"{layout.generation} {text}"
