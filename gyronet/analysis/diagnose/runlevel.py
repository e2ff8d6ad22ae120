"""Run-level candidates: what is constant within a run and changes between runs, and its null.

A campaign's runs differ by what no within-run history shows: a per-run offset (turn-on bias,
kind ``run_offset``: one constant per run) and the orientation of the fixture (a column that is
constant within each run but not between them, such as the mean ``acc_z_g``: g-sensitivity).
Such a candidate is constant within each run, so a circular shift within a run leaves it
unchanged, and a shift of the glued record carries the joint between the runs.

**The null: runs permuted in pieces.** Each run is cut into ``n_pieces`` contiguous pieces, and
the pieces are dealt out to the runs at random (each run gets as many as it had): under the null
the residual's level is the same in every piece whatever its run, so any deal explains as much as
the real one. A run-level candidate passes when its held-out score beats the best score of every
run-level candidate under the dealt labels in all but a fraction ``alpha`` of the deals. Whole
runs alone cannot be permuted usefully (two runs have two orders), and a circular shift within
a run leaves a constant unchanged. The test assumes that the residual forgets within a piece (a
twelfth of a run by default): a wander as slow as a run is, to any test, a per-run offset, and
the confirmation is what stands between it and the final bundle. Measured on synthetic campaigns
of three runs (``tests/test_diagnose_runs.py``, seeds 100-139, 49 deals or positions each), at
alpha = 0.05: a stationary wander alone passes 4 of 40 (two expected); two other nulls, pseudo-runs
relabelled at one point inside every run and one step per run, pass 6 and 4 of 40; with a decaying
start-up transient in every run (a per-run difference in effect) all three pass 15-20 of 40. The
deal is kept for its argument (pieces are exchangeable under the null; a relabelled pseudo-run is
not a contiguous piece), not for its figures.

The score is the screen's: the held-out drop of the 60 s residual's sum of squares, summed over
the axes, with K folds of interleaved spans within every run (each run's constants are fitted on
its training spans and scored on its held-out ones), on top of the model's frozen regressors.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np

from gyronet.recordings.data import AXES
from gyronet.analysis.diagnose.cv import _dots, _folds, _fwl, _scores, _standardise, choose_ridge


@dataclass
class RunCandidate:
    """A run-level candidate: its spec and its value per run, (n_runs, g) (g columns of constants)."""

    spec: dict
    per_run: np.ndarray

    @property
    def name(self) -> str:
        if self.spec["kind"] == "run_offset":
            return "run_offset"
        return f"{self.spec['source']}_per_run"


def run_candidates(run_means: dict[str, np.ndarray], run_spread: dict[str, np.ndarray], n_runs: int,
                   min_ratio: float = 5.0) -> list[RunCandidate]:
    """``run_offset`` and every column whose run means differ by ``min_ratio`` times its within-run spread.

    Parameters
    ----------
    run_means, run_spread
        Per column, its mean in each run and the standard deviation of its block means within
        each run, (n_runs,) each.
    """
    dummies = np.eye(n_runs)[:, 1:]
    out = [RunCandidate({"kind": "run_offset", "source": "run", "n_free": max(0, n_runs - 2)}, dummies)]
    for name, means in run_means.items():
        if np.ptp(means) > min_ratio * max(float(np.max(run_spread[name])), 1e-12):
            out.append(RunCandidate({"kind": "column", "source": name, "tau_s": 0.0}, means[:, None]))
    return out


def dealt_labels(run: np.ndarray, position: np.ndarray, n_pieces: int, rng: np.random.Generator) -> np.ndarray:
    """Each row's run after the runs' pieces (``n_pieces`` a run, by position) are dealt out at random."""
    n_runs = int(run.max()) + 1
    piece = run * n_pieces + np.minimum((position * n_pieces).astype(int), n_pieces - 1)
    return rng.permutation(np.repeat(np.arange(n_runs), n_pieces))[piece]


def _group_sse(folds: Sequence, target: np.ndarray, columns: np.ndarray) -> np.ndarray:
    """Held-out SSE per axis with the group ``columns`` (n, g) added to the basis (Frisch-Waugh-Lovell)."""
    sse = np.zeros(target.shape[1])
    for fold in folds:
        if columns.shape[1] == 0:
            y_res = _fwl(fold, target)[fold.test]
            sse += _dots(y_res, y_res)
            continue
        y_res, c_res = _fwl(fold, target), _fwl(fold, columns)
        tr, te = fold.train, fold.test
        coef, *_ = np.linalg.lstsq(c_res[tr], y_res[tr], rcond=None)
        diff = y_res[te] - c_res[te] @ coef
        sse += _dots(diff, diff)
    return sse


@dataclass
class RunScreen:
    """The run-level screen's result, one entry per candidate."""

    candidates: list[RunCandidate]
    gain: np.ndarray  # (m, 3)
    score: np.ndarray  # (m,)
    p_value: np.ndarray  # (m,)
    null_max: np.ndarray  # (n_u,)
    rmse_before: np.ndarray  # (3,)
    rmse_after: np.ndarray  # (m, 3)

    def passing(self, alpha: float, min_gain: float) -> np.ndarray:
        ok = np.flatnonzero((self.p_value <= alpha) & (self.score >= min_gain))
        return ok[np.argsort(-self.score[ok])]

    def table(self) -> list[dict[str, Any]]:
        order = np.argsort(-self.score)
        return [{"name": self.candidates[i].name, "spec": self.candidates[i].spec, "score": float(self.score[i]),
                 "p_value": float(self.p_value[i]), "gain": dict(zip(AXES, self.gain[i].round(5).tolist()))}
                for i in order]


def screen_runs(basis: np.ndarray, free: np.ndarray | None, target: np.ndarray, fold: np.ndarray, run: np.ndarray,
                position: np.ndarray, candidates: Sequence[RunCandidate], n_shifts: int = 199, seed: int = 0,
                ridge: float | None = None, n_pieces: int = 12) -> RunScreen:
    """Score run-level candidates on held-out blocks and test them against runs permuted in pieces.

    Parameters
    ----------
    basis, free
        (n, p) the model's block-averaged regressors and which are inputs (unpenalised).
    target
        (n, 3) block-averaged drift, deg/s.
    fold
        (n,) held-out fold of each row (interleaved spans within every run).
    run, position
        (n,) each row's run and its place in the run (0 at the start, 1 at the end).
    candidates
        From ``run_candidates``.
    n_shifts
        Random deals of the pieces.
    n_pieces
        Pieces a run is cut into.
    """
    ridge = choose_ridge(basis, target, fold, free) if ridge is None else ridge
    folds = _folds(basis, fold, ridge, free)

    sse0 = _group_sse(folds, target, np.zeros((len(target), 0)))
    sse1 = np.array([_group_sse(folds, target, np.nan_to_num(_standardise(c.per_run[run]))) for c in candidates])
    gain, score = _scores(sse0, sse1)
    rng = np.random.default_rng(seed)

    def best(labels: np.ndarray) -> float:
        sse = np.array([_group_sse(folds, target, np.nan_to_num(_standardise(c.per_run[labels]))) for c in candidates])
        return float(_scores(sse0, sse)[1].max())

    null_max = np.array([best(dealt_labels(run, position, n_pieces, rng)) for _ in range(n_shifts)])
    # p = (1 + #{deals whose best candidate did at least as well}) / (1 + n_shifts)
    p_value = (1 + (null_max[None, :] >= score[:, None]).sum(1)) / (1 + len(null_max))
    n_test = int(sum(f.test.sum() for f in folds))
    return RunScreen(list(candidates), gain, score, p_value, null_max, np.sqrt(sse0 / n_test),
                     np.sqrt(np.clip(sse1, 0, None) / n_test))
