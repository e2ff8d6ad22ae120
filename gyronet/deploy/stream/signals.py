"""SIGINT and SIGTERM as a stop flag that a run polls (``stream.py``, ``record.py``); imports no torch."""
from __future__ import annotations

import contextlib
import signal
import threading
from typing import Callable, Iterator


@contextlib.contextmanager
def stop_on_signals(signals: tuple[int, ...] = (signal.SIGINT, signal.SIGTERM)) -> Iterator[Callable[[], bool]]:
    """Within the block, SIGINT and SIGTERM ask the run to stop; yields the ``stop`` poll for ``run_stream``.

    The handlers are installed explicitly, whatever the parent left: a shell starts a background
    job with SIGINT ignored, and an inherited SIG_IGN would make Ctrl-C (or ``kill -INT``) do
    nothing. A handler only sets a flag, so no write is cut in the middle. The previous handlers
    are restored on exit. Only the main thread can install handlers; elsewhere this does nothing.
    """
    requested = threading.Event()
    if threading.current_thread() is not threading.main_thread():
        yield requested.is_set
        return

    def _request(signum, frame):
        requested.set()

    previous = {signum: signal.signal(signum, _request) for signum in signals}
    try:
        yield requested.is_set
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
