"""A real-time scheduling priority for the sample loop: at 1 kHz the latency's tail is the scheduler's.

At 1 kHz a frame's row is written within 0.2 ms of the read that brought it (p99), but 0.3-1.3 ms
after the sensor sent it (p99 over 300 s on an idle 2-core VM, from run to run): the rest is time
spent waiting to be woken. Under ``SCHED_FIFO`` the stream runs before every normal process as
soon as its frame arrives. Linux only; it needs root, ``CAP_SYS_NICE`` or an ``RLIMIT_RTPRIO`` of
at least the priority. Threads the loop starts later inherit the policy, so a helper thread (the
Allan worker) goes back to the normal scheduler itself (:func:`normal_thread`).
"""
from __future__ import annotations

import os
from typing import Callable

from gyronet.errors import ConfigError


def use_realtime(priority: int | None) -> Callable[[], None]:
    """Run the calling thread under ``SCHED_FIFO`` at ``priority`` (None: leave it); return what restores it."""
    if priority is None:
        return lambda: None
    if not hasattr(os, "sched_setscheduler"):
        raise ConfigError("realtime_priority needs Linux's SCHED_FIFO: leave it null on this OS")
    low, high = os.sched_get_priority_min(os.SCHED_FIFO), os.sched_get_priority_max(os.SCHED_FIFO)
    if not low <= int(priority) <= high:
        raise ConfigError(f"realtime_priority={priority}: SCHED_FIFO priorities run from {low} to {high}")
    policy, param = os.sched_getscheduler(0), os.sched_getparam(0)
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(int(priority)))
    except PermissionError as err:
        raise ConfigError(f"realtime_priority={priority}: the OS refused SCHED_FIFO ({err.strerror}); run as root, "
                          "grant the interpreter CAP_SYS_NICE or raise RLIMIT_RTPRIO, or leave it null") from None
    return lambda: os.sched_setscheduler(0, policy, param)


def normal_thread() -> None:
    """Put the calling thread back on the normal scheduler, if it inherited another policy from its parent."""
    if hasattr(os, "sched_getscheduler") and os.sched_getscheduler(0) != os.SCHED_OTHER:
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
