"""The GA's search space (``Param``, an individual), apart from the operators so that ``ga.py`` stays short."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Literal, Mapping, Sequence

import numpy as np

Kind = Literal["int", "float", "log-int", "log-float", "choice"]
KINDS: tuple[str, ...] = ("int", "float", "log-int", "log-float", "choice")
Individual = dict[str, Any]


@dataclass(frozen=True)
class Param:
    """One dimension of a search space.

    Parameters
    ----------
    name : str
        The key, e.g. ``"model.n_centers"``.
    kind : {"int", "float", "log-int", "log-float", "choice"}
        ``log-*`` kinds are searched uniformly in log space and need ``low > 0``.
    low, high : float, optional
        Inclusive bounds of a numeric kind (integers for the int kinds).
    choices : tuple, optional
        The values of a ``choice`` kind.
    """

    name: str
    kind: Kind
    low: float | None = None
    high: float | None = None
    choices: tuple[Any, ...] = field(default=())

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"{self.name}: kind {self.kind!r} is not one of {KINDS}")
        if self.kind == "choice":
            if len(self.choices) == 0:
                raise ValueError(f"{self.name}: a choice needs at least one value")
            return
        if self.low is None or self.high is None or not self.low <= self.high:
            raise ValueError(f"{self.name}: needs bounds low <= high, got {self.low}, {self.high}")
        if self.is_log and self.low <= 0:
            raise ValueError(f"{self.name}: a log scale needs low > 0, got {self.low}")
        if self.is_int and (self.low != int(self.low) or self.high != int(self.high)):
            raise ValueError(f"{self.name}: integer bounds expected, got {self.low}, {self.high}")

    @property
    def is_numeric(self) -> bool:
        """Whether the parameter has bounds (every kind but ``choice``)."""
        return self.kind != "choice"

    @property
    def is_int(self) -> bool:
        """Whether values are rounded to integers."""
        return self.kind in ("int", "log-int")

    @property
    def is_log(self) -> bool:
        """Whether the normalised coordinate is logarithmic."""
        return self.kind in ("log-int", "log-float")

    def _edges(self) -> tuple[float, float]:
        # an integer owns [k - 0.5, k + 0.5), so the end values are as likely as the others
        assert self.low is not None and self.high is not None
        pad = 0.5 if self.is_int else 0.0
        low, high = float(self.low) - pad, float(self.high) + pad
        return (math.log(low), math.log(high)) if self.is_log else (low, high)

    def to_unit(self, value: float) -> float:
        """Map a value to the normalised coordinate ``u`` in [0, 1]."""
        lo, hi = self._edges()
        x = math.log(value) if self.is_log else float(value)
        return 0.0 if hi == lo else min(max((x - lo) / (hi - lo), 0.0), 1.0)

    def from_unit(self, u: float) -> int | float:
        """Map ``u`` (clipped to [0, 1]) back to a value inside the bounds."""
        assert self.low is not None and self.high is not None
        lo, hi = self._edges()
        x = lo + min(max(float(u), 0.0), 1.0) * (hi - lo)
        value = math.exp(x) if self.is_log else x
        if self.is_int:
            return int(min(max(round(value), int(self.low)), int(self.high)))
        return float(min(max(value, float(self.low)), float(self.high)))

    def sample(self, rng: np.random.Generator) -> Any:
        """Draw a value uniformly (in log space for ``log-*`` kinds)."""
        if self.kind == "choice":
            return self.choices[int(rng.integers(len(self.choices)))]
        return self.from_unit(float(rng.random()))

    def contains(self, value: Any) -> bool:
        """Whether ``value`` is a legal value of this parameter."""
        if self.kind == "choice":
            return any(value == c and type(value) is type(c) for c in self.choices)
        if self.is_int and not isinstance(value, int):
            return False
        assert self.low is not None and self.high is not None
        return self.low <= value <= self.high

    def to_dict(self) -> dict[str, Any]:
        """A JSON-friendly description (the inverse of :meth:`from_dict`)."""
        if self.kind == "choice":
            return {"name": self.name, "kind": self.kind, "choices": list(self.choices)}
        return {"name": self.name, "kind": self.kind, "low": self.low, "high": self.high}

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "Param":
        """Rebuild a :class:`Param` from :meth:`to_dict` output."""
        return cls(name=d["name"], kind=d["kind"], low=d.get("low"), high=d.get("high"),
                   choices=tuple(d.get("choices", ())))


def random_individual(space: Sequence[Param], rng: np.random.Generator) -> Individual:
    """Draw one individual uniformly from ``space``."""
    return {p.name: p.sample(rng) for p in space}
