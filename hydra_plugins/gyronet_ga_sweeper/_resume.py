"""Starting a sweep in its folder: one sweep at a time, a new history or the one to resume, and what must match.

A resumed sweep reuses cached fitness figures, which compare only if the search, the fixed settings, the
files they name and the breeding options are the same; anything else is refused in one line. A last
generation that stopped the sweep for failures is run again, so "fix the cause and rerun" works.
"""
from __future__ import annotations

import errno
import hashlib
import logging
import os
from dataclasses import asdict
from pathlib import Path
from typing import Any, Dict, List, Optional

from hydra.errors import HydraException

from ._history import HISTORY_FILE, Generation, History
from ._watchdog import set_aside, set_aside_interrupted_jobs
from .config import GAOptions

log = logging.getLogger(__name__)

LOCK_FILE = ".ga_sweep.lock"
# the options that decide which individuals are bred: another value breeds another sweep
BREEDING = ("population_size", "tournament_size", "crossover_rate", "mutation_rate", "mutation_scale", "elitism",
            "seed", "start_from_config")
RESULTS_FILE = "optimization_results.yaml"  # the best so far, written by _impl
NEW_DIR = "use a new hydra.sweep.dir, or hydra.sweeper.resume=false to start over there"


class GASweepError(HydraException):
    """The sweep cannot go on: too many failed jobs, or a history that does not match."""


def lock_sweep_dir(sweep_dir: Path) -> Optional[Any]:
    """Hold ``<sweep dir>/.ga_sweep.lock`` for this process's life (None where ``fcntl`` is missing), or refuse:
    two sweeps in one folder train into the same job folders and overwrite each other's history."""
    try:
        import fcntl
    except ImportError:  # not POSIX: no lock
        return None
    handle = open(sweep_dir / LOCK_FILE, "a+")
    try:
        fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError as err:
        handle.close()
        if err.errno not in (errno.EAGAIN, errno.EWOULDBLOCK, errno.EACCES):  # a file system without locks (NFS)
            log.warning("cannot lock %s (%s): nothing stops a second sweep in this folder", sweep_dir / LOCK_FILE,
                        err.strerror or err)
            return None
        raise GASweepError(f"another GA sweep is running in {sweep_dir} (it holds {sweep_dir / LOCK_FILE}); "
                           "wait for it, or use another hydra.sweep.dir") from None
    handle.seek(0)
    handle.truncate()
    handle.write(f"{os.getpid()}\n")
    handle.flush()
    return handle


def file_digests(fixed: List[str]) -> Dict[str, str]:
    """SHA-256 of every existing file a fixed override names (``k=v`` or ``k=[a,b]``): the data the fitness is
    of, which the same override text could name with other contents."""
    digests = {}
    for override in fixed:
        value = override.partition("=")[2].strip()
        items = value[1:-1].split(",") if value.startswith("[") and value.endswith("]") else [value]
        for item in (i.strip().strip("'\"") for i in items):
            if item and Path(item).is_file():  # hashed here: gyronet.bundle.io's sha256_file would import torch
                digest = hashlib.sha256()
                with open(item, "rb") as f:
                    for chunk in iter(lambda: f.read(1 << 20), b""):
                        digest.update(chunk)
                digests[item] = digest.hexdigest()
    return digests


def too_many_failed(gen: Generation, max_failure_rate: float) -> bool:
    """Whether ``gen`` stops the sweep: more than ``max_failure_rate`` of its jobs failed."""
    summary = gen.summary()
    return summary["jobs"] > 0 and summary["failed"] / summary["jobs"] > max_failure_rate


def start(sweep_dir: Path, space_json: List[Dict[str, Any]], fixed: List[str], options: GAOptions,
          subdir: Optional[str]) -> History:
    """A new history, or the one in the sweep dir when resuming; the folders of jobs in no history set aside."""
    path = sweep_dir / HISTORY_FILE
    new = History(space_json, fixed, options=asdict(options), fixed_files=file_digests(fixed))
    old = _resumable(path, options)
    if old is None:  # a generation 0 that was killed, or a sweep started over: nothing of theirs is written into
        set_aside_interrupted_jobs(sweep_dir, 0, subdir)
        # its curves (the new steps would restart in them), and its results, which a kill before the new
        # generation 0 is saved would otherwise resume
        for name in ("tb", HISTORY_FILE, RESULTS_FILE, "best"):
            if (sweep_dir / name).exists():
                set_aside(sweep_dir / name)
        return new
    if old.search_space != space_json:
        raise GASweepError(f"{path} is a sweep over another search space ({old.search_space}); {NEW_DIR}")
    if sorted(old.fixed_overrides) != sorted(fixed):  # another recording or setting: its fitness would not compare
        raise GASweepError(f"{path} is a sweep with other fixed overrides ({old.fixed_overrides}, now {fixed}); "
                           f"{NEW_DIR}")
    changed = [f + ("" if f in new.fixed_files else " (gone)") for f, digest in old.fixed_files.items()
               if new.fixed_files.get(f) != digest]  # a file gone since is not the same data either
    if changed:
        raise GASweepError(f"{path} is a sweep of other data: {', '.join(changed)} changed since; {NEW_DIR}")
    bred = {k: (old.options[k], getattr(options, k)) for k in BREEDING if old.options.get(k, getattr(options, k))
            != getattr(options, k)}
    if bred:
        raise GASweepError(f"{path} was bred with other options ("
                           + ", ".join(f"{k} {a} now {b}" for k, (a, b) in bred.items()) + f"); {NEW_DIR}")
    old.options = asdict(options)
    log.info("resuming %s: %d generation(s) done", path, len(old.generations))
    set_aside_interrupted_jobs(sweep_dir, old.next_job_idx(), subdir)
    return old


def _resumable(path: Path, options: GAOptions) -> Optional[History]:
    """The history to resume, None to start anew; its last generation dropped if it stopped the sweep."""
    if not path.exists():
        return None
    if not options.resume:
        log.warning("resume=false: starting over, %s will be overwritten and the old job folders set aside", path)
        return None
    try:
        old = History.load(path)
    except (ValueError, KeyError, TypeError) as err:  # JSONDecodeError is a ValueError
        raise GASweepError(f"cannot resume from {path}: {err}; {NEW_DIR}") from err
    if old.generations and too_many_failed(old.generations[-1], options.max_failure_rate):
        log.warning("generation %d stopped the sweep for failed jobs: running it again", old.generations[-1].index)
        old.generations.pop()
        old.final_run = None
        if not old.generations:  # nothing to reuse: the fix may be a changed setting
            return None
    return old
