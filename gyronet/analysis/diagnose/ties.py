"""Do two candidates explain the held-out residual equally well? Their paired difference, block by block.

Two candidates are compared on the same held-out 60 s blocks. Each block and axis contributes
``(SSE_without - SSE_with) / SSE_without(axis)`` to a candidate's gain on that axis, so a
candidate's score (its positive gains summed over the axes) is the sum of its blocks'
contributions, and the difference of two scores is the sum of the blocks' paired differences.
Neighbouring blocks share their errors (a slow residual), so the noise of that sum is estimated
across spans (the cross-validation's own units, 600 s by default), not blocks: with ``S`` span
sums ``d_s`` of the paired difference, ``SE = sqrt(S / (S - 1) * sum (d_s - mean d)^2)``, the
standard error of a sum of ``S`` exchangeable parts (the clustered form of Diebold and Mariano's
test of equal predictive accuracy).

Pairing is what makes the test hold for collinear candidates: two near-copies of one signal err
alike on every block, so their difference is measured against the noise of the difference, not
of either score. Estimating it across a record's 50-odd spans rather than its five folds gives
the standard error 50 degrees of freedom instead of 4: with 4, a run of similar folds makes it
small by chance, and a consistent hair between near-copies was called a real difference.

References
----------
F. X. Diebold and R. S. Mariano, Comparing predictive accuracy, Journal of Business and Economic
Statistics 13(3), 253-263 (1995).
"""
from __future__ import annotations

import logging

import numpy as np

log = logging.getLogger(__name__)


def span_labels(fold: np.ndarray, recording: np.ndarray, max_rows: int = 10) -> np.ndarray:
    """A span label per row: runs of consecutive rows of one recording and one held-out fold, cut
    every ``max_rows`` rows (a separate validation recording is one fold: its span is ``max_rows``
    blocks). Rows never held out (fold -1) get -1."""
    fold, recording = np.asarray(fold), np.asarray(recording)
    start = np.ones(len(fold), bool)
    start[1:] = (fold[1:] != fold[:-1]) | (recording[1:] != recording[:-1])
    run = np.cumsum(start) - 1
    first_of_run = np.flatnonzero(start)[run]
    position = np.arange(len(fold)) - first_of_run
    label = np.cumsum(start | (position % max(1, int(max_rows)) == 0)) - 1
    return np.where(fold >= 0, label, -1)


def block_contributions(sse0_rows: np.ndarray, sse1_rows: np.ndarray, gain: np.ndarray,
                        index: np.ndarray) -> np.ndarray:
    """Each row's share (n, len(index)) of the scores of candidates ``index``: per axis with a
    positive gain, ``(sse0 - sse1) / SSE0(axis)``, summed over those axes (sums to the score)."""
    total = sse0_rows.sum(0)
    share = (sse0_rows[:, None, :] - sse1_rows[:, index, :]) / np.where(total > 0, total, 1.0)[None, None, :]
    return (share * (gain[index] > 0)[None, :, :]).sum(2)


def paired_noise(sse0_rows: np.ndarray, sse1_rows: np.ndarray, gain: np.ndarray, span: np.ndarray, best: int,
                 other: np.ndarray) -> np.ndarray:
    """Standard error of ``score[best] - score[other]`` from the paired per-block differences,
    clustered by span (module docstring); 0 where fewer than two spans are held out.

    Parameters
    ----------
    sse0_rows, sse1_rows
        Held-out squared errors per row without (n, 3) and with each candidate (n, m, 3).
    gain
        (m, 3) the candidates' held-out gains (which axes count in each score).
    span
        (n,) span label of each row (``span_labels``; -1: never held out).
    best, other
        The candidate compared and those it is compared with.
    """
    other = np.atleast_1d(np.asarray(other, dtype=int))
    held = span >= 0
    labels, cluster = np.unique(span[held], return_inverse=True)
    if len(labels) < 2 or not len(other):
        return np.zeros(len(other))
    share = block_contributions(sse0_rows[held], sse1_rows[held], gain, np.concatenate([[best], other]))
    diff = share[:, :1] - share[:, 1:]  # (n_held, len(other))
    by_span = np.zeros((len(labels), len(other)))
    np.add.at(by_span, cluster, diff)
    # var(sum of S parts) = S * var(part)
    return np.sqrt(len(labels) * by_span.var(0, ddof=1))
