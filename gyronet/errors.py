"""Errors a user can act on, and the one place where they become a one-line message and an exit code."""
from __future__ import annotations

import functools
import logging
import sys
from typing import Any, Callable, NoReturn, TypeVar

log = logging.getLogger(__name__)

F = TypeVar("F", bound=Callable)

EXIT_BAD_INPUT = 2  # every command's exit status for bad input (argparse's too)


class GyronetError(Exception):
    """A problem with the user's input or configuration, worded for the user."""


class RecordingError(GyronetError, ValueError):
    """A recording that does not follow the CSV format of CONTRACT.md section 1."""


class BundleError(GyronetError):
    """A compensator bundle that is missing, incomplete or incompatible with the data."""


class ConfigError(GyronetError):
    """A setting that does not exist, has no value, or cannot be read."""


def in_chain(err: BaseException, kind: type) -> Any:
    """The first exception of ``kind`` along ``err``'s ``raise ... from`` / context chain (``err`` first), or None."""
    seen: set[int] = set()
    current: BaseException | None = err
    while current is not None and id(current) not in seen:
        if isinstance(current, kind):
            return current
        seen.add(id(current))
        current = current.__cause__ or current.__context__
    return None


def user_error(err: BaseException) -> GyronetError | None:
    """The GyronetError behind ``err``: itself, or the first one along its chain.

    Libraries that call our code (Hydra's ``instantiate``) wrap what it raises; the user still
    needs our message, not the wrapper's.
    """
    return in_chain(err, GyronetError)


def one_line(message: str) -> str:
    """``message`` on one line: its lines joined, blank ones dropped."""
    return " ".join(line.strip() for line in str(message).splitlines() if line.strip())


def fail(message: str) -> NoReturn:
    """Print ``error: <message>`` as one line on stderr and exit with status 2."""
    print(f"error: {one_line(message)}", file=sys.stderr, flush=True)
    raise SystemExit(EXIT_BAD_INPUT)


def exit_on_error(fn: F) -> F:
    """Turn a GyronetError raised by a command (or one it caused) into one line on stderr and exit status 2.

    Scripts get this through ``scripts/_cli.py``'s ``command``, which also covers Hydra's own
    configuration errors. Other exceptions are bugs and keep their traceback.
    """

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except Exception as err:
            found = user_error(err)
            if found is None:
                raise
            log.debug("failed", exc_info=True)
            fail(str(found))

    return wrapper  # type: ignore[return-value]
