"""From the candidates that passed the screen to the effects worth a retraining, best first.

The screen tests a grid (time constants a factor of about 2 apart, widths a factor of 2). For
each family that passed (a kind and a source: ``lag`` of ``temp_c``, ``column`` of ``vdd_v``,
warm-up, ...) the best grid point's parameter is refined on a finer log grid (factors 2, sqrt 2,
... 2^(1/16)) by the same held-out score, without a new test: the family already passed, and
the refinement only places the effect better within it.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import numpy as np

from gyronet.diagnose.candidates import family, refinements
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


def ranked(result: ScreenResult, passing: np.ndarray, rows: ScreenRows, basis: tuple, top: int,
           longest_s: float) -> list[Choice]:
    """The best passing grid point of each of the ``top`` best families, refined, best score first."""
    best_of_family: dict[tuple, int] = {}
    for i in passing:
        best_of_family.setdefault(family(result.specs[i]), int(i))
    choices = [refine(result.specs[i], rows, basis, result.ridge, longest_s, i)
               for i in list(best_of_family.values())[:max(1, top)]]
    return sorted(choices, key=lambda c: -c.score)
