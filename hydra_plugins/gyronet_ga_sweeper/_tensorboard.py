"""TensorBoard output of a GA sweep; torch is imported only when a sweep starts."""
from __future__ import annotations

import logging
import math
from pathlib import Path

from ._history import Generation

log = logging.getLogger(__name__)


class SweepWriter:
    """Fitness curves per generation and an hparams row per job, in ``<sweep dir>/tb``."""

    def __init__(self, log_dir: Path) -> None:
        try:
            from torch.utils.tensorboard import SummaryWriter
        except ImportError as err:  # the sweep is worth running without curves
            log.warning("no TensorBoard output: %s", err)
            self.writer = None
            return
        self.writer = SummaryWriter(log_dir=str(log_dir))

    def generation(self, gen: Generation, best_so_far: float) -> None:
        if self.writer is None:
            return
        summary = gen.summary()
        for name in ("best_fitness", "mean_fitness", "std_fitness"):
            if math.isfinite(summary[name]):
                self.writer.add_scalar(f"ga/{name}", summary[name], gen.index)
        if math.isfinite(best_so_far):
            self.writer.add_scalar("ga/best_so_far", best_so_far, gen.index)
        self.writer.add_scalar("ga/failed_jobs", summary["failed"], gen.index)
        for e in gen.individuals:
            if not e.cached:
                fitness = e.fitness if math.isfinite(e.fitness) else math.nan
                self.writer.add_hparams(dict(e.params), {"ga/fitness": fitness},
                                        run_name=f"job{e.job_idx}")
        self.writer.flush()

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
