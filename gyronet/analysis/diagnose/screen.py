"""The screen: does a candidate feature lower the held-out error by more than chance can?

**What is compared.** The current network is frozen into a basis: every regressor its output
layers combine (``RBFNet.basis``: the Gaussians, the normalised inputs, the powers of T) plus a
constant, evaluated causally at the full rate and averaged over ``block_s`` (60 s) blocks, the
contract's error block. Per axis, the output layer is refitted by least squares without and with
one candidate column, and each is scored on blocks it was not fitted on: blocked K-fold
cross-validation over interleaved time spans (span ``i`` of ``n_spans`` belongs to fold
``i % n_folds``, so every fold covers the whole thermal history, the start included), or, with a
separate validation recording, fitted on the training record and scored on the other. The gain of
a candidate on an axis is ``1 - SSE_with / SSE_without`` of the held-out 60 s residual, and its
score is the sum of its positive gains over the axes. The candidate's coefficient is fitted to
what the basis fit leaves (the Frisch-Waugh-Lovell update, exact without a penalty; with the ridge
an approximation, used alike for the observed score and the shifted null), so a candidate costs a
few dot products and the whole screen needs no network training. The penalty on the refit is a ridge on the standardised nonlinear regressors
(the model's inputs themselves and the constant stay free, so a candidate that merely copies an
input gains nothing), chosen per round as the largest that predicts held-out blocks within 5 % as
well as the best: a long record gets almost none, a short one a lot.

**Why it is not fooled.** Held-out scoring already charges a candidate for fitting noise. What
remains is chance correlation between a slowly varying candidate and a slowly varying residual,
and the number of candidates tried. Both are handled by a max-statistic permutation test
(Westfall and Young): every candidate column is shifted circularly in time by the same random
lag (within each recording), which keeps each candidate's autocorrelation and the candidates'
correlations with one another but breaks any alignment with the residual; the best score over
all candidates is recorded for each of ``n_shifts`` distinct lags (all of them, when a short
record has fewer, so its p-values are as coarse as they should be). A candidate passes when its score
beats that maximum in all but a fraction ``alpha`` of the shifts (family-wise error ``alpha``
over every candidate tried) and when it is at least ``min_gain`` (an effect too small to matter
is not worth a retraining even when it is real). An axis is listed when its own gain passes the
same max-over-candidates test for that axis. What chance cannot explain may still be the
baseline's own small imperfection: the loop (:mod:`.loop`) therefore confirms every candidate
that passes by retraining the network with it.

References
----------
P. H. Westfall and S. S. Young, *Resampling-Based Multiple Testing*, Wiley (1993), ch. 2.
R. Frisch and F. V. Waugh, Partial time regressions as compared with individual trends,
Econometrica 1(4), 387-401 (1933).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import numpy as np

from gyronet.recordings.data import AXES
from gyronet.analysis.diagnose.cv import (_folds, _scores, _standardise, choose_ridge, cv_sse, cv_sse_by_fold,
                                          cv_sse_by_row)
from gyronet.analysis.diagnose.ties import paired_noise, span_labels

log = logging.getLogger(__name__)


def assign_folds(time_s: np.ndarray, n_spans: int = 20, n_folds: int = 5) -> np.ndarray:
    """Fold of each row: the record cut into ``n_spans`` equal spans of time, span i in fold i % n_folds."""
    span_s = (time_s[-1] - time_s[0]) / n_spans * (1 + 1e-12) or 1.0
    return (np.floor((time_s - time_s[0]) / span_s).astype(np.int64)) % n_folds


def _shifted(columns: np.ndarray, recording: np.ndarray, fraction: float) -> np.ndarray:
    out = np.empty_like(columns)
    for r in np.unique(recording):
        rows = np.flatnonzero(recording == r)
        out[rows] = np.roll(columns[rows], int(round(fraction * len(rows))), axis=0)
    return out


def shift_fractions(recording: np.ndarray, n_shifts: int, rng: np.random.Generator) -> np.ndarray:
    """Distinct circular shifts between 10 % and 90 % of the longest recording, as fractions of it.

    When there are fewer distinct shifts than ``n_shifts`` all of them are used, so a short record
    gets the coarse p-values it deserves instead of repeats that would fake precision.
    """
    n_rows = int(np.bincount(recording - recording.min()).max())
    lags = np.arange(int(np.ceil(0.1 * n_rows)), int(np.floor(0.9 * n_rows)) + 1)
    if len(lags) > n_shifts:
        lags = np.sort(rng.choice(lags, n_shifts, replace=False))
    return lags / n_rows


@dataclass
class ScreenResult:
    """What the screen found, one entry per candidate (rows of ``gain``)."""

    names: list[str]
    specs: list[dict]
    gain: np.ndarray  # (m, 3): 1 - SSE_with / SSE_without, held out
    score: np.ndarray  # (m,): sum of positive gains
    p_value: np.ndarray  # (m,): family-wise, from the max over candidates under circular shifts
    axis_p_value: np.ndarray  # (m, 3): the same per axis
    null_max: np.ndarray  # (n_shifts,): best score over all candidates at each shift
    rmse_before: np.ndarray  # (3,): held-out RMS of the 60 s residual, deg/s
    rmse_after: np.ndarray  # (m, 3): the same with each candidate
    n_rows: int  # held-out 60 s blocks scored
    n_folds: int
    ridge: float
    fold_score: np.ndarray | None = None  # (m, k): the score on each held-out fold alone
    row_sse: tuple | None = None  # held-out squared errors per row, (n, 3) without and (n, m, 3) with
    span: np.ndarray | None = None  # (n,): span of each row (``ties.span_labels``), -1 never held out

    def tie_noise(self, best: int, other: np.ndarray) -> np.ndarray:
        """The screen's own noise on ``score[best] - score[other]``: the standard error of the paired
        per-block difference, clustered by span (:mod:`.ties`); without the rows, of the paired
        per-fold difference (0 with a single held-out set of one span)."""
        other = np.atleast_1d(other)
        if self.row_sse is not None and self.span is not None:
            return paired_noise(*self.row_sse, self.gain, self.span, best, other)
        if self.fold_score is None or self.fold_score.shape[1] < 2:
            return np.zeros(len(other))
        diff = self.fold_score[best][None, :] - self.fold_score[other]
        return diff.std(1, ddof=1) / np.sqrt(diff.shape[1])

    def passing(self, alpha: float, min_gain: float) -> np.ndarray:
        """Indices of candidates that pass, best score first."""
        ok = np.flatnonzero((self.p_value <= alpha) & (self.score >= min_gain))
        return ok[np.argsort(-self.score[ok])]

    def axes(self, index: int, alpha: float) -> list[str]:
        """Axes on which candidate ``index`` passes alone (the best one if none does)."""
        hits = [a for i, a in enumerate(AXES) if self.axis_p_value[index, i] <= alpha and self.gain[index, i] > 0]
        return hits or [AXES[int(np.argmax(self.gain[index]))]]

    def table(self) -> list[dict[str, Any]]:
        """One JSON-ready row per candidate, best score first."""
        order = np.argsort(-self.score)
        return [{"name": self.names[i], "spec": self.specs[i], "score": float(self.score[i]),
                 "p_value": float(self.p_value[i]), "gain": dict(zip(AXES, self.gain[i].round(5).tolist())),
                 "rmse_after_dps": dict(zip(AXES, self.rmse_after[i].tolist()))} for i in order]


def screen(basis: np.ndarray, target: np.ndarray, candidates: np.ndarray, fold: np.ndarray,
           recording: np.ndarray, names: Sequence[str], specs: Sequence[Mapping[str, Any]],
           n_shifts: int = 199, seed: int = 0, ridge: float | None = None,
           free: np.ndarray | None = None, span_rows: int = 10) -> ScreenResult:
    """Test every candidate against the current model's held-out residual.

    Parameters
    ----------
    basis
        (n, p) the current model's regressors, block-averaged (rows are 60 s blocks).
    target
        (n, 3) the block-averaged drift (gyro minus the static rate), deg/s.
    candidates
        (n, m) block-averaged candidate features.
    fold
        (n,) held-out fold of each row; -1 for rows only ever fitted on (a training record
        scored on a separate one).
    recording
        (n,) which recording each row belongs to; shifts stay within a recording.
    names, specs
        One per candidate column.
    n_shifts
        Circular shifts for the null distribution (p-values no smaller than 1 / (n_shifts + 1)).
    seed
        Seeds the shifts.
    ridge
        Ridge penalty on the standardised basis, relative to the number of rows; None chooses it
        by cross-validation of the basis alone (``choose_ridge``).
    free
        (p,) regressors never penalised (the model's inputs themselves), or None.
    span_rows
        Longest span, in rows, over which the tie test's noise is clustered (:mod:`.ties`): the
        cross-validation span over the block (600 s / 60 s).
    """
    ridge = choose_ridge(basis, target, fold, free) if ridge is None else ridge
    folds = _folds(basis, fold, ridge, free)
    cand = np.nan_to_num(_standardise(candidates))
    sse0_fold, sse1_fold = cv_sse_by_fold(folds, target, cand)
    sse0, sse1 = sse0_fold.sum(0), sse1_fold.sum(0)
    gain, score = _scores(sse0, sse1)
    fold_score = np.column_stack([_scores(a, b)[1] for a, b in zip(sse0_fold, sse1_fold)])
    fractions = shift_fractions(recording, n_shifts, np.random.default_rng(seed))
    null_max = np.empty(len(fractions))
    null_axis = np.empty((len(fractions), target.shape[1]))
    for k, fraction in enumerate(fractions):
        _, sse1_null = cv_sse(folds, target, _shifted(cand, recording, fraction))
        gain_null, score_null = _scores(sse0, sse1_null)
        null_max[k] = score_null.max(initial=0.0)
        null_axis[k] = gain_null.max(0, initial=0.0)
    # p = (1 + #{shifts whose best candidate did at least as well}) / (1 + n_shifts)
    p_value = (1 + (null_max[None, :] >= score[:, None]).sum(1)) / (1 + len(fractions))
    axis_p = (1 + (null_axis[None, :, :] >= gain[:, None, :]).sum(1)) / (1 + len(fractions))
    n_test = int(sum(f.test.sum() for f in folds))
    return ScreenResult(list(names), [dict(s) for s in specs], gain, score, p_value, axis_p, null_max,
                        np.sqrt(sse0 / n_test), np.sqrt(np.clip(sse1, 0, None) / n_test),
                        n_test, len(folds), ridge, fold_score, cv_sse_by_row(folds, target, cand),
                        span_labels(fold, recording, span_rows))


def score_only(basis: np.ndarray, target: np.ndarray, candidates: np.ndarray, fold: np.ndarray,
               ridge: float | None = None, free: np.ndarray | None = None, by_row: bool = False) -> tuple:
    """Held-out gains (m, 3), scores (m,) and RMS after (m, 3), without the permutation test
    (for refining a parameter of a candidate that passed); with ``by_row``, also the held-out
    squared errors per row, ``cv_sse_by_row``'s pair, for the tie test."""
    folds = _folds(basis, fold, choose_ridge(basis, target, fold, free) if ridge is None else ridge, free)
    cand = np.nan_to_num(_standardise(candidates))
    sse0, sse1 = cv_sse(folds, target, cand)
    n_test = int(sum(f.test.sum() for f in folds))
    out = (*_scores(sse0, sse1), np.sqrt(np.clip(sse1, 0, None) / n_test))
    return (*out, cv_sse_by_row(folds, target, cand)) if by_row else out
