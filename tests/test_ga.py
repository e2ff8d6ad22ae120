"""gyronet.training.ga: pure genetic operators, checked on known problems with a seeded rng."""
from __future__ import annotations

import math

import numpy as np
import pytest

from gyronet.training.ga import (
    Param,
    crossover,
    elite_indices,
    minimise,
    mutate,
    next_generation,
    random_individual,
    sanitize_fitness,
    tournament_select,
)

MIXED = [
    Param("n", "int", 8, 64),
    Param("w", "float", 0.3, 3.0),
    Param("lr", "log-float", 1e-4, 1e-1),
    Param("k", "log-int", 1, 1024),
    Param("act", "choice", choices=("relu", "tanh", 3)),
]


def _in_space(ind: dict, space: list[Param]) -> bool:
    return set(ind) == {p.name for p in space} and all(p.contains(ind[p.name]) for p in space)


def test_sphere_minimum_found_within_small_budget() -> None:
    space = [Param(f"x{i}", "float", -5.0, 5.0) for i in range(3)]
    result = minimise(lambda ind: sum(v**2 for v in ind.values()), space, population_size=20,
                      generations=30, rng=np.random.default_rng(0))
    assert result.best_fitness < 1e-2
    assert max(abs(v) for v in result.best.values()) < 0.1
    # the search improved on its first, random generation
    assert result.best_fitness < 0.01 * float(result.history[0][1].min())


def test_integer_and_log_minimum_found() -> None:
    # minimum at n = 23, lr = 1e-3: an int and a log-float dimension together
    space = [Param("n", "int", 8, 64), Param("lr", "log-float", 1e-5, 1e-1)]
    def f(ind: dict) -> float:
        return (ind["n"] - 23) ** 2 + math.log10(ind["lr"] / 1e-3) ** 2
    result = minimise(f, space, population_size=16, generations=25, rng=np.random.default_rng(1))
    assert result.best["n"] == 23
    assert abs(math.log10(result.best["lr"] / 1e-3)) < 0.1


def test_same_seed_same_search() -> None:
    def run(seed: int) -> dict:
        return minimise(lambda ind: (ind["n"] - 30) ** 2 + ind["w"], MIXED, 8, 4,
                        np.random.default_rng(seed)).best
    assert run(5) == run(5)
    assert run(5) != run(6)


def test_offspring_stay_in_bounds() -> None:
    rng = np.random.default_rng(2)
    population = [random_individual(MIXED, rng) for _ in range(12)]
    fitness = rng.normal(size=12)
    for _ in range(30):
        # a huge mutation scale and wide blends push hard against every bound
        population = next_generation(population, fitness, MIXED, rng, mutation_rate=1.0,
                                     mutation_scale=5.0, crossover_rate=1.0)
        fitness = rng.normal(size=12)
        assert all(_in_space(ind, MIXED) for ind in population)
    assert all(isinstance(ind["n"], int) and isinstance(ind["k"], int) for ind in population)
    assert all(isinstance(ind["w"], float) for ind in population)


def test_random_individuals_cover_the_space() -> None:
    rng = np.random.default_rng(3)
    draws = [random_individual(MIXED, rng) for _ in range(2000)]
    n = np.array([d["n"] for d in draws])
    assert n.min() == 8 and n.max() == 64
    # log-uniform: about as many draws in each decade of [1e-4, 1e-1]
    decades = np.floor(np.log10([d["lr"] for d in draws]))
    counts = np.array([np.sum(decades == e) for e in (-4, -3, -2)])
    assert counts.min() > 0.8 * counts.max()
    assert {d["act"] for d in draws} == {"relu", "tanh", 3}


def test_mutation_in_log_space_is_relative() -> None:
    param = Param("lr", "log-float", 1e-6, 1.0)
    rng = np.random.default_rng(4)
    out = [mutate({"lr": 1e-3}, [param], rate=1.0, scale=0.05, rng=rng)["lr"] for _ in range(500)]
    ratios = np.log10(np.array(out) / 1e-3)
    # scale 0.05 of six decades: a spread of 0.3 decade, centred on the parent
    assert abs(ratios.mean()) < 0.05
    assert 0.2 < ratios.std() < 0.4


def test_choice_mutation_changes_the_value() -> None:
    param = Param("act", "choice", choices=("relu", "tanh"))
    rng = np.random.default_rng(5)
    assert all(mutate({"act": "relu"}, [param], 1.0, 0.1, rng)["act"] == "tanh" for _ in range(20))
    single = Param("only", "choice", choices=("a",))
    assert mutate({"only": "a"}, [single], 1.0, 0.1, rng) == {"only": "a"}


def test_mutation_rate_zero_and_crossover_rate_zero_copy() -> None:
    rng = np.random.default_rng(6)
    a, b = random_individual(MIXED, rng), random_individual(MIXED, rng)
    assert mutate(a, MIXED, 0.0, 1.0, rng) == a
    assert crossover(a, b, MIXED, 0.0, rng) == (a, b)


@pytest.mark.parametrize("method", ["blend", "uniform"])
def test_crossover_mixes_parents(method: str) -> None:
    space = [Param(f"x{i}", "float", 0.0, 1.0) for i in range(8)] + [MIXED[-1]]
    rng = np.random.default_rng(7)
    a = {**{f"x{i}": 0.0 for i in range(8)}, "act": "relu"}
    b = {**{f"x{i}": 1.0 for i in range(8)}, "act": "tanh"}
    c1, c2 = crossover(a, b, space, 1.0, rng, method=method)
    assert c1 != a and c2 != b
    assert all(0.0 <= c1[k] <= 1.0 and 0.0 <= c2[k] <= 1.0 for k in a if k != "act")
    assert {c1["act"], c2["act"]} == {"relu", "tanh"}


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_nonfinite_fitness_is_worst(bad: float) -> None:
    assert np.array_equal(sanitize_fitness([1.0, bad]), [1.0, math.inf])
    population = [{"x": 0}, {"x": 1}, {"x": 2}]
    fitness = [bad, 5.0, bad]
    rng = np.random.default_rng(8)
    # a full tournament always picks the one finite individual
    assert all(tournament_select(population, fitness, 3, rng) == {"x": 1} for _ in range(10))
    assert elite_indices(fitness, 1) == [1]
    space = [Param("x", "int", 0, 2)]
    assert next_generation(population, fitness, space, rng, elitism=1)[0] == {"x": 1}


def test_tournament_prefers_the_fit() -> None:
    population = [{"x": i} for i in range(10)]
    fitness = np.arange(10.0)
    rng = np.random.default_rng(9)
    picks = [tournament_select(population, fitness, 3, rng)["x"] for _ in range(2000)]
    # P(winner = 0) = P(0 among 3 of 10) = 0.3; the worst can never win a 3-tournament
    assert abs(np.mean(np.array(picks) == 0) - 0.3) < 0.04
    assert max(picks) <= 7


def test_elites_survive_unchanged() -> None:
    rng = np.random.default_rng(10)
    population = [random_individual(MIXED, rng) for _ in range(6)]
    fitness = [3.0, 1.0, 2.0, 0.5, 9.0, 4.0]
    nxt = next_generation(population, fitness, MIXED, rng, elitism=2, size=9)
    assert len(nxt) == 9
    assert nxt[:2] == [population[3], population[1]]


def test_failing_objective_scores_inf() -> None:
    def f(ind: dict) -> float:
        if ind["x"] > 0.5:
            raise RuntimeError("diverged")
        return ind["x"]
    result = minimise(f, [Param("x", "float", 0.0, 1.0)], 6, 3, np.random.default_rng(11))
    assert np.isinf(np.concatenate([h[1] for h in result.history])).any()
    assert result.best["x"] <= 0.5


@pytest.mark.parametrize("kwargs", [
    dict(name="a", kind="float", low=1.0, high=0.0),
    dict(name="a", kind="log-float", low=0.0, high=1.0),
    dict(name="a", kind="int", low=0.5, high=3),
    dict(name="a", kind="choice"),
    dict(name="a", kind="gauss", low=0.0, high=1.0),
])
def test_bad_params_rejected(kwargs: dict) -> None:
    with pytest.raises(ValueError, match="a"):
        Param(**kwargs)


def test_param_round_trip() -> None:
    for p in MIXED:
        assert Param.from_dict(p.to_dict()) == p
    p = Param("k", "log-int", 1, 1024)
    assert p.from_unit(0.0) == 1 and p.from_unit(1.0) == 1024
    assert p.from_unit(p.to_unit(37)) == 37
