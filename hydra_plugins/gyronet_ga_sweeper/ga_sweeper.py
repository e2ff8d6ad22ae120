"""The ``Sweeper`` Hydra discovers; the work happens in ``_impl``, imported only when used."""
from typing import Any, List, Optional

from hydra.plugins.sweeper import Sweeper
from hydra.types import HydraContext, TaskFunction
from omegaconf import DictConfig


class GASweeper(Sweeper):
    """Minimise the task's return value with a genetic algorithm (see ``config.GASweeperConf``)."""

    def __init__(
        self,
        population_size: int,
        generations: int,
        tournament_size: int,
        crossover_rate: float,
        mutation_rate: float,
        mutation_scale: float,
        elitism: int,
        seed: int,
        max_failure_rate: float,
        resume: bool,
        best_artifact: Optional[str],
        params: Optional[DictConfig] = None,
        start_from_config: bool = True,
        final: Optional[DictConfig] = None,
    ) -> None:
        from ._impl import GASweeperImpl
        from .config import GAOptions

        options = GAOptions(
            population_size=population_size,
            generations=generations,
            tournament_size=tournament_size,
            crossover_rate=crossover_rate,
            mutation_rate=mutation_rate,
            mutation_scale=mutation_scale,
            elitism=elitism,
            seed=seed,
            max_failure_rate=max_failure_rate,
            start_from_config=start_from_config,
            resume=resume,
            best_artifact=best_artifact,
            final={str(k): str(v) for k, v in (final or {}).items()},
        )
        self.sweeper = GASweeperImpl(options, params)

    def setup(
        self,
        *,
        hydra_context: HydraContext,
        task_function: TaskFunction,
        config: DictConfig,
    ) -> None:
        self.sweeper.setup(hydra_context=hydra_context, task_function=task_function, config=config)

    def sweep(self, arguments: List[str]) -> Any:
        return self.sweeper.sweep(arguments)
