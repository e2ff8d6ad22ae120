"""The real-time priority of the sample loop (gyronet.deploy.stream.priority): taken, given back, refused in one line."""
import os
import threading

import pytest

from gyronet.errors import ConfigError
from gyronet.deploy.stream import priority
from gyronet.deploy.stream.priority import normal_thread, use_realtime

linux_only = pytest.mark.skipif(not hasattr(os, "sched_setscheduler"), reason="SCHED_FIFO is Linux's")


@pytest.fixture
def fifo() -> None:
    """Skip where this user may not use SCHED_FIFO; probed when a test needs it, not as the file is collected."""
    if not hasattr(os, "sched_setscheduler"):
        pytest.skip("SCHED_FIFO is Linux's")
    try:
        use_realtime(1)()
    except ConfigError:
        pytest.skip("this user may not use SCHED_FIFO (not root, no CAP_SYS_NICE)")


def test_the_loop_runs_under_fifo_and_gets_the_normal_scheduler_back(fifo):
    restore = use_realtime(10)
    try:
        assert os.sched_getscheduler(0) == os.SCHED_FIFO
        assert os.sched_getparam(0).sched_priority == 10
    finally:
        restore()
    assert os.sched_getscheduler(0) == os.SCHED_OTHER


def test_a_thread_started_by_the_loop_inherits_fifo_and_goes_back_to_normal(fifo):
    seen = []

    def worker():
        seen.append(os.sched_getscheduler(0))
        normal_thread()
        seen.append(os.sched_getscheduler(0))

    restore = use_realtime(10)
    try:
        thread = threading.Thread(target=worker)
        thread.start()
        thread.join(5)
        assert os.sched_getscheduler(0) == os.SCHED_FIFO  # the loop's own thread keeps its priority
    finally:
        restore()
    assert seen == [os.SCHED_FIFO, os.SCHED_OTHER]


@linux_only
def test_a_refused_priority_is_one_line_naming_the_fix(monkeypatch):
    def refuse(*args):
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(priority.os, "sched_setscheduler", refuse)
    with pytest.raises(ConfigError, match=r"realtime_priority=50: the OS refused SCHED_FIFO \(Operation not permitted\)"
                                          r".*CAP_SYS_NICE"):
        use_realtime(50)


@linux_only
@pytest.mark.parametrize("value", [0, 100])
def test_a_priority_outside_fifos_range_is_refused(value):
    with pytest.raises(ConfigError, match="priorities run from 1 to 99"):
        use_realtime(value)


def test_none_leaves_the_scheduler_alone():
    before = os.sched_getscheduler(0) if hasattr(os, "sched_getscheduler") else None
    use_realtime(None)()
    assert (os.sched_getscheduler(0) if before is not None else None) == before
