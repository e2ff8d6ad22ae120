"""From the candidates that passed the screen to the effects worth a retraining, measured and simplest first.

The screen tests a grid (time constants a factor of about 2 apart, widths a factor of 2).
Families (a kind and a source: ``lag`` of ``temp_c``, ``column`` of ``vdd_v`` as it is, the same
through a lag, warm-up, ...) are compared at their best, each refined alike: every passing
family's best grid point is moved on a finer log grid (factors 2, sqrt 2, ... 2^(1/16)) by the
same held-out score, without a new test (the family already passed). Comparing grid points
instead would decide between two near-copies by where each family's grid happens to fall: the
columns' lags (60, 300, 1200, 3600 s) are a coarser grid than the temperature's.

**Equivalent explanations.** Families whose refined score is within the screen's own noise of
the best family's (``tie_z`` standard errors of their paired difference on the same held-out
blocks, clustered by span, :mod:`.ties`; or less than 1 % of the best score), and short of it
by no more than a fifth, explain the held-out residual equally well. Of such a group the
simplest is tried first, and of equal freedom a measured one (``complexity``: a recording
column as it is, ageing or a warm-up; then a recording column through a lag; then what is
derived from the temperature, a lag of ``temp_c`` last) and the others are its ``alternatives``.

**What a derived effect approximates.** When the effect kept is derived (a lag of ``temp_c``, a
warm-up, ...) and a measured column scored nearly as well (within ``near`` of its score) and
follows nearly the same course once the model's own regressors are removed (correlation of at
least ``min_corr``), the evidence names that column: a person acts on the name, and would look
for a lag inside the package rather than at the board sensor that explains it.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import numpy as np

from gyronet.analysis.diagnose.candidates import effect_kind, effect_params, effect_source, family, refinements
from gyronet.analysis.diagnose.rows import ScreenRows
from gyronet.analysis.diagnose.screen import ScreenResult, choose_ridge, score_only
from gyronet.model.features import feature_name

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


def complexity(spec: Mapping[str, Any]) -> tuple[int, ...]:
    """Sort key, simplest and measured first: (free parameters, tier, not measured, lagged, not a run offset).

    A recording column (other than ``temp_c``) is measured; as it is, it has no free parameter,
    like ageing (hours, from the clock). A time constant, a width or an exponent is one. Of
    equal freedom, the tiers: a column as it is and the clock's own shapes (ageing, a warm-up);
    then a recording column through a lag or squared; then what is derived from the temperature
    (hysteresis, powers, then a lag of ``temp_c``). A warm-up comes before a lagged column because
    a lag filter's start mimics one (``candidates.filter_tau``): a static accelerometer through a
    2141 s lag took the simulator's warm-up's place when it came first. A lag filter comes after
    an instantaneous shape. A per-run offset (its constants are one more than a coefficient only
    beyond two runs) comes first of equals: every power-up has one.
    """
    kind = spec["kind"]
    if kind == "run_offset":
        return int(spec.get("n_free", 0)), 0, 0, 0, 0
    n_free = int(bool(spec.get("tau_s")) or "width" in spec or kind == "power")
    measured = effect_kind(spec) == "column"
    tier = 0 if kind == "time" or (measured and not n_free) else 1 if measured else 2
    lagged = kind == "lag" or (kind == "column" and bool(spec.get("tau_s")))
    return n_free, tier, int(not measured), int(lagged), 1


def alternative(spec: Mapping[str, Any], score: float) -> dict[str, Any]:
    """One entry of an effect's ``alternatives`` (CONTRACT.md section 4)."""
    return {"kind": effect_kind(spec), "source": effect_source(spec), "params": effect_params(spec),
            "score": float(score)}


def tie_groups(result: ScreenResult, passing: np.ndarray, tie_z: float = 2.0, rel_tol: float = 0.01,
               max_shortfall: float = 0.2) -> list[list[int]]:
    """The passing families' best rows, grouped by equivalence, best group first; each group sorted
    measured and simplest first (``complexity``).

    A group holds the families whose score is below its best's by no more than the screen's noise,
    ``tie_z`` standard errors of their paired difference on the same held-out blocks
    (``ScreenResult.tie_noise``), or by less than ``rel_tol`` of the best score: two near-copies of
    one signal differ consistently by a hair, which the paired error alone would call apart. (The
    median best score under the circular shifts, what chance alone gives, was tried as the floor
    instead: on slow residuals it reached 10 % of the best and made hours-since-start the equal
    of a 5000 s warm-up that it is not on another history.) Nor is a family that falls short of
    the best by more than ``max_shortfall`` of its score an equal, whatever the noise: a
    difference that lives in a few spans (a warm-up's first half hour) has a standard error as
    large as itself, and a 2050 s lag of ``acc_z_g`` scoring 0.39 was listed as the equal of a
    warm-up scoring 0.76 (near-copies come within 3 %).
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
        tied = [int(j) for j, w in zip(rest, within) if result.score[head] - result.score[j] <= w
                and result.score[j] >= (1.0 - max_shortfall) * result.score[head]]
        group = sorted([head, *tied], key=lambda j: (complexity(result.specs[j]), -result.score[j]))
        groups.append(group)
        left = [j for j in left if j not in group]
    return groups


def refined_result(result: ScreenResult, passing: np.ndarray, rows: ScreenRows, basis: tuple,
                   longest_s: float = np.inf) -> tuple[ScreenResult, list[Choice]]:
    """Every passing family's best grid point refined (``refine``), scored again on the same
    held-out blocks: a ``ScreenResult`` of one row per family, best first (its p-values those of
    the grid points), and the refined ``Choice`` of each row."""
    heads: dict[tuple, int] = {}
    for i in passing:  # best score first
        heads.setdefault(family(result.specs[i]), int(i))
    choices = [refine(result.specs[i], rows, basis, result.ridge, longest_s, i) for i in heads.values()]
    order = sorted(range(len(choices)), key=lambda k: -choices[k].score)
    choices = [choices[k] for k in order]
    specs = [c.spec for c in choices]
    gain, score, rmse_after, row_sse = score_only(basis[0], rows.target, rows.features(specs), rows.fold,
                                                  result.ridge, basis[1], by_row=True)
    grid = np.array([c.index for c in choices], dtype=int)
    refined = ScreenResult([feature_name(x) for x in specs], specs, gain, score, result.p_value[grid],
                           result.axis_p_value[grid], result.null_max, result.rmse_before, rmse_after,
                           result.n_rows, result.n_folds, result.ridge, None, row_sse, result.span)
    for k, choice in enumerate(choices):
        choice.gain, choice.score, choice.rmse_after = gain[k], float(score[k]), rmse_after[k]
    return refined, choices


def ranked(result: ScreenResult, passing: np.ndarray, rows: ScreenRows, basis: tuple, top: int,
           longest_s: float, tie_z: float = 2.0) -> list[Choice]:
    """Up to ``top`` candidates to try, measured and simplest of the best group first, each refined
    and carrying the other members of its group as ``alternatives``."""
    refined, choices = refined_result(result, passing, rows, basis, longest_s)
    order = []
    for group in tie_groups(refined, np.arange(len(choices)), tie_z):
        order += [(i, [j for j in group if j != i]) for i in group]
    out = []
    for i, others in order[:max(1, top)]:
        choice = choices[i]
        choice.alternatives = [alternative(refined.specs[j], refined.score[j]) for j in others]
        out.append(choice)
    return out


def approximations(choice: Choice, result: ScreenResult, passing: np.ndarray, rows: ScreenRows, basis: tuple,
                   near: float = 0.1, min_corr: float = 0.9) -> list[dict[str, Any]]:
    """The measured columns a derived effect approximates (module docstring), best first, one per
    column: ``{"spec", "name", "score", "corr"}``; empty when the effect is itself measured.

    ``corr`` is the correlation of the two features' 60 s means once the basis (the model's own
    regressors and a constant) is removed by least squares: what each adds to the model.
    """
    if effect_kind(choice.spec) in ("column", "run_offset"):
        return []
    floor = (1 - near) * choice.score
    best: dict[str, int] = {}
    for i in passing:  # best first
        spec = result.specs[i]
        if effect_kind(spec) == "column" and result.score[i] >= floor:
            best.setdefault(effect_source(spec), int(i))
    if not best:
        return []
    design = np.column_stack([np.ones(len(rows)), basis[0]])
    features = rows.features([choice.spec, *(result.specs[i] for i in best.values())])
    residual = features - design @ np.linalg.lstsq(design, features, rcond=None)[0]
    unit = residual / np.maximum(np.linalg.norm(residual, axis=0), 1e-300)
    corr = unit[:, 1:].T @ unit[:, 0]
    out = [{"spec": result.specs[i], "name": result.names[i], "score": float(result.score[i]), "corr": float(c)}
           for i, c in zip(best.values(), corr) if abs(c) >= min_corr]
    log.info("%s approximates %s", feature_name(choice.spec), ", ".join(a["name"] for a in out) or "no measured column")
    return out
