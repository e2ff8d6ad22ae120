"""From the candidates that passed the screen to the effects worth a retraining, simplest first.

The screen tests a grid (time constants a factor of about 2 apart, widths a factor of 2). Families
(a kind and a source: ``lag`` of ``temp_c``, ``column`` of ``vdd_v``, warm-up, ...) are compared
at their best grid point, at equal freedom: a parameter refined on the data would give its family
an advantage that the refinement itself produced, so refinement comes only after the choice.

**Equivalent explanations.** Families whose best score is within the screen's own noise of the
best family's (``tie_z`` standard errors of the paired per-fold difference,
``ScreenResult.tie_noise``, or less than 1 % of the best score) explain the held-out residual
equally well. Of such a group the
simplest is tried first (``complexity``: fewer free parameters, a measured column before a
derived one, no lag before a lag) and the others are its ``alternatives``. Only then is the chosen
parameter refined on a finer log grid (factors 2, sqrt 2, ... 2^(1/16)) by the same held-out
score, without a new test: the family already passed, and the refinement only places the effect
better within it.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import numpy as np

from gyronet.diagnose.candidates import effect_kind, effect_params, effect_source, family, refinements
from gyronet.diagnose.rows import ScreenRows
from gyronet.diagnose.screen import ScreenResult, choose_ridge, score_only

log = logging.getLogger(__name__)


@dataclass
class Choice:
    """A candidate effect to try: its spec, the grid point (screen row) it came from, its held-out
    gain per axis, score and RMS after (60 s, deg/s) against the round's basis."""

    spec: dict
    index: int
    gain: np.ndarray
    score: float
    rmse_after: np.ndarray
    alternatives: list = field(default_factory=list)  # [{kind, source, params, score}]


def score_specs(rows: ScreenRows, basis: tuple, specs: Sequence[Mapping[str, Any]], ridge: float | None) -> tuple:
    """Held-out gains, scores and RMS after of ``specs`` against ``basis = (values, free)``."""
    values, free = basis
    return score_only(values, rows.target, rows.features(specs), rows.fold, ridge, free)


def refine(spec: Mapping[str, Any], rows: ScreenRows, basis: tuple, ridge: float | None = None,
           longest_s: float = np.inf, index: int = -1) -> Choice:
    """The spec with its time constant or width moved to the best held-out score nearby.

    Parameters
    ----------
    spec
        A candidate spec (those without a continuous parameter come back as they are).
    rows, basis
        The screen's rows and ``(values, free)`` regressors of the model to score against.
    ridge
        The screen's penalty; None chooses it for this basis.
    longest_s
        No time constant beyond this.
    index
        The screen row the spec came from, kept in the result.
    """
    ridge = choose_ridge(basis[0], rows.target, rows.fold, basis[1]) if ridge is None else ridge
    gain, score, rmse_after = score_specs(rows, basis, [spec], ridge)
    best = Choice(dict(spec), index, gain[0], float(score[0]), rmse_after[0])
    for step in (1.0, 0.5, 0.25, 0.125, 0.0625):
        trial = refinements(best.spec, (-step, step), longest_s)
        if not trial:
            break
        gain, score, rmse_after = score_specs(rows, basis, trial, ridge)
        k = int(np.argmax(score))
        if score[k] > best.score:
            best = Choice(trial[k], index, gain[k], float(score[k]), rmse_after[k])
    return best


def complexity(spec: Mapping[str, Any]) -> tuple[int, int, int, int]:
    """Sort key, simplest first: (free parameters, derived, lagged, not a run offset).

    A column as it is has no free parameter and is measured; ageing (hours) has none but is derived
    from the clock; a time constant, a width or an exponent is one free parameter; a lag filter
    comes after an instantaneous shape. A per-run offset (its constants are one more than a
    coefficient only beyond two runs) comes first of equals: every power-up has one.
    """
    kind = spec["kind"]
    if kind == "run_offset":
        return int(spec.get("n_free", 0)), 0, 0, 0
    n_free = int(bool(spec.get("tau_s")) or "width" in spec or kind == "power")
    measured = kind == "column" and not spec.get("tau_s")
    lagged = kind == "lag" or (kind == "column" and bool(spec.get("tau_s")))
    return n_free, int(not measured), int(lagged), 1


def alternative(spec: Mapping[str, Any], score: float) -> dict[str, Any]:
    """One entry of an effect's ``alternatives`` (CONTRACT.md section 4)."""
    return {"kind": effect_kind(spec), "source": effect_source(spec), "params": effect_params(spec),
            "score": float(score)}


def tie_groups(result: ScreenResult, passing: np.ndarray, tie_z: float = 1.0, rel_tol: float = 0.01) -> list[list[int]]:
    """The passing families' best grid points, grouped by equivalence, best group first; each
    group sorted simplest first.

    A group holds the families whose score is below its best's by no more than the screen's noise,
    ``tie_z`` standard errors of the paired per-fold difference, or by less than ``rel_tol`` of the
    best score: two near-copies of one signal differ consistently by a hair, which the paired error
    alone would call apart. (The median best score under the circular shifts, what chance alone
    gives, was tried as the floor instead: on slow residuals it reached 10 % of the best and made
    hours-since-start the equal of a 5000 s warm-up that it is not on another history.)
    """
    best_of_family: dict[tuple, int] = {}
    for i in passing:  # best score first
        best_of_family.setdefault(family(result.specs[i]), int(i))
    left = list(best_of_family.values())
    groups = []
    while left:
        head, rest = left[0], np.array(left[1:], dtype=int)
        noise = result.tie_noise(head, rest) if len(rest) else np.zeros(0)
        within = np.maximum(tie_z * noise, rel_tol * result.score[head])
        tied = [int(j) for j, w in zip(rest, within) if result.score[head] - result.score[j] <= w]
        group = sorted([head, *tied], key=lambda j: (complexity(result.specs[j]), -result.score[j]))
        groups.append(group)
        left = [j for j in left if j not in group]
    return groups


def ranked(result: ScreenResult, passing: np.ndarray, rows: ScreenRows, basis: tuple, top: int,
           longest_s: float, tie_z: float = 1.0) -> list[Choice]:
    """Up to ``top`` candidates to try, simplest of the best group first, each refined only once
    chosen and carrying the other members of its group as ``alternatives``."""
    order = []
    for group in tie_groups(result, passing, tie_z):
        order += [(i, [j for j in group if j != i]) for i in group]
    choices = []
    for i, others in order[:max(1, top)]:
        choice = refine(result.specs[i], rows, basis, result.ridge, longest_s, i)
        choice.alternatives = [alternative(result.specs[j], result.score[j]) for j in others]
        choices.append(choice)
    return choices
