"""``@command``: Hydra's entry point for every gyronet script, with every bad input as one line and exit 2.

Hydra reports its own configuration errors (an unknown key, a missing value, a bad override, an
unknown config option) in several lines and exits 1, and wraps what a constructor raises in its
own exception. Here they all become ``error: <one line>`` on stderr and exit status 2, as the
library's ``GyronetError`` does; an unknown key gets the closest known one as a suggestion.
Anything else is a bug and keeps its traceback.

In a multirun, a failed job raises instead (a sweeper scores it inf) with the same one-line text.
"""
from __future__ import annotations

import collections.abc
import difflib
import errno
import functools
import importlib
import inspect
import logging
import os
import re
import subprocess
import sys
import types
import typing
from pathlib import Path
from typing import Any, Callable, Iterator, Mapping, Sequence

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.errors import (ConfigCompositionException, HydraException, InstantiationException,
                          MissingConfigException, OverrideParseException)
from hydra.types import RunMode
from omegaconf import DictConfig, ListConfig, OmegaConf
from omegaconf.errors import (ConfigAttributeError, ConfigKeyError, MissingMandatoryValue,
                              OmegaConfBaseException)

from gyronet.errors import ConfigError, fail, in_chain, one_line, user_error

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


def _refuse_file_globs(overrides: Sequence[str], conf_dir: Path) -> None:
    """``key=glob(...)`` on a key that is not a config group: Hydra would sweep nothing and exit 0."""
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
            return task(cfg)
        except Exception as err:
            message = user_message(err)
            if message is None:
                raise
            if HydraConfig.initialized() and HydraConfig.get().mode == RunMode.MULTIRUN:
                # the sweeper records the failure (one line) and scores it inf
                found = user_error(err)
                if found is err:
                    raise
                if found is not None:  # ours, unwrapped from Hydra's InstantiationException
                    raise found from None
                raise ConfigError(message) from err
            log.debug("failed", exc_info=True)
            fail(message)  # before Hydra's own "Error executing job" line

    return guarded


# ---------------------------------------------------------------- settings the code cannot take


def check_settings(cfg: DictConfig, schemas: Mapping[str, Any] = {}, required: Sequence[str] = ()) -> None:
    """Refuse, before any work, a setting that would end in a traceback deep inside the code.

    That is a ``required`` key without a value; a key (added with ``+key=``) that the node's
    ``_target_`` or schema callable does not take; and a value of the wrong type for its typed
    parameter (``diagnose.alpha=abc``). A schema is a callable's dotted path, whose keyword
    arguments the node holds, or a type, that of a single value (``{"seed": int}``).
    """
    for key in required:
        parent_key, _, name = key.rpartition(".")
        parent = OmegaConf.select(cfg, parent_key) if parent_key else cfg
        if isinstance(parent, DictConfig) and OmegaConf.is_missing(parent, name):
            raise ConfigError(f"no value for {key}: add {key}=...")
    for key, schema in schemas.items():
        if not isinstance(schema, str):
            _check_type(cfg, key, schema)
    tree = OmegaConf.to_container(cfg, resolve=False)
    for key, node in _nodes(tree, ""):
        target = node.get("_target_") if isinstance(node, dict) else None
        name = schemas.get(key) or (target if isinstance(target, str) and "${" not in target else None)
        if not isinstance(name, str):
            continue
        hints = _parameters(name)
        if hints is None:  # not importable (instantiate says why) or takes **kwargs
            continue
        for setting in node:
            if setting.startswith("_"):
                continue
            if setting not in hints:
                raise ConfigError(unknown_setting(f"{key}.{setting}", [f"{key}.{p}" for p in hints]))
            _check_type(cfg, f"{key}.{setting}", hints[setting])


def _check_type(cfg: DictConfig, key: str, hint: Any) -> None:
    try:
        value = OmegaConf.select(cfg, key, throw_on_missing=True)
        if isinstance(value, (DictConfig, ListConfig)):
            value = OmegaConf.to_container(value, resolve=True, throw_on_missing=True)
    except Exception:  # noqa: BLE001 -- a missing or unresolvable value: the task's own access says so
        return
    expected = _expected(value, hint)
    if expected is not None:
        raise ConfigError(f"{key} must be {expected}, got {value!r}")


_SEQUENCES = (list, tuple, collections.abc.Sequence)
_NAMES = {int: "an integer", float: "a number", bool: "true or false", str: "a string", type(None): "null",
          dict: "a mapping", list: "a list", tuple: "a list"}
_PLURALS = {int: "integers", float: "numbers", bool: "true/false values", str: "strings"}


def _expected(value: Any, hint: Any) -> str | None:
    """None when ``value`` fits the type ``hint`` (or the hint is not a plain one), else what it must be."""
    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        known = [a for a in args if a in _NAMES or typing.get_origin(a) in (*_SEQUENCES, dict)]
        if not known or any(_expected(value, a) is None for a in known):
            return None
        return " or ".join(_expected(value, a) or "" for a in known)
    if hint is bool:
        return None if isinstance(value, bool) else _NAMES[bool]
    if hint is int:
        return None if isinstance(value, int) and not isinstance(value, bool) else _NAMES[int]
    if hint is float:
        return None if isinstance(value, (int, float)) and not isinstance(value, bool) else _NAMES[float]
    if hint in (str, type(None), dict):
        return None if isinstance(value, hint) else _NAMES[hint]
    if hint in (list, tuple) or origin in _SEQUENCES:
        if not isinstance(value, list):
            return _NAMES[list]
        items = [a for a in args if a is not Ellipsis]
        if len(set(items)) == 1 and items[0] in _PLURALS and any(_expected(v, items[0]) for v in value):
            return f"a list of {_PLURALS[items[0]]}"
        return None
    if origin is dict or hint is collections.abc.Mapping or origin is collections.abc.Mapping:
        return None if isinstance(value, dict) else _NAMES[dict]
    return None


def _nodes(tree: Any, prefix: str) -> Iterator[tuple[str, Any]]:
    if isinstance(tree, dict):
        for key, value in tree.items():
            path = f"{prefix}.{key}" if prefix else str(key)
            yield path, value
            yield from _nodes(value, path)
    elif isinstance(tree, list):
        for i, value in enumerate(tree):
            yield from _nodes(value, f"{prefix}[{i}]")


def _parameters(name: str) -> dict[str, Any] | None:
    """The keyword parameters of the callable at ``name`` and their type hints (Any when unknown)."""
    try:
        target = _locate(name)
        signature = inspect.signature(target)
    except Exception:  # noqa: BLE001 -- the task's own instantiate reports a bad target
        return None
    params = signature.parameters.values()
    if any(p.kind == p.VAR_KEYWORD for p in params):
        return None
    try:
        hints = typing.get_type_hints(target.__init__ if inspect.isclass(target) else target)
    except Exception:  # noqa: BLE001 -- unresolvable annotations: check the names only
        hints = {}
    return {p.name: hints.get(p.name, Any) for p in params if p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)}


def _locate(path: str) -> Any:
    """The object at a dotted path (quietly: hydra.utils.get_object logs its failures)."""
    parts = path.split(".")
    for split in range(len(parts) - 1, 0, -1):
        try:
            found: Any = importlib.import_module(".".join(parts[:split]))
        except ImportError:
            continue
        for part in parts[split:]:
            found = getattr(found, part)
        return found
    raise ImportError(path)


def unknown_setting(key: str, known: list[str]) -> str:
    """``unknown setting data.pth; did you mean data.path?`` (or the known ones when none is close)."""
    if key in known:  # a mapping that exists but takes no new keys by assignment (an empty {} in the yaml)
        return f"{key} takes new entries one at a time: +{key}.<name>=<value>"
    match = difflib.get_close_matches(key, known, n=1, cutoff=0.6)
    if match:
        return f"unknown setting {key}; did you mean {match[0]}?"
    parent = key.rsplit(".", 1)[0] if "." in key else ""
    siblings = sorted({k[len(parent) + 1:].split(".")[0] if parent else k.split(".")[0]
                       for k in known if not parent or k.startswith(parent + ".")})
    where = f"in {parent}" if parent and siblings else "at the top level"
    siblings = siblings or sorted({k.split(".")[0] for k in known})
    return f"unknown setting {key}; the settings {where} are {', '.join(siblings)}"


def _config_keys(cfg: DictConfig, hydra_keys: bool) -> list[str]:
    """Every dotted key of ``cfg`` (the ``hydra.`` ones only if asked), without resolving anything."""
    tree = OmegaConf.to_container(cfg, resolve=False)
    keys = [k for k, _ in _nodes(tree, "") if "[" not in k]
    return [k for k in keys if (k == "hydra" or k.startswith("hydra.")) == hydra_keys]


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
    known = _config_keys(root, key.startswith("hydra.")) if isinstance(root, DictConfig) else []
    return unknown_setting(key, known)
