"""A sweep's jobs die with it: a launcher's worker process exits as soon as the sweeping process is gone.

joblib's loky workers are children of the sweeping process, and nothing stops them when it is
killed (SIGKILL runs no cleanup): they finish the job at hand and take the next queued ones,
writing into the job folders that a resumed sweep reuses. The sweeper hands the launcher its task
wrapped in :class:`WatchedTask`; in a worker process (a direct child of the sweep), its first call
starts a daemon thread that polls the parent pid and ends the process when the sweep is gone.
Jobs the sweep runs in its own process (the basic launcher), or on other machines (a cluster
launcher), are left alone. On resume, the folders of the interrupted generation's jobs are set
aside (:func:`set_aside_interrupted_jobs`), so the jobs run again into clean folders.
"""
from __future__ import annotations

import functools
import logging
import os
import threading
import time
from pathlib import Path
from typing import Any, Callable, List, Optional

log = logging.getLogger(__name__)

POLL_S = 0.2  # how often a worker checks its parent: the longest a worker outlives a killed sweep
EXIT_STATUS = 70  # the worker's exit status when it stops because the sweep is gone

_watched: set = set()
_lock = threading.Lock()


class WatchedTask:
    """``task`` as the launcher runs it: in a worker process of the sweep, the worker exits with the sweep."""

    def __init__(self, task: Callable[..., Any], sweep_pid: int | None = None) -> None:
        self.task = task
        self.sweep_pid = os.getpid() if sweep_pid is None else sweep_pid
        functools.update_wrapper(self, task)

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        watch_parent(self.sweep_pid)
        return self.task(*args, **kwargs)


def watch_parent(sweep_pid: int, poll_s: float = POLL_S) -> bool:
    """In a direct child of ``sweep_pid``, start (once per process) the thread that exits when it dies.

    Returns whether this process is watched: False in the sweep's own process, and in a process
    the sweep did not start (a job on a cluster node).
    """
    if os.getpid() == sweep_pid or os.getppid() != sweep_pid:
        return False
    with _lock:
        if sweep_pid not in _watched:
            _watched.add(sweep_pid)
            threading.Thread(target=_exit_when_orphaned, args=(sweep_pid, poll_s),
                             name="gyronet-ga-watchdog", daemon=True).start()
    return True


def _exit_when_orphaned(sweep_pid: int, poll_s: float) -> None:
    # when the parent dies, the kernel reparents this process at once: its parent pid changes
    while os.getppid() == sweep_pid:
        time.sleep(poll_s)
    try:
        log.warning("the sweep (pid %d) is gone: worker %d stops its job and exits", sweep_pid, os.getpid())
    finally:
        os._exit(EXIT_STATUS)


JOB_NUM_SUBDIR = "${hydra.job.num}"  # Hydra's default hydra.sweep.subdir: job n writes to <sweep dir>/n
INTERRUPTED_DIR = "interrupted"


def set_aside(path: Path) -> Path:
    """Move ``path`` (a file or folder in the sweep dir) to ``<sweep dir>/interrupted/``, as ``name.1``,
    ``name.2``, ... if an earlier one is there; return where it went."""
    target, n = path.parent / INTERRUPTED_DIR / path.name, 1
    while target.exists():
        target, n = path.parent / INTERRUPTED_DIR / f"{path.name}.{n}", n + 1
    target.parent.mkdir(exist_ok=True)
    path.rename(target)
    return target


def set_aside_interrupted_jobs(sweep_dir: Path, first_job: int, subdir: Optional[str]) -> List[Path]:
    """Move the folders of jobs numbered ``first_job`` and up (run by an interrupted sweep, in no
    history) to ``<sweep dir>/interrupted/``, so a resumed job does not write beside its killed
    predecessor's files (two event files in one ``tb/``). Only with the default ``subdir``, where
    a folder's name is its job number; returns where they went.
    """
    if subdir != JOB_NUM_SUBDIR or not sweep_dir.is_dir():
        return []
    moved = [set_aside(folder) for folder in sorted(sweep_dir.iterdir())
             if folder.is_dir() and folder.name.isdigit() and int(folder.name) >= first_job]
    if moved:
        log.warning("set aside %d folder(s) of the interrupted generation's jobs in %s", len(moved),
                    sweep_dir / INTERRUPTED_DIR)
    return moved
