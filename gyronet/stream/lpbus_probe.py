"""Check a passively read LP-BUS stream's layout against its first frames, before any output.

With ``lpbus.configure=false`` nothing asks the sensor what it sends, and two configurations of
the same frame length decode without a fault: an IG1 frame of acc + gyro + temperature read as
the legacy gyro + acc + temperature, or legacy acc + angular velocity + temperature read as gyro +
acc + temperature. Both put a gyro rate (a few deg/s, or rad/s) where the accelerometer should
read about 1 g. A stream faster than the timestamp clock repeats its times. So the first frames
are checked, where the layout makes it possible:

- times: more than a quarter of the intervals not increasing means ``timestamp_hz`` is wrong; so
  does a rate (median interval) off the bundle's ``fs_hz`` by exactly the ratio of two LPMS
  timestamp clocks (400, 500, 800 Hz: legacy above 400 Hz, or an IG1, read at the wrong one);
- acceleration, when the layout has it: the median of |a| must lie within 0.7-1.5 g (1 g at rest;
  a moving sensor's median stays near it);
- temperature: the median must lie within -60-150 degC.

What passes nonetheless: a misread whose gyro, read in the accelerometer's place, turns at
about 1 deg/s (an IG1 read as legacy; its 500 Hz clock read at 400 Hz still fails the live rate
check unless ``resample=true``), and any layout without acceleration. Configure the sensor
(``lpbus.configure=true``) to be sure.
"""
from __future__ import annotations

import math
import statistics

from gyronet.errors import GyronetError
from gyronet.stream.lpbus_layout import LpBusLayout

ACC_RANGE_G = (0.7, 1.5)
TEMP_RANGE_C = (-60.0, 150.0)
MAX_NOT_INCREASING = 0.25
CLOCKS_HZ = (400.0, 500.0, 800.0)  # the LPMS timestamp clocks (lpbus_legacy, lpbus_ig1)
RATE_TOLERANCE = 0.05


class LayoutError(GyronetError):
    """Frames that do not read as the layout says: the sensor sends something else."""


class FirstFrames:
    """Collect the first ``n_frames`` decoded frames and refuse the layout if they do not fit it."""

    def __init__(self, layout: LpBusLayout, n_frames: int = 20, source: str = "the stream",
                 expected_hz: float | None = None):
        self.layout, self.n_frames, self.source = layout, max(2, int(n_frames)), source
        self.expected_hz = expected_hz  # the bundle's fs_hz, if any
        self.frames: list[tuple[float, dict[str, float]]] = []
        self.done = False

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
        clock, measured_hz = self._other_clock(times)
        if clock is not None:
            raise LayoutError(f"{where}: the stream runs at {measured_hz:.4g} Hz by its times, the bundle's "
                              f"fs_hz ({self.expected_hz:g} Hz) times "
                              f"{layout.timestamp_hz:g}/{clock:g}: the timestamp counts at {clock:g} Hz (set "
                              f"lpbus.timestamp_hz={clock:g}, or lpbus.configure=true), unless the sensor streams "
                              "at another rate than the bundle's (resample=true)")
        if "acc_x_g" in layout.columns:
            norms = [math.sqrt(sum(v[f"acc_{a}_g"] ** 2 for a in "xyz")) for _, v in self.frames]
            median = _median(norms)
            if not ACC_RANGE_G[0] <= median <= ACC_RANGE_G[1]:
                raise LayoutError(f"{where}: the accelerometer reads |a| = {median:.3g} g (median), not about "
                                  "1 g, so these frames carry other outputs in that place (an IG1 sensor sends "
                                  "acc first; angular velocity is bit 16, raw gyro bit 12): set lpbus.generation "
                                  "and lpbus.fields to what the sensor sends, or lpbus.configure=true")
        if "temp_c" in layout.columns:
            median = _median([v["temp_c"] for _, v in self.frames])
            if not TEMP_RANGE_C[0] <= median <= TEMP_RANGE_C[1]:
                raise LayoutError(f"{where}: the temperature reads {median:.4g} degC (median), outside "
                                  f"{TEMP_RANGE_C[0]:g}-{TEMP_RANGE_C[1]:g} degC: the frames carry other outputs, "
                                  "precision or units: set lpbus.fields/precision, or lpbus.configure=true")


    def _other_clock(self, times: list[float]) -> tuple[float | None, float]:
        """Another LPMS clock rate that makes the measured rate the bundle's (None if none), and that rate, Hz."""
        steps = [b - a for a, b in zip(times, times[1:]) if b > a]
        if self.expected_hz is None or self.layout.timestamp != "count" or not steps:
            return None, math.nan
        measured_hz = 1.0 / statistics.median(steps)
        if abs(measured_hz - self.expected_hz) <= RATE_TOLERANCE * self.expected_hz:
            return None, measured_hz
        for clock in CLOCKS_HZ:
            if clock != self.layout.timestamp_hz:
                rescaled_hz = measured_hz * clock / self.layout.timestamp_hz
                if abs(rescaled_hz - self.expected_hz) <= RATE_TOLERANCE * self.expected_hz:
                    return clock, measured_hz
        return None, measured_hz


def _median(values: list[float]) -> float:
    finite = [v for v in values if math.isfinite(v)]
    return statistics.median(finite) if finite else math.nan


def _bits(layout: LpBusLayout) -> str:
    bits = [spec.bit for spec in layout.specs]
    text = ", ".join(map(str, sorted(bits)))
    if layout.generation == "legacy" and layout.precision == 16:
        text += ", 22 (16-bit)"
    return f"{layout.generation} {text}"
