"""The screen's held-out least squares (folds, FWL update, ridge), apart so that screen.py stays short."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np


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
