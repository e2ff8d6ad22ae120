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
from gyronet.analysis.diagnose.ties import paired_noise, span_labels

log = logging.getLogger(__name__)


def assign_folds(time_s: np.ndarray, n_spans: int = 20, n_folds: int = 5) -> np.ndarray:
    """Fold of each row: the record cut into ``n_spans`` equal spans of time, span i in fold i % n_folds."""
    span_s = (time_s[-1] - time_s[0]) / n_spans * (1 + 1e-12) or 1.0
    return (np.floor((time_s - time_s[0]) / span_s).astype(np.int64)) % n_folds


def _standardise(columns: np.ndarray) -> np.ndarray:
    centred = columns - columns.mean(0)
    scale = centred.std(0)
    return centred / np.where(scale > 1e-12 * (np.abs(columns).max(0) + 1e-300), scale, np.inf)


@dataclass
class _Fold:
    train: np.ndarray  # boolean row masks
    test: np.ndarray
    project: np.ndarray  # (p, n_train): least-squares coefficients of the basis for any columns
    basis: np.ndarray  # (n, p)


def _folds(basis: np.ndarray, fold: np.ndarray, ridge: float, free: np.ndarray | None = None) -> list[_Fold]:
    design = np.column_stack([np.ones(len(basis)), np.nan_to_num(_standardise(basis))])
    # the constant and the regressors marked free (the inputs themselves) are never shrunk
    shrink = np.concatenate([[0.0], np.ones(basis.shape[1]) if free is None else (~np.asarray(free)).astype(float)])
    out = []
    for f in np.unique(fold[fold >= 0]):
        test, train = fold == f, fold != f
        rows = design[train]
        penalty = np.diag(ridge * len(rows) * shrink + 1e-9 * len(rows))
        out.append(_Fold(train, test, np.linalg.solve(rows.T @ rows + penalty, rows.T), design))
    return out


def _fwl(fold: _Fold, columns: np.ndarray) -> np.ndarray:
    """Columns minus their least-squares fit on the basis (fitted on the fold's training rows)."""
    return columns - fold.basis @ (fold.project @ columns[fold.train])


def _dots(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.einsum("ij,ij->j", a, b)


def cv_sse(folds: Sequence[_Fold], target: np.ndarray, candidates: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Held-out sums of squares per axis without (3,) and with each candidate (m, 3).

    ``candidates`` (n, m) are standardised columns; each is added alone to the basis.
    """
    sse0, sse1 = cv_sse_by_fold(folds, target, candidates)
    return sse0.sum(0), sse1.sum(0)


def cv_sse_by_fold(folds: Sequence[_Fold], target: np.ndarray, candidates: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``cv_sse`` fold by fold: (k, 3) without and (k, m, 3) with each candidate."""
    sse0 = np.zeros((len(folds), target.shape[1]))
    sse1 = np.zeros((len(folds), candidates.shape[1], target.shape[1]))
    for k, fold in enumerate(folds):
        y_te, c_te, gamma = _held_out_fit(fold, target, candidates)
        base = _dots(y_te, y_te)
        sse0[k] = base
        # sum (y - gamma c)^2 = sum y^2 - 2 gamma c.y + gamma^2 c.c
        sse1[k] = base[None, :] - 2 * gamma * (c_te.T @ y_te) + gamma**2 * _dots(c_te, c_te)[:, None]
    return sse0, sse1


def cv_sse_by_row(folds: Sequence[_Fold], target: np.ndarray, candidates: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Held-out squared errors row by row: (n, 3) without and (n, m, 3) with each candidate (0 on
    rows never held out), so that two candidates can be compared on the same blocks, paired."""
    sse0 = np.zeros(target.shape)
    sse1 = np.zeros((len(target), candidates.shape[1], target.shape[1]))
    for fold in folds:
        y_te, c_te, gamma = _held_out_fit(fold, target, candidates)
        sse0[fold.test] = y_te**2
        sse1[fold.test] = (y_te[:, None, :] - c_te[:, :, None] * gamma[None, :, :]) ** 2
    return sse0, sse1


def _held_out_fit(fold: _Fold, target: np.ndarray, candidates: np.ndarray) -> tuple[np.ndarray, ...]:
    """The fold's held-out target and candidates, residualised on the basis, and each candidate's
    coefficient per axis (m, 3) fitted on the training rows."""
    # Frisch-Waugh-Lovell: residualise target and candidates on the basis (fitted on the
    # training rows), then one coefficient per candidate and axis from the training rows
    y_res, c_res = _fwl(fold, target), _fwl(fold, candidates)
    tr, te = fold.train, fold.test
    energy = _dots(c_res[tr], c_res[tr])
    usable = energy > 1e-9 * tr.sum()
    gamma = np.where(usable[:, None], (c_res[tr].T @ y_res[tr]) / np.where(usable, energy, 1.0)[:, None], 0.0)
    return y_res[te], c_res[te], gamma


def _scores(sse0: np.ndarray, sse1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Gain (m, 3): the drop in held-out SSE over SSE without; score (m,): its positive part summed."""
    gain = 1.0 - sse1 / np.where(sse0 > 0, sse0, 1.0)[None, :]
    return gain, np.clip(gain, 0.0, None).sum(1)


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


def choose_ridge(basis: np.ndarray, target: np.ndarray, fold: np.ndarray, free: np.ndarray | None = None,
                 grid: Sequence[float] = tuple(10.0 ** np.arange(-6, 4)), tolerance: float = 0.05) -> float:
    """The largest ridge penalty whose held-out error with the basis alone is within ``tolerance``
    of the best (a tolerance in the spirit of the one-standard-error rule).

    A long record needs almost none; a short one (a few dozen blocks for as many regressors)
    needs a lot, or every refit, with or without a candidate, is noise. Of the penalties that
    predict equally well, the largest is taken: an unpenalised candidate then cannot win by
    leaning on the fine structure of a barely determined basis.
    """
    scale = target.std(0) + 1e-300
    errors = np.array([float(cv_sse(_folds(basis, fold, r, free), target / scale, np.zeros((len(target), 0)))[0].sum())
                       for r in grid])
    return float(max(r for r, e in zip(grid, errors) if e <= (1 + tolerance) * errors.min()))


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
    n_rows: int
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
                        len(target), len(folds), ridge, fold_score, cv_sse_by_row(folds, target, cand),
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
