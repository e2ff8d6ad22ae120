"""A run's port speed, read timeout and stop limits, refused before the port opens: a bad one ended in a traceback
after the sensor was set up (``duration_s=abc``), or in a silently short run (``max_samples=-3``: one sample)."""
from __future__ import annotations

import math

from gyronet.errors import ConfigError


def check_run_limits(baud: int, max_samples: int | None, duration_s: float | None, read_timeout_s: float) -> None:
    """Refuse, in one line, a ``baud`` or ``max_samples`` that is not a positive integer, or a ``duration_s`` or
    ``read_timeout_s`` that is not a positive number (``duration_s``/``max_samples`` may be None: no limit)."""
    for name, value in (("baud", baud), ("max_samples", max_samples)):
        if value is None and name == "max_samples":
            continue
        if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
            raise ConfigError(f"{name} must be a positive integer{' or null' if name == 'max_samples' else ''}, "
                              f"got {value!r}")
    for name, value in (("duration_s", duration_s), ("read_timeout_s", read_timeout_s)):
        if value is None and name == "duration_s":
            continue
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not value > 0 or \
                (name == "read_timeout_s" and not math.isfinite(value)):
            raise ConfigError(f"{name} must be a positive number of seconds{' or null' if name == 'duration_s' else ''}"
                              f", got {value!r}")
