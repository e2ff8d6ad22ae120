"""Genetic operators for hyperparameter search: pure functions seeded by an explicit ``rng``.

An *individual* is a ``dict`` from parameter name to value; a *search space* is a sequence of
:class:`Param`. Every numeric parameter is handled in a normalised coordinate ``u`` in [0, 1]
(logarithmic for the ``log-*`` kinds), so one mutation scale suits bounds of any size. Fitness
is minimised; NaN and infinite fitness count as the worst possible.

Nothing here knows about Hydra: the sweeper in ``hydra_plugins/gyronet_ga_sweeper`` turns
override strings into :class:`Param` and launches the jobs that compute the fitness.

References
----------
D. E. Goldberg, *Genetic Algorithms in Search, Optimization and Machine Learning*, 1989
(tournament selection, elitism). L. J. Eshelman and J. D. Schaffer, "Real-coded genetic
algorithms and interval-schemata", FOGA 1993 (blend crossover, BLX-alpha).
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any, Callable, Literal, Sequence

import numpy as np

from gyronet.training.ga_space import KINDS, Individual, Kind, Param, random_individual

log = logging.getLogger(__name__)


def sanitize_fitness(fitness: Sequence[float] | np.ndarray) -> np.ndarray:
    """Return fitness as float64 with NaN and +-inf replaced by +inf (the worst, minimising)."""
    f = np.asarray(fitness, dtype=float).copy()
    f[~np.isfinite(f)] = np.inf
    return f


def tournament_select(population: Sequence[Individual], fitness: Sequence[float] | np.ndarray,
                      k: int, rng: np.random.Generator) -> Individual:
    """Pick the fittest of ``k`` individuals drawn without replacement.

    Parameters
    ----------
    population : sequence of dict
        The candidates.
    fitness : array_like, shape (len(population),)
        Their fitness (lower is better; NaN and inf are worst).
    k : int
        Tournament size, clipped to [1, len(population)]. ``k = 1`` is a random pick.
    rng : numpy.random.Generator

    Returns
    -------
    dict
        A copy of the winner.
    """
    f = sanitize_fitness(fitness)
    if len(population) == 0 or len(f) != len(population):
        raise ValueError("tournament_select needs a non-empty population with one fitness each")
    contestants = rng.choice(len(population), size=min(max(k, 1), len(population)), replace=False)
    # argmin keeps the first of equals, and the draw order is random, so ties break at random
    winner = contestants[int(np.argmin(f[contestants]))]
    return dict(population[winner])


def _reflect(u: float) -> float:
    # fold a coordinate back into [0, 1] like a mirror, so the bounds do not collect offspring
    u = abs(u) % 2.0
    return 2.0 - u if u > 1.0 else u


def crossover(a: Individual, b: Individual, space: Sequence[Param], rate: float,
              rng: np.random.Generator, method: Literal["blend", "uniform"] = "blend",
              alpha: float = 0.25) -> tuple[Individual, Individual]:
    """Recombine two parents into two children.

    Parameters
    ----------
    a, b : dict
        The parents.
    space : sequence of Param
    rate : float
        Probability in [0, 1] that the pair is recombined at all; otherwise the children are copies.
    rng : numpy.random.Generator
    method : {"blend", "uniform"}
        ``blend`` (BLX-alpha) draws each numeric gene between and a little beyond the parents'
        values in normalised space; ``uniform`` swaps each gene with probability 1/2. Choice
        genes are always swapped uniformly.
    alpha : float
        How far beyond the parents a blended gene may land, as a fraction of their distance.

    Returns
    -------
    tuple of dict
        Two children inside the bounds of ``space``.
    """
    c1, c2 = dict(a), dict(b)
    if rng.random() >= rate:
        return c1, c2
    for p in space:
        if p.is_numeric and method == "blend":
            ua, ub = p.to_unit(a[p.name]), p.to_unit(b[p.name])
            w = rng.uniform(-alpha, 1.0 + alpha)
            # u1 = (1 - w) ua + w ub,  u2 = w ua + (1 - w) ub
            c1[p.name] = p.from_unit(_reflect((1.0 - w) * ua + w * ub))
            c2[p.name] = p.from_unit(_reflect(w * ua + (1.0 - w) * ub))
        elif rng.random() < 0.5:
            c1[p.name], c2[p.name] = b[p.name], a[p.name]
    return c1, c2


def mutate(ind: Individual, space: Sequence[Param], rate: float, scale: float,
           rng: np.random.Generator) -> Individual:
    """Perturb each gene with probability ``rate``.

    Numeric genes get gaussian noise of standard deviation ``scale`` in normalised space
    (logarithmic for ``log-*`` kinds), then are reflected, rounded and clipped into bounds.
    A choice gene is redrawn among the other choices.

    Returns
    -------
    dict
        The mutated copy of ``ind``.
    """
    out = dict(ind)
    for p in space:
        if rng.random() >= rate:
            continue
        if p.is_numeric:
            # u' = u + N(0, scale^2)
            out[p.name] = p.from_unit(_reflect(p.to_unit(ind[p.name]) + rng.normal(0.0, scale)))
        elif len(p.choices) > 1:
            others = [c for c in p.choices if not (c == ind[p.name] and type(c) is type(ind[p.name]))]
            out[p.name] = others[int(rng.integers(len(others)))]
    return out


def elite_indices(fitness: Sequence[float] | np.ndarray, n: int) -> list[int]:
    """Indices of the ``n`` fittest, best first (a stable sort, so earlier wins ties)."""
    f = sanitize_fitness(fitness)
    return [int(i) for i in np.argsort(f, kind="stable")[: max(n, 0)]]


def next_generation(population: Sequence[Individual], fitness: Sequence[float] | np.ndarray,
                    space: Sequence[Param], rng: np.random.Generator, *, elitism: int = 1,
                    tournament_size: int = 3, crossover_rate: float = 0.9,
                    mutation_rate: float = 0.2, mutation_scale: float = 0.1,
                    size: int | None = None,
                    method: Literal["blend", "uniform"] = "blend") -> list[Individual]:
    """Breed the next population: elites first, then tournament, crossover and mutation.

    Parameters
    ----------
    population : sequence of dict
        The evaluated population.
    fitness : array_like, shape (len(population),)
        Its fitness, lower is better.
    space : sequence of Param
    rng : numpy.random.Generator
    elitism : int
        How many of the best are copied unchanged (at most ``size``).
    tournament_size, crossover_rate, mutation_rate, mutation_scale
        See :func:`tournament_select`, :func:`crossover` and :func:`mutate`.
    size : int, optional
        Size of the new population; default ``len(population)``.
    method : {"blend", "uniform"}
        Crossover of numeric genes.

    Returns
    -------
    list of dict
        ``size`` individuals, the elites first in order of fitness.
    """
    size = len(population) if size is None else size
    children = [dict(population[i]) for i in elite_indices(fitness, min(elitism, size))]
    while len(children) < size:
        a = tournament_select(population, fitness, tournament_size, rng)
        b = tournament_select(population, fitness, tournament_size, rng)
        for child in crossover(a, b, space, crossover_rate, rng, method=method):
            if len(children) < size:
                children.append(mutate(child, space, mutation_rate, mutation_scale, rng))
    return children


@dataclass
class GAResult:
    """What :func:`minimise` found: the best individual, its fitness and every generation."""

    best: Individual
    best_fitness: float
    history: list[tuple[list[Individual], np.ndarray]]


def minimise(f: Callable[[Individual], float], space: Sequence[Param], population_size: int,
             generations: int, rng: np.random.Generator, **kwargs: Any) -> GAResult:
    """Minimise ``f`` over ``space`` in-process (for tests and notebooks).

    Parameters
    ----------
    f : callable
        Maps an individual to a fitness; NaN, inf and exceptions score inf.
    space : sequence of Param
    population_size, generations : int
        The budget is ``population_size * generations`` calls to ``f``.
    rng : numpy.random.Generator
    **kwargs
        Passed to :func:`next_generation` (``elitism``, ``mutation_scale``, ...).

    Returns
    -------
    GAResult
    """
    population = [random_individual(space, rng) for _ in range(population_size)]
    history: list[tuple[list[Individual], np.ndarray]] = []
    for generation in range(generations):
        fitness = sanitize_fitness([_safe_call(f, ind) for ind in population])
        history.append((population, fitness))
        log.debug("generation %d: best %.6g", generation, float(fitness.min()))
        if generation + 1 < generations:
            population = next_generation(population, fitness, space, rng, **kwargs)
    fits = np.concatenate([h[1] for h in history])
    inds = [ind for h in history for ind in h[0]]
    best = int(np.argmin(fits))
    return GAResult(best=dict(inds[best]), best_fitness=float(fits[best]), history=history)


def _safe_call(f: Callable[[Individual], float], ind: Individual) -> float:
    try:
        return float(f(ind))
    except Exception as err:  # a failed evaluation is the worst, not the end of the search
        log.debug("evaluation failed for %s: %s", ind, err)
        return math.inf


__all__ = ["GAResult", "Individual", "KINDS", "Kind", "Param", "crossover", "elite_indices", "minimise", "mutate",
           "next_generation", "random_individual", "sanitize_fitness", "tournament_select"]
