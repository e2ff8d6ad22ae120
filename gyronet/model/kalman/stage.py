"""``KalmanStage``: the filter after the network, run causally, sample by sample or in blocks.

Per axis the state is ``x = [r, d_1, ..., d_p]``: the true rate r (a random walk) and the residual
drift's AR(p) companion state. The three axes are one block-diagonal
``filterpy.kalman.KalmanFilter``. ``P`` and ``K`` do not depend on the data, so once the gain has
converged (``max |K_k - K_{k-1}| < gain_tol``) the filter is linear time-invariant; from that
sample on it runs as ``scipy.signal.lfilter`` per axis, with the filter's state carried over
exactly. The switch happens at the same sample count however the stream is cut into calls, so
one call on a recording and one call per sample give the same numbers.
"""
from __future__ import annotations

import copy
import json
import logging
import os
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
from filterpy.kalman import KalmanFilter
from scipy import signal

from gyronet.atomic import write_json
from gyronet.errors import GyronetError
from gyronet.model.kalman.identify import AXES, KalmanModel
from gyronet.model.kalman.state_space import axis_matrices, lfilter_state, q_rate_for_time_constant

__all__ = ["DEFAULT_MODE", "DEFAULT_Q_RATE_DPS2_PER_S", "FORMAT", "KalmanInputError", "KalmanStage", "MODES", "VERSION",
           "q_rate_for_time_constant"]

log = logging.getLogger(__name__)

MODES = ("rate", "smooth", "bias")
FORMAT = "gyronet.model.kalman"
VERSION = 1
DEFAULT_MODE = "smooth"
# A time constant of about 1 s on the noisiest of the paper's axes (N = 5.89 deg/sqrt(h)):
# tau = sqrt(R / fs) / sqrt(q) = (5.89 / 60) / sqrt(1e-2) = 0.98 s; measured in docs/guides/kalman.md.
DEFAULT_Q_RATE_DPS2_PER_S = 1e-2
# Blocks this long go through scipy.signal.lfilter; shorter ones (live samples) through the same
# recursion written in numpy, which skips lfilter's per-call overhead.
_LFILTER_MIN_SAMPLES = 16


class KalmanInputError(GyronetError, ValueError):
    """A rate sample the filter cannot take (NaN or inf, wrong shape)."""


class KalmanStage:
    """Kalman filter on the compensated rate ``c = gyro - drift_hat``, deg/s, shape (n, 3).

    Model, per axis and per sample (``dt = 1 / fs_hz``)::

        r_k = r_{k-1} + u_k                        u ~ N(0, q_rate_dps2_per_s * dt)
        d_k = a_1 d_{k-1} + ... + a_p d_{k-p} + w_k  w ~ N(0, q_drift)   (identified)
        c_k = r_k + d_k + v_k                      v ~ N(0, R)         (identified)

    Parameters
    ----------
    model
        The identified residual model (:func:`gyronet.model.kalman.identify`), or its ``to_dict()``.
    mode
        What comes out, per axis:

        - ``"smooth"`` (default): ``r_hat + d_hat``, the paper's variant: the compensated signal
          with only the white noise removed, an optimal low-pass of unit DC gain.
        - ``"rate"``: the estimated true rate ``r_hat``: white noise and residual drift removed.
          Equal to ``smooth`` at any useful bandwidth (the drift is not observable there); with a
          tiny ``q_rate`` it takes a rotation step for drift and needs about the drift's
          correlation time (an hour in docs/guides/kalman.md) to pass it.
        - ``"bias"``: ``c - d_hat``: only the residual drift removed, the white noise and fast
          rotations passed at full bandwidth; a no-op unless ``q_rate`` is tiny.
    q_rate_dps2_per_s
        The bandwidth knob: the true rate's random-walk intensity, (deg/s)^2 per second, one
        number or one per axis. Larger follows a rotation faster and removes less noise; the
        rate's time constant is about ``sqrt(R / fs) / sqrt(q)`` seconds (``R`` per sample), see
        :func:`q_rate_for_time_constant`. A static record cannot identify it: a sensor at rest
        has ``q = 0``. Must be > 0.
    initial_rate_sigma_dps
        Prior standard deviation of the rate at ``reset()``, deg/s: large means "unknown".
    gain_tol
        Switch to the steady-state gain once no element of K moves by more than this in a step.
        The drift part of K keeps creeping towards its limit for as long as the drift's
        correlation time; the switched filter stays within 1e-6 deg/s of the fully time-varying
        one on the records of docs/guides/kalman.md.

    Notes
    -----
    Observability: r and d enter the measurement only as their sum, so they are told apart by
    their dynamics alone. A constant is always rate (the AR drift has mean 0); a change faster
    than the rate's time constant is mostly attributed to the drift while its AR model makes that
    plausible. With ``q_rate`` much larger than the drift's ``q_drift`` (any useful bandwidth) the
    filter cannot see the drift, ``rate`` and ``smooth`` agree and ``bias`` does almost nothing;
    only a filter told the rate is nearly constant (tiny ``q_rate``, a static sensor) removes the
    drift, and then a real rotation is first taken for drift too.

    ``process`` raises :class:`KalmanInputError` (a ValueError) on NaN or inf, naming the sample
    (counted from ``reset()``) and the axis, before changing any state; the live path must drop
    or fill such samples before the stage.

    References
    ----------
    .. [1] R. G. Brown, P. Y. C. Hwang, "Introduction to Random Signals and Applied Kalman
       Filtering", 4th ed., Wiley, 2012, ch. 4 (the filter), ch. 7 (augmented states).
    .. [2] B. D. O. Anderson, J. B. Moore, "Optimal Filtering", Prentice-Hall, 1979, ch. 4
       (steady-state gain, time-invariant filter).
    """

    def __init__(self, model: KalmanModel | Mapping[str, Any], mode: str = DEFAULT_MODE,
                 q_rate_dps2_per_s: float | Sequence[float] = DEFAULT_Q_RATE_DPS2_PER_S,
                 initial_rate_sigma_dps: float = 100.0, gain_tol: float = 1e-10):
        self.model = model if isinstance(model, KalmanModel) else KalmanModel.from_dict(dict(model))
        if mode not in MODES:
            raise GyronetError(f"kalman mode must be one of {', '.join(MODES)}, got {mode!r}")
        n_axes = len(self.model.axes)
        q = np.broadcast_to(np.asarray(q_rate_dps2_per_s, dtype=np.float64), (n_axes,)).copy()
        if not np.all(np.isfinite(q) & (q > 0)):
            raise GyronetError(f"q_rate_dps2_per_s must be > 0 (per axis), got {q.tolist()}")
        self.mode, self.q_rate_dps2_per_s = mode, q
        self.initial_rate_sigma_dps, self.gain_tol = float(initial_rate_sigma_dps), float(gain_tol)
        self._blocks = [axis_matrices(m, float(qi) / self.model.fs_hz, mode) for m, qi in zip(self.model.axes, q)]
        self._slices, start = [], 0
        for block in self._blocks:
            self._slices.append(slice(start, start + len(block["F"])))
            start += len(block["F"])
        # y = C x + D z for all axes at once
        self._C = np.zeros((n_axes, start))
        for i, (blk, s) in enumerate(zip(self._blocks, self._slices)):
            self._C[i, s] = blk["C"]
        self._D = np.array([blk["D"] for blk in self._blocks])
        self.reset()

    # -- running ---------------------------------------------------------------------------------

    def reset(self) -> None:
        """Start a new stream: the prior state, the time-varying gain again."""
        self.kf = self._new_filter()
        self.n_samples = 0
        self.steady_since: int | None = None
        # steady state: lfilter coefficients b, a (n_axes, m + 1) and state zi (n_axes, m)
        self._lti: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self._gain = self.kf.K.copy()

    def peek(self, rate_dps: np.ndarray) -> np.ndarray:
        """``process`` without changing the state: the output for samples that must not enter it.

        A flagged sample (``bad_input``: a glitch) gets the filter's estimate from it, while the
        next samples see the filter as if it had never come.
        """
        saved = (copy.deepcopy(self.kf), self.n_samples, self.steady_since, self._gain,
                 None if self._lti is None else tuple(a.copy() for a in self._lti))
        try:
            return self.process(rate_dps)
        finally:
            self.kf, self.n_samples, self.steady_since, self._gain, self._lti = saved

    def process(self, rate_dps: np.ndarray) -> np.ndarray:
        """Filter the next samples of the compensated rate.

        Parameters
        ----------
        rate_dps
            Compensated rate, deg/s, shape (n, 3); finite.

        Returns
        -------
        np.ndarray
            The filtered rate (see ``mode``), deg/s, shape (n, 3).
        """
        z = self._checked(rate_dps)
        out = np.empty_like(z)
        k = 0
        while k < len(z) and self._lti is None:
            out[k] = self._step(z[k])
            k += 1
        if k < len(z):
            out[k:] = self._steady_state(z[k:])
            self.n_samples += len(z) - k
        return out

    def _step(self, z_k: np.ndarray) -> np.ndarray:
        """One time-varying Kalman step (filterpy); switch to the LTI form once K has settled."""
        kf = self.kf
        # x = F x, P = F P F^T + Q
        kf.predict()
        # K = P H^T (H P H^T + R)^-1, x = x + K (z - H x), P = (I - K H) P (I - K H)^T + K R K^T
        kf.update(z_k[:, None])
        self.n_samples += 1
        y = self._C @ kf.x[:, 0] + self._D * z_k
        if self.n_samples > 1 and np.max(np.abs(kf.K - self._gain)) < self.gain_tol:
            self._switch_to_steady_state()
        self._gain = kf.K.copy()
        return y

    def _switch_to_steady_state(self) -> None:
        """Freeze K; carry the state over into a direct-form-II-transposed filter per axis."""
        systems = []
        for i, (blk, s) in enumerate(zip(self._blocks, self._slices)):
            K = self.kf.K[s, i]
            # x_k = A x_{k-1} + B z_k with A = (I - K H) F, B = K; y_k = C x_k + D z_k
            A = (np.eye(len(K)) - np.outer(K, blk["H"])) @ blk["F"]
            C_next, D_next = blk["C"] @ A, blk["C"] @ K + blk["D"]
            num, den = signal.ss2tf(A, K[:, None], C_next[None, :], np.array([[D_next]]))
            systems.append((num[0] / den[0], den / den[0], A, C_next, self.kf.x[s, 0]))
        # one order m for all axes: trailing zero coefficients leave the extra states at 0
        m = max(len(a) for _, a, *_ in systems) - 1
        b, a = np.zeros((len(systems), m + 1)), np.zeros((len(systems), m + 1))
        for i, (bi, ai, *_ ) in enumerate(systems):
            b[i, :len(bi)], a[i, :len(ai)] = bi, ai
        zi = np.array([lfilter_state(b[i], a[i], A, C, x) for i, (_, _, A, C, x) in enumerate(systems)])
        self._lti = (b, a, zi)
        self.steady_since = self.n_samples
        log.debug("kalman gain steady after %d samples (%.1f s)", self.n_samples, self.n_samples / self.model.fs_hz)

    def _steady_state(self, z: np.ndarray) -> np.ndarray:
        """The LTI filter: lfilter per axis for blocks, the same recursion in numpy for a few samples."""
        b, a, zi = self._lti
        out = np.empty_like(z)
        if len(z) >= _LFILTER_MIN_SAMPLES:
            for i in range(z.shape[1]):
                out[:, i], zi[i] = signal.lfilter(b[i], a[i], z[:, i], zi=zi[i])
            return out
        for k, x in enumerate(z):
            # lfilter's DF2T, same operations in the same order: y = z_0 + b_0 x,
            # z_j = (z_{j+1} + x b_{j+1}) - y a_{j+1}, z_{m-1} = x b_m - y a_m
            y = zi[:, 0] + b[:, 0] * x
            zi[:, :-1] = (zi[:, 1:] + x[:, None] * b[:, 1:-1]) - y[:, None] * a[:, 1:-1]
            zi[:, -1] = x * b[:, -1] - y * a[:, -1]
            out[k] = y
        return out

    def _checked(self, rate_dps: np.ndarray) -> np.ndarray:
        z = np.asarray(rate_dps, dtype=np.float64)
        if z.ndim != 2 or z.shape[1] != len(self._blocks):
            raise KalmanInputError(f"kalman: rate_dps must have shape (n, {len(self._blocks)}), got {z.shape}")
        if not np.isfinite(z).all():
            row, col = np.argwhere(~np.isfinite(z))[0]
            raise KalmanInputError(f"kalman: sample {self.n_samples + row} (axis {AXES[col]}) is {z[row, col]}; "
                                   "drop or fill NaN/inf samples before the Kalman stage")
        return z

    def _new_filter(self) -> KalmanFilter:
        n_x = sum(len(b["F"]) for b in self._blocks)
        kf = KalmanFilter(dim_x=n_x, dim_z=len(self._blocks))
        F, Q, P, H = (np.zeros((n_x, n_x)) for _ in range(4))
        H = np.zeros((len(self._blocks), n_x))
        for i, (blk, s) in enumerate(zip(self._blocks, self._slices)):
            F[s, s], Q[s, s], P[s, s], H[i, s] = blk["F"], blk["Q"], blk["P0"], blk["H"]
            P[s.start, s.start] = self.initial_rate_sigma_dps ** 2
        kf.F, kf.Q, kf.P, kf.H = F, Q, P, H
        kf.R = np.diag([m.r_dps2 for m in self.model.axes])
        kf.x = np.zeros((n_x, 1))
        return kf

    # -- inspection ------------------------------------------------------------------------------

    @property
    def steady(self) -> bool:
        """True once the gain has converged and the filter runs as an LTI filter."""
        return self._lti is not None

    def rate_sigma_dps(self) -> np.ndarray:
        """Predicted standard deviation of the rate estimate, sqrt(P[r, r]) per axis, deg/s."""
        return np.sqrt([self.kf.P[s.start, s.start] for s in self._slices])

    # -- persistence -----------------------------------------------------------------------------

    def to_dict(self) -> dict[str, Any]:
        """The ``kalman.json`` content: options and the identified model; JSON-able."""
        return {"format": FORMAT, "version": VERSION, "mode": self.mode,
                "q_rate_dps2_per_s": self.q_rate_dps2_per_s.tolist(),
                "initial_rate_sigma_dps": self.initial_rate_sigma_dps, "gain_tol": self.gain_tol,
                "model": self.model.to_dict()}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> "KalmanStage":
        """Rebuild a stage from :meth:`to_dict` output (a fresh, reset stage)."""
        if data.get("format", FORMAT) != FORMAT or int(data.get("version", VERSION)) > VERSION:
            raise GyronetError(f"kalman: unsupported format {data.get('format')!r} version {data.get('version')!r}")
        options = {k: data[k] for k in ("mode", "q_rate_dps2_per_s", "initial_rate_sigma_dps", "gain_tol") if k in data}
        return cls(KalmanModel.from_dict(data["model"]), **options)

    def save(self, path: str | os.PathLike) -> Path:
        """Write :meth:`to_dict` as JSON (``kalman.json``), whole or not at all."""
        path = Path(path)
        write_json(path, self.to_dict())
        return path

    @classmethod
    def load(cls, path: str | os.PathLike) -> "KalmanStage":
        """Read a stage written by :meth:`save`."""
        return cls.from_dict(json.loads(Path(path).read_text()))
