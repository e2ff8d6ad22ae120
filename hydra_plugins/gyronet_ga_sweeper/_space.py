"""The search space in Hydra's override grammar, and individuals written back as overrides."""
from __future__ import annotations

from typing import Any, Dict, List, Optional, Sequence, Tuple

from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.core.override_parser.types import Override, Transformer

from gyronet.training.ga import Individual, Param

SIGNIFICANT_DIGITS = 6


def param_from_override(override: Override) -> Optional[Param]:
    """Turn a sweep override into a :class:`Param`; None for a plain (fixed) override.

    ``interval`` is a float (``int(interval(...))`` an int), ``tag(log, ...)`` makes it
    logarithmic; ``choice``, ``a,b,c`` and ``range`` become a categorical choice.
    """
    if not override.is_sweep_override():
        return None
    name, value = override.get_key_element(), override.value()
    if override.is_interval_sweep():
        is_int = isinstance(value.start, int) and isinstance(value.end, int)
        kind = ("log-" if "log" in value.tags else "") + ("int" if is_int else "float")
        return Param(name, kind, value.start, value.end)  # type: ignore[arg-type]
    choices = tuple(override.sweep_iterator(transformer=Transformer.encode))
    return Param(name, "choice", choices=choices)


def parse_search_space(lines: Sequence[str], parser: OverridesParser
                       ) -> Tuple[List[Param], List[str]]:
    """Split overrides into the search space and the fixed overrides passed to every job.

    A later line for the same key replaces an earlier one, so command-line arguments win over
    ``hydra.sweeper.params``.
    """
    by_key: Dict[str, Override] = {}
    for override in parser.parse_overrides(list(lines)):
        by_key.pop(override.get_key_element(), None)
        by_key[override.get_key_element()] = override
    space, fixed = [], []
    for override in by_key.values():
        param = param_from_override(override)
        if param is None:
            assert override.input_line is not None
            fixed.append(override.input_line)
        else:
            space.append(param)
    return space, fixed


def tidy(individual: Individual, space: Sequence[Param]) -> Individual:
    """Round floats to a few significant digits, so overrides and dir names stay readable."""
    out = dict(individual)
    for p in space:
        if p.kind in ("float", "log-float"):
            assert p.low is not None and p.high is not None
            value = float(f"{out[p.name]:.{SIGNIFICANT_DIGITS}g}")
            out[p.name] = min(max(value, float(p.low)), float(p.high))
    return out


def format_value(value: Any) -> str:
    """Write a parameter value in Hydra's override grammar."""
    if isinstance(value, bool):
        return "true" if value else "false"
    return repr(value) if isinstance(value, float) else str(value)


def to_overrides(individual: Individual) -> List[str]:
    """``key=value`` overrides for one individual."""
    return [f"{k}={format_value(v)}" for k, v in individual.items()]


def describe(p: Param) -> str:
    """``name in [a, b]`` or ``name float [low, high]``, for the log."""
    if p.kind == "choice":
        return f"{p.name} in {list(p.choices)}"
    return f"{p.name} {p.kind} [{p.low}, {p.high}]"
