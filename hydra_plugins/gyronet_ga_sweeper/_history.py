"""The sweep's record, ``<sweep dir>/ga_history.json``: every generation, every individual, and what a job scores.

It is rewritten after each generation, so an interrupted sweep can resume from its last
complete generation. Non-finite numbers are stored as ``null`` (JSON has no inf or NaN).
"""
from __future__ import annotations

import json
import math
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

import numpy as np
from hydra.core.utils import JobReturn, JobStatus
from omegaconf import OmegaConf

HISTORY_FILE = "ga_history.json"
FORMAT_VERSION = 1

# a job that raised, or returned something that is not a number: counts towards max_failure_rate
FAILED_STATUSES = ("FAILED", "INVALID")


def params_key(params: Dict[str, Any]) -> str:
    """A hashable identity of an individual's parameters (stable across a JSON round trip)."""
    return json.dumps(params, sort_keys=True)


def _finite_or_none(x: float) -> Optional[float]:
    return float(x) if math.isfinite(x) else None


@dataclass
class Evaluation:
    """One individual of one generation and what its job returned.

    ``status`` is ``COMPLETED`` (a finite number), ``NONFINITE`` (NaN or inf: scored inf),
    ``FAILED`` (the job raised) or ``INVALID`` (it returned something that is not a number).
    ``cached`` marks an individual whose parameters were already evaluated (an elite, or a
    repeat); it reuses that job's result and directory instead of running again.
    """

    params: Dict[str, Any]
    fitness: float
    status: str
    job_idx: Optional[int] = None
    job_dir: Optional[str] = None
    overrides: List[str] = field(default_factory=list)
    error: Optional[str] = None
    cached: bool = False

    @property
    def failed(self) -> bool:
        """Whether the job failed (as opposed to returning a bad but numeric value)."""
        return self.status in FAILED_STATUSES

    def to_json(self) -> Dict[str, Any]:
        d = asdict(self)
        d["fitness"] = _finite_or_none(self.fitness)
        return d

    @classmethod
    def from_json(cls, d: Dict[str, Any]) -> "Evaluation":
        fitness = math.inf if d.get("fitness") is None else float(d["fitness"])
        return cls(**{**d, "fitness": fitness})


@dataclass
class Generation:
    """One evaluated population."""

    index: int
    individuals: List[Evaluation]

    @property
    def fitness(self) -> np.ndarray:
        return np.array([e.fitness for e in self.individuals], dtype=float)

    def summary(self) -> Dict[str, Any]:
        """Best, mean and std of the finite fitness (NaN when none), and the job counts."""
        f = self.fitness
        finite = f[np.isfinite(f)]
        launched = [e for e in self.individuals if not e.cached]
        return {
            "best_fitness": float(finite.min()) if finite.size else math.nan,
            "mean_fitness": float(finite.mean()) if finite.size else math.nan,
            "std_fitness": float(finite.std()) if finite.size else math.nan,
            "jobs": len(launched),
            "failed": sum(e.failed for e in launched),
            "reused": len(self.individuals) - len(launched),
        }

    def to_json(self) -> Dict[str, Any]:
        summary = {k: _finite_or_none(v) if isinstance(v, float) else v
                   for k, v in self.summary().items()}
        return {"generation": self.index, **summary,
                "individuals": [e.to_json() for e in self.individuals]}

    @classmethod
    def from_json(cls, d: Dict[str, Any]) -> "Generation":
        return cls(d["generation"], [Evaluation.from_json(e) for e in d["individuals"]])


@dataclass
class History:
    """Everything a sweep did, in order; the first generation is number 0."""

    search_space: List[Dict[str, Any]]
    fixed_overrides: List[str]
    generations: List[Generation] = field(default_factory=list)
    options: Dict[str, Any] = field(default_factory=dict)
    final_run: Optional[Dict[str, Any]] = None  # the best's run with ``final``'s overrides: job_idx, job_dir, overrides
    fixed_files: Dict[str, str] = field(default_factory=dict)  # SHA-256 of each file a fixed override names

    def evaluations(self) -> List[Evaluation]:
        """Every individual of every generation, in order."""
        return [e for g in self.generations for e in g.individuals]

    def best(self) -> Optional[Evaluation]:
        """The first individual with the lowest finite fitness, or None."""
        finite = [e for e in self.evaluations() if math.isfinite(e.fitness)]
        return min(finite, key=lambda e: e.fitness) if finite else None

    def generation_of(self, evaluation: Evaluation) -> int:
        """Index of the first generation holding ``evaluation``."""
        return next(g.index for g in self.generations if evaluation in g.individuals)

    def lookup(self) -> Dict[str, Evaluation]:
        """Results that can be reused, by :func:`params_key`: every job that did not fail."""
        done: Dict[str, Evaluation] = {}
        for e in self.evaluations():
            if not e.failed:
                done.setdefault(params_key(e.params), e)
        return done

    def next_job_idx(self) -> int:
        """The job number after the highest one used so far."""
        used = [e.job_idx for e in self.evaluations() if e.job_idx is not None]
        if self.final_run is not None:
            used.append(self.final_run["job_idx"])
        return max(used) + 1 if used else 0

    def save(self, path: Path) -> None:
        """Write atomically, so an interruption never leaves a truncated file."""
        doc = {"version": FORMAT_VERSION, "search_space": self.search_space,
               "fixed_overrides": self.fixed_overrides, "fixed_files": self.fixed_files, "options": self.options,
               "generations": [g.to_json() for g in self.generations],
               **({"final_run": self.final_run} if self.final_run is not None else {})}
        tmp = path.with_name(path.name + ".tmp")
        tmp.write_text(json.dumps(doc, indent=1))
        os.replace(tmp, path)

    @classmethod
    def load(cls, path: Path) -> "History":
        doc = json.loads(path.read_text())
        if doc.get("version") != FORMAT_VERSION:
            raise ValueError(f"{path}: unknown format version {doc.get('version')!r}")
        return cls(search_space=doc["search_space"], fixed_overrides=doc["fixed_overrides"],
                   generations=[Generation.from_json(g) for g in doc["generations"]],
                   options=doc.get("options", {}), final_run=doc.get("final_run"),
                   fixed_files=doc.get("fixed_files", {}))


def score(ret: JobReturn) -> Tuple[float, str, Optional[str]]:
    """Fitness, status and error text of a finished job (see ``Evaluation``)."""
    if ret.status != JobStatus.COMPLETED:
        err = ret._return_value  # the exception; ret.return_value would re-raise it
        return math.inf, "FAILED", f"{type(err).__name__}: {err}"
    value = ret.return_value
    if value is None or isinstance(value, (str, bytes, bool)):
        return math.inf, "INVALID", f"returned {value!r}, not a number"
    try:
        fitness = float(value)
    except (TypeError, ValueError):
        return math.inf, "INVALID", f"returned {type(value).__name__} {value!r}, not a number"
    if not math.isfinite(fitness):
        return math.inf, "NONFINITE", f"returned {fitness}"
    return fitness, "COMPLETED", None


def job_dir(ret: JobReturn, sweep_dir: Path) -> Optional[str]:
    """The job's output dir, relative to the sweep dir when inside it."""
    out = OmegaConf.select(ret.hydra_cfg, "hydra.runtime.output_dir") if ret.hydra_cfg else None
    if out is None:
        return None
    rel = os.path.relpath(out, sweep_dir.resolve())
    return out if rel.startswith("..") else rel
