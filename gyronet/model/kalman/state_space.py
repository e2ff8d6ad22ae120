"""The Kalman stage's per-axis state-space matrices and their steady-state ``lfilter`` form, apart from running it."""
from __future__ import annotations

import math

import numpy as np
from scipy import signal

from gyronet.model.kalman.identify import companion, companion_covariance


def axis_matrices(axis, q_rate_per_sample: float, mode: str) -> dict[str, np.ndarray]:
    """F, Q, H, the prior P0 (drift part) and the output row C, D of one axis.

    The state is ``[r, d_1, ..., d_p]``; an order-0 model (no drift found) has ``[r]`` alone.
    """
    p = axis.order
    n = p + 1
    F, Q, P0 = np.zeros((n, n)), np.zeros((n, n)), np.zeros((n, n))
    F[0, 0], F[1:, 1:] = 1.0, companion(np.asarray(axis.ar))
    Q[0, 0] = q_rate_per_sample
    P0[1:, 1:] = companion_covariance(np.asarray(axis.ar), axis.q_drift_dps2)
    H, drift = np.zeros(n), np.zeros(n)
    H[0] = 1.0
    if p:
        Q[1, 1] = axis.q_drift_dps2
        H[1] = drift[1] = 1.0
    rate = np.eye(n)[0]
    # y = C x + D z: r_hat, r_hat + d_hat or z - d_hat
    C, D = {"rate": (rate, 0.0), "smooth": (rate + drift, 0.0), "bias": (-drift, 1.0)}[mode]
    return {"F": F, "Q": Q, "P0": P0, "H": H, "C": C, "D": D}


def lfilter_state(b: np.ndarray, a: np.ndarray, A: np.ndarray, C: np.ndarray, x: np.ndarray) -> np.ndarray:
    """The lfilter ``zi`` whose free response equals the state-space one from ``x``.

    With zero input the state-space output is ``C A^j x``; lfilter's is linear in ``zi``. Matching
    the first m samples (m = the order) fixes ``zi``: the DF2T free-response matrix is triangular
    with a unit diagonal.
    """
    m = len(a) - 1
    free = np.empty(m)
    state = x.copy()
    for j in range(m):
        free[j] = C @ state
        state = A @ state
    basis = np.column_stack([signal.lfilter(b, a, np.zeros(m), zi=np.eye(m)[i])[0] for i in range(m)])
    return np.linalg.solve(basis, free)


def q_rate_for_time_constant(r_dps2: float | np.ndarray, fs_hz: float, tau_s: float) -> np.ndarray:
    """The ``q_rate_dps2_per_s`` that gives the rate estimate a time constant ``tau_s``.

    For a random walk in white noise of variance ``R`` the steady gain is ``K``, the pole
    ``1 - K = exp(-1 / (fs tau))``, and ``q dt = K^2 R / (1 - K)`` (the drift state ignored).

    Parameters
    ----------
    r_dps2
        White noise variance per sample, (deg/s)^2 (``AxisModel.r_dps2``), scalar or per axis.
    fs_hz
        Sampling rate, Hz.
    tau_s
        Wanted time constant (63 % of a step), s.

    Returns
    -------
    np.ndarray
        q per axis, (deg/s)^2/s.
    """
    gain = 1.0 - math.exp(-1.0 / (fs_hz * tau_s))
    return np.asarray(r_dps2, dtype=np.float64) * gain ** 2 / (1.0 - gain) * fs_hz
