"""Options of the GA sweeper, registered in the ConfigStore as ``hydra/sweeper=ga``."""
from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional

from hydra.core.config_store import ConfigStore

# An application may ship its default search space as conf/hydra/sweeper/params/default.yaml;
# it fills hydra.sweeper.params and is skipped when absent. Select another with
# hydra/sweeper/params=NAME. Likewise conf/hydra/sweeper/final/default.yaml fills
# hydra.sweeper.final.
defaults: List[Any] = ["_self_", {"optional params": "default"}, {"optional final": "default"}]


@dataclass
class GASweeperConf:
    """The GA sweeper's options (``hydra.sweeper.*``): what each field does is said above it."""

    _target_: str = "hydra_plugins.gyronet_ga_sweeper.ga_sweeper.GASweeper"
    defaults: List[Any] = field(default_factory=lambda: list(defaults))

    # individuals per generation; each generation is one batch sent to the launcher, which
    # runs at most its own number of workers at a time
    population_size: int = 16

    # generations to reach, counting those already in a resumed ga_history.json; the budget
    # is about population_size * generations jobs (elites and repeats are not run again)
    generations: int = 10

    # individuals drawn at random for each parent tournament; the fittest wins
    # (1 is random selection, larger is greedier)
    tournament_size: int = 3

    # probability that two parents are recombined (otherwise the children are copies)
    crossover_rate: float = 0.9

    # probability that each gene of a child is mutated
    mutation_rate: float = 0.2

    # standard deviation of a numeric mutation, as a fraction of the parameter's range
    # (of its log range for tag(log, ...) parameters)
    mutation_scale: float = 0.1

    # how many of the best individuals pass unchanged to the next generation
    elitism: int = 1

    # seed of the GA's random numbers; generation g is drawn from (seed, g), so a resumed
    # sweep continues exactly as an uninterrupted one would
    seed: int = 0

    # stop the sweep with an error when the fraction of failed jobs in a generation (an
    # exception, or a return value that is not a number) exceeds this
    max_failure_rate: float = 0.5

    # make the first individual of generation 0 the application's own config (its values for
    # the searched keys, clipped into the space), so that with elitism the sweep's best is never
    # worse than the defaults; the other individuals are drawn at random
    start_from_config: bool = True

    # continue from <sweep dir>/ga_history.json when it exists with the same search space
    resume: bool = True

    # folder in the best job's output dir to copy to <sweep dir>/best/ (null: copy nothing)
    best_artifact: Optional[str] = "compensator"

    # search space in Hydra's override grammar, e.g.
    #   model.n_centers: int(interval(8, 64))
    #   optim.lr: tag(log, interval(1e-4, 1e-1))
    #   model: choice(rbf, poly3)
    # non-sweep values are passed unchanged to every job; sweep overrides on the command
    # line (x='interval(0, 1)') are added to it and win over the same key here
    params: Dict[str, str] = field(default_factory=dict)

    # overrides (key: value) for one more run of the best individual after the last generation,
    # whose best_artifact is the one copied to <sweep dir>/best/: work the fitness does not need
    # (gyronet's search jobs stop at validation, train.for_bundle=false in params; the final run
    # sets it true). Empty: no final run, the best search job's artifact is copied
    final: Dict[str, str] = field(default_factory=dict)


@dataclass(frozen=True)
class GAOptions:
    """The GA sweeper's options, checked; see ``GASweeperConf`` for what each one means."""

    population_size: int
    generations: int
    tournament_size: int
    crossover_rate: float
    mutation_rate: float
    mutation_scale: float
    elitism: int
    seed: int
    max_failure_rate: float
    start_from_config: bool
    resume: bool
    best_artifact: Optional[str]
    final: Dict[str, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        """Refuse options that would run a sweep that searches nothing, in one line each."""
        if self.population_size < 2:  # one individual breeds no other: only the default config would be scored
            raise ValueError(f"population_size must be at least 2, got {self.population_size}")
        if self.generations < 1:
            raise ValueError(f"generations must be at least 1, got {self.generations}")
        if not 0 <= self.elitism < self.population_size:
            raise ValueError(f"elitism must be in [0, population_size - 1 = {self.population_size - 1}] (the rest "
                             f"are children), got {self.elitism}")
        if self.tournament_size < 1:
            raise ValueError(f"tournament_size must be at least 1, got {self.tournament_size}")
        if self.seed < 0:  # numpy's generators take no negative seed
            raise ValueError(f"seed must be >= 0, got {self.seed}")
        if self.mutation_scale < 0:
            raise ValueError(f"mutation_scale must be >= 0, got {self.mutation_scale}")
        for name in ("crossover_rate", "mutation_rate", "max_failure_rate"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"{name} must be in [0, 1], got {getattr(self, name)}")


ConfigStore.instance().store(
    group="hydra/sweeper",
    name="ga",
    node=GASweeperConf,
    provider="gyronet_ga_sweeper",
)
