"""Errors a user can act on, and the one place where they become a one-line message and an exit code."""
from __future__ import annotations

import functools
import logging
import sys
from typing import Callable, TypeVar

log = logging.getLogger(__name__)

F = TypeVar("F", bound=Callable)


class GyronetError(Exception):
    """A problem with the user's input or configuration, worded for the user."""


class RecordingError(GyronetError, ValueError):
    """A recording that does not follow the CSV format of CONTRACT.md section 1."""


class BundleError(GyronetError):
    """A compensator bundle that is missing, incomplete or incompatible with the data."""


def exit_on_error(fn: F) -> F:
    """Turn a GyronetError raised by a command into one line on stderr and exit status 2.

    Scripts wrap their Hydra task with this, below ``@hydra.main``, so that bad input never shows a
    traceback. Other exceptions are bugs and keep their traceback.
    """

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except GyronetError as err:
            log.debug("failed", exc_info=True)
            print(f"error: {err}", file=sys.stderr, flush=True)
            raise SystemExit(2) from None

    return wrapper  # type: ignore[return-value]
