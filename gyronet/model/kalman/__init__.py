"""The Kalman stage after the network: the residual drift's time-series model and its filter.

The input is the compensated rate ``c = gyro - drift_hat`` (deg/s, one column per axis) and the
output a filtered rate. Per axis, with k the sample index:

- ``x``: the state, ``[r, d_1, ..., d_p]``: the true rate r (deg/s) and the residual drift's
  AR(p) companion state (``d_1`` the current drift, deg/s; the rest its past values).
- ``P``: the covariance of the error of ``x``, (deg/s)^2.
- ``F``: the state transition, ``x_k = F x_{k-1} + noise``: 1 for the rate (a random walk), the
  AR companion matrix for the drift.
- ``Q``: the covariance of that noise per sample: ``q_rate_dps2_per_s / fs`` on the rate (the
  bandwidth knob), the identified ``q_drift`` on the drift.
- ``H``: the measurement row, ``c_k = H x_k + v_k = r_k + d_k + v_k``.
- ``R``: the variance of the white measurement noise ``v_k``, (deg/s)^2, identified.
- ``K``: the Kalman gain, ``x <- x + K (c - H x)``; it depends only on the model, so it converges
  and the filter then runs as a linear time-invariant filter.

:func:`identify` fits the model to the network's residual on the training record,
:class:`KalmanStage` runs it causally (``reset``, ``process``, ``to_dict``/``from_dict``,
``save``/``load``), and :func:`allan_cost` and :func:`step_response` measure what it buys and
costs. docs/guides/kalman.md has the design and the measurements.
"""
from gyronet.model.kalman.costs import allan_cost, step_response
from gyronet.model.kalman.identify import AxisModel, KalmanModel, identify
from gyronet.model.kalman.stage import KalmanInputError, KalmanStage, q_rate_for_time_constant

__all__ = ["AxisModel", "KalmanInputError", "KalmanModel", "KalmanStage", "allan_cost", "identify",
           "q_rate_for_time_constant", "step_response"]
