"""Settings the code cannot take, refused before any work: a missing value, an unknown key, a wrong type.

``check_settings`` reads a script's config against the callables its nodes are built from; ``unknown_setting``
names the closest known key. Used by ``_cli.command`` for every script.
"""
from __future__ import annotations

import collections.abc
import difflib
import importlib
import inspect
import types
import typing
from typing import Any, Iterator, Mapping, Sequence

from omegaconf import DictConfig, ListConfig, OmegaConf

from gyronet.errors import ConfigError


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
        # one value where a list belongs: the shell's quoting of a Hydra list is the usual stumble
        quoted = f" (a list on the command line: '{key}=[{value}]')" if expected.startswith("a list") and \
            not isinstance(value, (list, dict)) else ""
        raise ConfigError(f"{key} must be {expected}, got {value!r}{quoted}")


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
        return (f"{key} takes new entries with a +: '+{key}={{<name>: <value>, ...}}' or one at a time, "
                f"+{key}.<name>=<value>")
    match = difflib.get_close_matches(key, known, n=1, cutoff=0.6)
    if match:
        return f"unknown setting {key}; did you mean {match[0]}?"
    parent = key.rsplit(".", 1)[0] if "." in key else ""
    siblings = sorted({k[len(parent) + 1:].split(".")[0] if parent else k.split(".")[0]
                       for k in known if not parent or k.startswith(parent + ".")})
    where = f"in {parent}" if parent and siblings else "at the top level"
    siblings = siblings or sorted({k.split(".")[0] for k in known})
    return f"unknown setting {key}; the settings {where} are {', '.join(siblings)}"


def config_keys(cfg: DictConfig, hydra_keys: bool) -> list[str]:
    """Every dotted key of ``cfg`` (the ``hydra.`` ones only if asked), without resolving anything."""
    tree = OmegaConf.to_container(cfg, resolve=False)
    keys = [k for k, _ in _nodes(tree, "") if "[" not in k]
    return [k for k in keys if (k == "hydra" or k.startswith("hydra.")) == hydra_keys]
