"""Ask, launch, tell: the GA sweeper's loop over generations.

Each generation is bred by :mod:`gyronet.training.ga` from the previous one, sent to the launcher as
one batch, and scored by the jobs' return values (lower is better; a failed job scores inf).
Outputs in the sweep dir: ``ga_history.json`` after every generation, and at the end
``optimization_results.yaml``, ``best/<best_artifact>/`` and TensorBoard curves in ``tb/``.
"""
from __future__ import annotations

import logging
import math
import shutil
from dataclasses import asdict
from pathlib import Path
from typing import Any, Dict, List, Optional

import numpy as np
from hydra.core.override_parser.overrides_parser import OverridesParser
from hydra.core.plugins import Plugins
from hydra.plugins.sweeper import Sweeper
from hydra.types import HydraContext, TaskFunction
from omegaconf import DictConfig, OmegaConf
from tqdm import tqdm

from gyronet.training.ga import Individual, Param, next_generation, random_individual

from ._history import HISTORY_FILE, Evaluation, Generation, History, job_dir, params_key, score
from ._space import describe, parse_search_space, tidy, to_overrides
from ._tensorboard import SweepWriter
from ._resume import RESULTS_FILE, GASweepError, lock_sweep_dir, start, too_many_failed
from ._watchdog import WatchedTask
from .config import GAOptions

log = logging.getLogger(__name__)



# ---------------------------------------------------------------- the sweeper


class GASweeperImpl(Sweeper):
    """Genetic-algorithm sweeper: one launcher batch per generation."""

    def __init__(self, options: GAOptions, params: Optional[DictConfig]) -> None:
        self.options = options
        self.params: Dict[str, Any] = dict(params) if params else {}
        self.config: Optional[DictConfig] = None
        self.hydra_context: Optional[HydraContext] = None
        self.launcher: Any = None
        self.job_idx = 0

    def setup(self, *, hydra_context: HydraContext, task_function: TaskFunction,
              config: DictConfig) -> None:
        self.config = config
        self.hydra_context = hydra_context
        # a worker process of the launcher exits when this process dies, even by SIGKILL
        self.launcher = Plugins.instance().instantiate_launcher(
            config=config, hydra_context=hydra_context, task_function=WatchedTask(task_function))
        self.sweep_dir = Path(str(config.hydra.sweep.dir))

    def sweep(self, arguments: List[str]) -> None:
        assert self.config is not None and self.hydra_context is not None
        parser = OverridesParser.create(config_loader=self.hydra_context.config_loader)
        lines = [f"{k}={v}" for k, v in self.params.items()] + list(arguments)
        try:
            space, fixed = parse_search_space(lines, parser)
        except (ValueError, TypeError) as err:  # bounds the ga module refuses, e.g. interval(3.0, 0.3)
            raise GASweepError(f"bad GA search space: {err}") from None
        if not space:
            raise GASweepError("the GA sweeper has no search space: set hydra.sweeper.params or "
                               "pass sweep overrides such as x='interval(0, 1)'")
        self.sweep_dir.mkdir(parents=True, exist_ok=True)
        self._lock = lock_sweep_dir(self.sweep_dir)  # held until this process ends
        history = self._start(space, fixed)
        opts = self.options
        log.info("GA sweep: population %d, generations %d, seed %d, into %s", opts.population_size,
                 opts.generations, opts.seed, self.sweep_dir)
        log.info("search space: %s; fixed: %s", ", ".join(describe(p) for p in space), fixed)
        tb = SweepWriter(self.sweep_dir / "tb")
        # the bar shows on a terminal only: in a log file, the line per generation says it all
        bar = tqdm(total=opts.generations, initial=len(history.generations), desc="GA",
                   unit="gen", dynamic_ncols=True, disable=None)
        completed = False
        try:
            for index in range(len(history.generations), opts.generations):
                gen = self._evaluate(index, self._breed(index, history, space), fixed, history)
                history.generations.append(gen)
                history.save(self.sweep_dir / HISTORY_FILE)
                best_so_far = self._report(gen, history, bar)
                self._check_failures(gen)
                tb.generation(gen, best_so_far)  # after the check: a stopping generation is run again on resume
            completed = True
        finally:
            bar.close()
            tb.close()
            if history.generations:
                self._write_results(history, final_run=completed)
        if history.best() is None:
            raise GASweepError(f"GA sweep ended without a result: none of its {self.job_idx} jobs returned a finite "
                               f"number (every job and its error are in {self.sweep_dir / HISTORY_FILE})")

    # -- ask

    def _start(self, space: List[Param], fixed: List[str]) -> History:
        """A new history, or the one in the sweep dir when resuming (``_resume.start``)."""
        assert self.config is not None
        subdir = OmegaConf.to_container(self.config.hydra.sweep, resolve=False).get("subdir")
        history = start(self.sweep_dir, [p.to_dict() for p in space], fixed, self.options, subdir)
        self.job_idx = history.next_job_idx()
        return history

    def _breed(self, index: int, history: History, space: List[Param]) -> List[Individual]:
        """Generation ``index``, drawn from its own rng so a resumed sweep repeats it exactly."""
        rng = np.random.default_rng([self.options.seed, index])
        opts = self.options
        if index == 0:
            population = [random_individual(space, rng) for _ in range(opts.population_size)]
            start = self._config_individual(space) if opts.start_from_config else None
            if start is not None:
                population[0] = start
        else:
            last = history.generations[-1]
            population = next_generation(
                [e.params for e in last.individuals], last.fitness, space, rng,
                elitism=opts.elitism, tournament_size=opts.tournament_size,
                crossover_rate=opts.crossover_rate, mutation_rate=opts.mutation_rate,
                mutation_scale=opts.mutation_scale, size=opts.population_size)
        return [tidy(ind, space) for ind in population]

    def _config_individual(self, space: List[Param]) -> Optional[Individual]:
        """The application's config values for the searched keys, numbers clipped into their
        bounds; None when a key has no plain value there (a config group) or a choice misses it."""
        values: Individual = {}
        for p in space:
            value = OmegaConf.select(self.config, p.name, default=None)
            if isinstance(value, (int, float)) and not isinstance(value, bool) and p.is_numeric:
                value = min(max(value, p.low), p.high)
                value = int(round(value)) if p.is_int else float(value)
            if value is None or not p.contains(value):
                log.info("generation 0 is random: the config has no usable value for %s (%r)", p.name, value)
                return None
            values[p.name] = value
        log.info("generation 0 starts from the config: %s", " ".join(to_overrides(values)))
        return values

    # -- launch and tell

    def _evaluate(self, index: int, population: List[Individual], fixed: List[str],
                  history: History) -> Generation:
        """Run the individuals not evaluated before as one batch; reuse the others' results."""
        done = history.lookup()
        to_run: Dict[str, List[int]] = {}  # params key -> positions in the population
        for i, ind in enumerate(population):
            if params_key(ind) not in done:
                to_run.setdefault(params_key(ind), []).append(i)
        batch = [fixed + to_overrides(population[pos[0]]) for pos in to_run.values()]
        results: Dict[str, Evaluation] = {}
        if batch:
            self.validate_batch_is_legal(batch)
            returns = self.launcher.launch(batch, initial_job_idx=self.job_idx)
            for key, overrides, ret in zip(to_run, batch, returns):
                fitness, status, error = score(ret)
                if error:
                    log.warning("job %d %s: %s", self.job_idx, status.lower(), error)
                results[key] = Evaluation(population[to_run[key][0]], fitness, status,
                                          self.job_idx, job_dir(ret, self.sweep_dir),
                                          list(overrides), error)
                self.job_idx += 1
        individuals = []
        for i, ind in enumerate(population):
            key = params_key(ind)
            first_run = key in results and to_run[key][0] == i
            source = results[key] if key in results else done[key]
            individuals.append(Evaluation(**{**asdict(source), "cached": not first_run}))
        return Generation(index, individuals)

    def _check_failures(self, gen: Generation) -> None:
        if not too_many_failed(gen, self.options.max_failure_rate):
            return
        summary = gen.summary()
        first = next(e for e in gen.individuals if e.failed and not e.cached)
        msg = (f"GA sweep stopped: {summary['failed']} of {summary['jobs']} jobs failed in "
               f"generation {gen.index}, more than max_failure_rate="
               f"{self.options.max_failure_rate}. First failure, job {first.job_idx} "
               f"({first.job_dir}): {first.error}. Every job is in "
               f"{self.sweep_dir / HISTORY_FILE}; rerun to resume after fixing the cause.")
        log.error(msg)
        raise GASweepError(msg)

    # -- report

    def _report(self, gen: Generation, history: History, bar: tqdm) -> float:
        """The generation's line in the log and the bar; the best fitness so far."""
        s = gen.summary()
        best = history.best()
        best_so_far = best.fitness if best else math.inf
        log.info("generation %d (%d of %d): best %.6g, mean %.6g, std %.6g; %d jobs, %d failed, "
                 "%d reused; best so far %.6g (job %s)", gen.index, gen.index + 1,
                 self.options.generations,
                 s["best_fitness"], s["mean_fitness"], s["std_fitness"], s["jobs"], s["failed"],
                 s["reused"], best_so_far, best.job_idx if best else None)
        bar.set_postfix(best=f"{best_so_far:.4g}")
        bar.update(1)
        return best_so_far

    def _write_results(self, history: History, final_run: bool = False) -> None:
        """``optimization_results.yaml`` and ``best/<best_artifact>`` from the best job so far
        (with ``final_run``, from its run with ``final``'s overrides when there are any)."""
        best = history.best()
        results = {
            "name": "ga",
            "best_evaluated_params": best.params if best else None,
            "best_evaluated_result": best.fitness if best else None,
            "best_overrides": self._with_final(best.overrides) if best else None,
            "best_job_dir": best.job_dir if best else None,
            "best_generation": history.generation_of(best) if best else None,
            "generations": len(history.generations),
            "jobs": sum(g.summary()["jobs"] for g in history.generations),
        }
        OmegaConf.save(OmegaConf.create(results), self.sweep_dir / RESULTS_FILE)
        if best is None:
            log.warning("no job returned a finite value: no best parameters")
            return
        log.info("best value %.6g with %s", best.fitness, " ".join(to_overrides(best.params)))
        # an extension that stopped keeps the final run of a best it did not beat
        final_dir = self._done_final_run(best, history) or (self._final_run(best, history) if final_run else None)
        if self._copy_best(final_dir or best.job_dir):
            results.update(best_artifact_job_dir=final_dir or best.job_dir, best_artifact_is_final_run=bool(final_dir))
            OmegaConf.save(OmegaConf.create(results), self.sweep_dir / RESULTS_FILE)

    def _done_final_run(self, best: Evaluation, history: History) -> Optional[str]:
        """The job dir of the history's final run when it is the best's with ``final``'s overrides, else None."""
        done = history.final_run
        if not self.options.final or not self.options.best_artifact or done is None or done["job_dir"] is None \
                or done["overrides"] != self._with_final(best.overrides) \
                or not (self.sweep_dir / done["job_dir"] / self.options.best_artifact).is_dir():
            return None
        log.info("final run reused: job %d (%s)", done["job_idx"], done["job_dir"])
        return done["job_dir"]

    def _final_run(self, best: Evaluation, history: History) -> Optional[str]:
        """Run the best individual once more with ``final``'s overrides; its job dir, or None.

        The run is kept in the history: a finished sweep run again reuses it (its folder is not an
        interrupted job's), unless the best or ``final`` changed.
        """
        final = self.options.final
        if not final or not self.options.best_artifact:
            return None
        overrides = self._with_final(best.overrides)
        log.info("final run of the best (job %d) with %s", self.job_idx, " ".join(f"{k}={v}" for k, v in final.items()))
        try:
            ret = self.launcher.launch([overrides], initial_job_idx=self.job_idx)[0]
        except Exception as err:  # a bad final override or a launcher failure must not lose the sweep's results
            log.warning("the final run could not start (%s: %s): copying the best search job's %s instead",
                        type(err).__name__, str(err).splitlines()[0] if str(err) else "", self.options.best_artifact)
            return None
        finally:
            self.job_idx += 1
        fitness, status, error = score(ret)
        if error:
            log.warning("the final run %s (%s): copying the best search job's %s instead",
                        status.lower(), error, self.options.best_artifact)
            return None
        log.info("final run: value %.6g (the search job's %.6g)", fitness, best.fitness)
        history.final_run = {"job_idx": self.job_idx - 1, "job_dir": job_dir(ret, self.sweep_dir),
                             "overrides": overrides, "fitness": fitness}
        history.save(self.sweep_dir / HISTORY_FILE)
        return history.final_run["job_dir"]

    def _with_final(self, overrides: List[str]) -> List[str]:
        """``overrides`` with ``final``'s in place of any for the same keys."""
        final = self.options.final
        keys = {k.lstrip("+~") for k in final}
        kept = [o for o in overrides if o.split("=", 1)[0].lstrip("+~") not in keys]
        return kept + [f"{k}={v}" for k, v in final.items()]

    def _copy_best(self, best_dir: str) -> bool:
        """Copy ``best_artifact`` from ``best_dir`` to ``<sweep dir>/best/``; whether there was one to copy."""
        name = self.options.best_artifact
        if not name:
            return False
        src = self.sweep_dir / best_dir / name  # an absolute job_dir replaces the prefix
        dst = self.sweep_dir / "best" / name
        if not src.is_dir():
            log.warning("the best job wrote no %s folder: nothing copied to %s", src, dst)
            return False
        if dst.exists():
            shutil.rmtree(dst)
        shutil.copytree(src, dst)
        log.info("copied %s to %s", src, dst)
        return True
