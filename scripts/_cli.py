"""``@command``: Hydra's entry point for every gyronet script, with every bad input as one line and exit 2.

Hydra reports its own configuration errors (an unknown key, a missing value, a bad override, an
unknown config option) in several lines and exits 1, and wraps what a constructor raises in its
own exception. Here they all become ``error: <one line>`` on stderr and exit status 2, as the
library's ``GyronetError`` does; an unknown key gets the closest known one as a suggestion.
Anything else is a bug and keeps its traceback.

In a multirun, a failed job raises instead (a sweeper scores it inf) with the same one-line text.
"""
from __future__ import annotations

import difflib
import errno
import functools
import logging
import os
import re
import subprocess
import sys
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.experimental.callback import Callback
from hydra.errors import (ConfigCompositionException, HydraException, InstantiationException,
                          MissingConfigException, OverrideParseException)
from hydra.types import RunMode
from omegaconf import DictConfig, ListConfig, OmegaConf
from omegaconf.errors import (ConfigAttributeError, ConfigKeyError, MissingMandatoryValue,
                              OmegaConfBaseException)

from gyronet.atomic import refuse_overwriting
from gyronet.errors import ConfigError, fail, in_chain, one_line, user_error

from _settings import check_settings, config_keys, unknown_setting  # scripts/_settings.py, beside this file

# a launcher's workers (submitit's local processes, SLURM's jobs) are fresh interpreters that unpickle
# the task function by module name: they inherit the environment, so they find this folder too
_SCRIPTS = str(Path(__file__).resolve().parent)
if _SCRIPTS not in os.environ.get("PYTHONPATH", "").split(os.pathsep):
    os.environ["PYTHONPATH"] = os.pathsep.join(p for p in (_SCRIPTS, os.environ.get("PYTHONPATH")) if p)

log = logging.getLogger(__name__)

CONF_DIR = Path(__file__).resolve().parent.parent / "conf"
SCRIPTS_DIR = Path(__file__).resolve().parent


def run_script(script: str, *overrides: str) -> None:
    """One step as the README's command for it, in its own interpreter (its own Hydra run).

    A failure is a ``GyronetError`` with the step and the script's own last error line.
    """
    from gyronet.errors import GyronetError

    command_line = [sys.executable, str(SCRIPTS_DIR / script), *overrides]
    log.info("%s", " ".join(command_line[1:]))
    done = subprocess.run(command_line, capture_output=True, text=True)
    if done.returncode != 0:
        last = (done.stderr.strip().splitlines() or ["(no message)"])[-1].removeprefix("error: ")
        raise GyronetError(f"{script} {' '.join(overrides)} failed: {last}")


GRAMMAR_URL = "https://hydra.cc/docs/advanced/override_grammar/basic/"
Task = Callable[[DictConfig], Any]
_OURS = "GYRONET_CLI_SET_HYDRA_FULL_ERROR"  # marks HYDRA_FULL_ERROR as set by command(), for child processes


def command(config_name: str, config_dir: str = "", schemas: Mapping[str, Any] | None = None,
            required: Sequence[str] = ()) -> Callable[[Task], Callable[[], Any]]:
    """Decorate a script's task: ``@hydra.main`` on ``conf/<config_dir>/<config_name>.yaml``, errors as one line.

    Parameters
    ----------
    config_name, config_dir
        The primary config, ``conf/<config_dir>/<config_name>.yaml``.
    schemas
        What a config node is, by dotted key: the keyword arguments of a callable, by its dotted
        path (``{"train": "gyronet.training.train.fit"}``), or a value of a type (``{"seed": int}``). A key
        the callable does not take, or a value of the wrong type, is refused before the task runs.
        Nodes with a ``_target_`` are checked against their target without this.
    required
        Dotted keys that must have a value (not ``???``) before the task runs: those a task reads
        with ``OmegaConf.to_container``, which passes ``???`` on as a string.
    """

    def decorate(task: Task) -> Callable[[], Any]:
        guarded = _guard(task, dict(schemas or {}), tuple(required))
        hydra_main = hydra.main(version_base="1.3", config_path=str(CONF_DIR / config_dir),
                                config_name=config_name)(guarded)

        @functools.wraps(task)
        def main() -> Any:
            _refuse_file_globs(sys.argv[1:], CONF_DIR / config_dir)
            # the user asked for Hydra's full tracebacks (not we, for a parent command)
            if os.environ.get("HYDRA_FULL_ERROR") == "1" and _OURS not in os.environ:
                return hydra_main()
            # Hydra then raises its errors instead of printing them in several lines and exiting 1
            os.environ.update({"HYDRA_FULL_ERROR": "1", _OURS: "1"})
            try:
                return hydra_main()
            except KeyboardInterrupt:  # Ctrl-C: one line, not the traceback of wherever it landed
                print("interrupted (Ctrl-C)", file=sys.stderr, flush=True)
                raise SystemExit(130) from None
            except Exception as err:
                message = user_message(err)
                if message is None:
                    raise
                log.debug("failed", exc_info=True)
                fail(message)
            finally:
                os.environ.pop("HYDRA_FULL_ERROR", None)
                os.environ.pop(_OURS, None)

        main.__wrapped__ = guarded  # type: ignore[attr-defined]  # the task as Hydra runs it
        return main

    return decorate


class SetAsideEarlierOutputs(Callback):
    """fleet.py's Hydra callback: a unit's job moves its earlier run's outputs into ``previous/`` before it starts,
    so a re-run that fails is not tabulated with the earlier bundle (a launch refused outright touches nothing)."""

    def on_job_start(self, config: DictConfig, **kwargs: Any) -> None:
        from gyronet.training.fleet import set_aside_outputs  # only fleet.py's jobs need it

        set_aside_outputs(config.hydra.runtime.output_dir)


# Hydra's own flags; any other --name is a habit from argparse tools
HYDRA_FLAGS = ("--multirun", "--help", "--hydra-help", "--version", "--cfg", "--resolve", "--package", "--run",
               "--config-path", "--config-name", "--config-dir", "--info", "--shell-completion", "--experimental-rerun")


def _refuse_file_globs(overrides: Sequence[str], conf_dir: Path) -> None:
    """``key=glob(...)`` on a key that is not a config group: Hydra would sweep nothing and exit 0; ``--model X``
    (argparse's style) would print Hydra's usage."""
    for at, override in enumerate(overrides):
        name = override.split("=")[0]
        if name.startswith("--") and len(name) > 2 and name not in HYDRA_FLAGS:
            value = override.partition("=")[2] or (overrides[at + 1] if at + 1 < len(overrides) else "VALUE")
            fail(f"{override}: options are key=value, not --key value: write {name[2:]}={value}")
    for override in overrides:
        key, sep, value = override.partition("=")
        group = key.lstrip("+~").split("@")[0].replace(".", "/")
        if sep and value.strip().startswith("glob(") and not (conf_dir / group).is_dir():
            fail(f"{key}=glob(...) sweeps nothing: Hydra's glob() chooses among a config group's options, and "
                 f"{key} is not a group; for recording files use scripts/fleet.py '{key}={value}'")


def _guard(task: Task, schemas: Mapping[str, Any], required: Sequence[str]) -> Task:
    """The task as Hydra runs it: settings checked first; a user error ends a single run in one line."""

    @functools.wraps(task)
    def guarded(cfg: DictConfig) -> Any:
        try:
            check_settings(cfg, schemas, required)
            if all(k in cfg and not OmegaConf.is_missing(cfg, k) for k in ("input", "output")):
                refuse_overwriting(str(cfg.input), str(cfg.output))  # compensate, convert, allan, ...
            return task(cfg)
        except Exception as err:
            message = user_message(err)
            if message is None:
                raise
            if HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN:
                # the sweeper records the failure (one line) and scores it inf; the job's log keeps it too, as
                # Hydra prints only a multirun's first failure
                log.error("%s", message)
                found = user_error(err)
                if found is err:
                    raise
                if found is not None:  # ours, unwrapped from Hydra's InstantiationException
                    raise found from None
                raise ConfigError(message) from err
            log.debug("failed", exc_info=True)
            fail(message)  # before Hydra's own "Error executing job" line

    return guarded


# ---------------------------------------------------------------- messages


def user_message(err: BaseException) -> str | None:
    """The one-line message for a user error (ours, Hydra's or OmegaConf's), or None for a bug."""
    found = user_error(err)
    if found is not None:
        return str(found)
    missing = in_chain(err, MissingMandatoryValue)
    if missing is not None:
        key = missing.full_key or missing.key
        return f"no value for {key}: add {key}=..." if key else one_line(missing.msg or str(missing))
    if isinstance(err, OverrideParseException):
        reason = str(err.message).splitlines()[0] if err.message else "cannot parse it"
        return f"bad override {err.override!r}: {reason} (see {GRAMMAR_URL})"
    if isinstance(err, MissingConfigException):
        return _missing_option(err)
    if isinstance(err, ConfigCompositionException):
        unknown = _unknown_override(err)
        if unknown is not None:
            return unknown
    if isinstance(err, InstantiationException):
        cause = err.__cause__
        what = re.search(r"full_key: (\S+)", str(err))
        target = re.search(r"target '([^']+)'", str(err))
        reason = f"{type(cause).__name__}: {cause}" if cause is not None else str(err).splitlines()[0]
        name = what.group(1) if what else (target.group(1) if target else "an object")
        return one_line(f"cannot build {name}" + (f" ({target.group(1)})" if what and target else "")
                        + f": {reason}")
    if isinstance(err, HydraException):
        text = str(err).split("Config search path:")[0]
        cause = err.__cause__
        if isinstance(cause, OmegaConfBaseException):
            text += f": {_omegaconf_text(cause)}"
        return one_line(text)
    if isinstance(err, OmegaConfBaseException):
        return _omegaconf_text(err)
    if isinstance(err, OSError) and (err.filename is not None or err.errno in _USER_ERRNOS):
        # a path that cannot be read or written, a full disk: the user's to fix, not a bug
        where = f"{err.filename}: " if err.filename is not None else ""
        return f"{where}{err.strerror or err}"
    return None


_USER_ERRNOS = {errno.ENOSPC, errno.EDQUOT, errno.EACCES, errno.EROFS, errno.EPERM}


def _omegaconf_text(err: OmegaConfBaseException) -> str:
    first = (getattr(err, "msg", None) or str(err)).splitlines()[0].strip()
    key = getattr(err, "full_key", None)
    return f"{first} ({key})" if key and key not in first else first


def _missing_option(err: MissingConfigException) -> str:
    """``model=nope``: the group's options, and the closest one."""
    missing = err.missing_cfg_file or ""
    options = list(err.options or [])
    if "/" not in missing or not options:
        return one_line(str(err).split("Config search path:")[0])
    group, name = missing.rsplit("/", 1)
    match = difflib.get_close_matches(name, options, n=1, cutoff=0.6)
    hint = f"did you mean {group}={match[0]}? " if match else ""
    return f"no option {name!r} for {group}; {hint}the options are {', '.join(options)}"


def _unknown_override(err: ConfigCompositionException) -> str | None:
    """``data.pth=x``: the key does not exist (Hydra would suggest ``+data.pth=x``, which then fails)."""
    cause = in_chain(err, (ConfigAttributeError, ConfigKeyError))
    if cause is None:
        return None
    named = re.search(r"Could not override '([^']+)'", str(err))
    key = named.group(1) if named else (cause.full_key or cause.key)
    if not key:
        return None
    parent = getattr(cause, "parent_node", None)
    root = parent._get_root() if isinstance(parent, (DictConfig, ListConfig)) else None
    known = config_keys(root, key.startswith("hydra.")) if isinstance(root, DictConfig) else []
    return unknown_setting(key, known)
