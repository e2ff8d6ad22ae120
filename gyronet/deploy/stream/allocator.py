"""Keep glibc's malloc from holding on to freed memory over a long live run.

glibc serves a request of at least its mmap threshold (128 KiB at start) with its own ``mmap``,
given back to the system when freed, but by default it raises the threshold to the size of each
such block freed, after which blocks of up to that size come from the heap, whose freed middle it
keeps. Over one hour of 1 kHz data flooded through the live loop in-process, with the Allan
monitor (without it the RSS stayed flat), the RSS rose 10-14 MB, of which ``malloc_trim(0)`` at
the end gave back 8-9 MB; with the threshold fixed it rose 3-5 MB. Fixing it once costs nothing
per sample.

It is fixed at 4 MiB, not at glibc's starting 128 KiB: a flood's chunk (up to ~1,500 frames from
one 64 KiB read) makes arrays of several hundred KiB (the RBF layers' (n, 60) float64), and below
the threshold each was a fresh ``mmap`` whose page faults cost ~1.1 us of CPU a sample flooded
(in-process, LP-BUS: 6.6 -> 5.9 us a sample). In-process over one hour of 1 kHz frames flooded,
the RSS then stays flat after the first 120,000 samples (417 MB from there to the end; at 128 KiB
407 -> 410 MB).

Through ``stream.py`` the heap still kept what the Allan monitor frees below blocks in use (its
history's doublings, each report's temporaries): over an hour of 1 kHz frames its free memory grew
from 1 to 18 MB while 3 MB more was in use. :func:`trim_heap`, when each report falls due, hands
those pages back (0.2-0.8 ms once every ``allan_every_s`` of data).
"""
from __future__ import annotations

import ctypes
import functools
import logging
import sys

log = logging.getLogger(__name__)

M_MMAP_THRESHOLD = -3  # mallopt's parameter (glibc malloc.h)
MMAP_THRESHOLD_BYTES = 4 * 1024 * 1024  # above a flood chunk's arrays (glibc starts at 128 KiB), kept from here on


@functools.lru_cache(maxsize=1)
def _glibc() -> ctypes.CDLL | None:
    """The process's C library where it is glibc (has ``mallopt`` and ``malloc_trim``), else None."""
    if not sys.platform.startswith("linux"):
        return None
    try:  # another C library: musl has mallopt as a no-op or not at all, and no malloc_trim
        libc = ctypes.CDLL(None)
        libc.mallopt, libc.malloc_trim  # noqa: B018 - looked up to fail here, not at the call
    except (OSError, AttributeError):
        return None
    return libc


def fix_mmap_threshold(threshold_bytes: int = MMAP_THRESHOLD_BYTES) -> bool:
    """Fix glibc's mmap threshold (no longer raised as blocks are freed); False where there is no glibc."""
    libc = _glibc()
    if libc is None:
        return False
    libc.mallopt.argtypes, libc.mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    done = bool(libc.mallopt(M_MMAP_THRESHOLD, int(threshold_bytes)))
    if not done:
        log.debug("mallopt(M_MMAP_THRESHOLD, %d) refused", threshold_bytes)
    return done


def trim_heap() -> bool:
    """Hand the heap's free pages back to the system (``malloc_trim``); True if any went back."""
    libc = _glibc()
    return libc is not None and bool(libc.malloc_trim(0))
