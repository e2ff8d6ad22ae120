"""One channel group of an LP-BUS sensor-data frame: the type both generations' tables share."""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class LpBusField:
    """One channel group of a sensor-data frame (command 9).

    ``angular``: a rate or an angle, sent in rad/s (rad) or deg/s (deg) as the generation and its
    setting say, always given here in deg/s (deg). ``scale_16bit``: int16 / scale = value in 16-bit
    mode; ``scale_16bit_rad``: the same when the sensor sends radians, if that scale differs.
    """

    name: str
    bit: int  # bit of the output register that enables it
    columns: tuple[str, ...]
    angular: bool
    scale_16bit: float
    scale_16bit_rad: float | None = None

    def scale(self, radians: bool) -> float:
        """The 16-bit scale for the unit the sensor sends."""
        return self.scale_16bit_rad if radians and self.scale_16bit_rad is not None else self.scale_16bit
