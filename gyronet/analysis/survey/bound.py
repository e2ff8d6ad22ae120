"""What an estimator that knows the simulator's drift formula gets on the same records: a bound, not a method.

``form-bound`` fits, by least squares, the terms of :mod:`gyronet.sim.sensor`'s formula along the
true die temperature: each axis's cubic, its knees' tanh at their true centres and widths and
``(g + h x) dT/dt``, at the axis's true thermal lag, every axis's terms on every axis (the
cross-axis coupling), and a constant per training run. Only the coefficients are learnt, so it
shows what the records' noise leaves to a model of the right form. A method that must learn the
form from the data fits more from the same samples. A real sensor gives no formula, so it is not
a method to train.
"""
from __future__ import annotations

from typing import Any, Mapping, Sequence

import numpy as np

from gyronet.analysis.survey.scoring import kept_rows, score_rates, with_startup_offset
from gyronet.errors import GyronetError
from gyronet.recordings.data import Recording
from gyronet.sim.sensor import N_AXES, first_order_lag
from gyronet.training.dataset import static_rate_dps

BOUND = "form-bound"  # its name in the survey's table


def form_columns(truth: Mapping[str, np.ndarray], sensor: Mapping[str, Any]) -> np.ndarray:
    """The formula's terms of every axis along a record's true die temperature, shape (n, 6-7 per axis)."""
    time_s, die_c = truth["time_s"], truth["die_temp_c"]
    step_s = np.diff(time_s)
    if step_s.max() > 1.5 * np.median(step_s):  # the lags would be filtered over the gaps: a wrong bound
        raise GyronetError("form-bound needs records without lost rows (simulate's loss): use bound=false")
    fs_hz = 1.0 / float(np.median(step_s))
    lags_s = sensor.get("axis_lag_s", [0.0] * N_AXES)
    knee2_dps = sensor.get("knee2_dps", [0.0] * N_AXES)
    columns = []
    for axis in range(N_AXES):
        temp_c = first_order_lag(die_c, fs_hz, float(lags_s[axis]))
        x = (temp_c - sensor["ref_c"]) / sensor["scale_c"]
        rate_c_per_s = np.gradient(temp_c, time_s)
        columns += [x, x**2, x**3, np.tanh((temp_c - sensor["knee_c"][axis]) / sensor["knee_width_c"][axis]),
                    rate_c_per_s, x * rate_c_per_s]
        if knee2_dps[axis]:
            columns.append(np.tanh((temp_c - sensor["knee2_c"][axis]) / sensor["knee2_width_c"][axis]))
    return np.column_stack(columns)


def form_bound_rate_dps(train: Sequence[tuple[Recording, Mapping[str, np.ndarray]]], check: Recording,
                        check_truth: Mapping[str, np.ndarray], sensor: Mapping[str, Any]) -> np.ndarray:
    """The held-out record compensated by the formula's least-squares fit to the training runs, shape (n, 3).

    Each run has its own constant (its turn-on bias), and the fit keeps their mean, as a campaign's model does.
    """
    n_runs = len(train)
    designs, targets = [], []
    for k, (recording, truth) in enumerate(train):
        terms = form_columns(truth, sensor)
        run_constant = np.zeros((len(terms), n_runs))
        run_constant[:, k] = 1.0
        designs.append(np.hstack([terms, run_constant]))
        targets.append(recording.gyro_dps - static_rate_dps(recording))
    coef, *_ = np.linalg.lstsq(np.vstack(designs), np.vstack(targets), rcond=None)
    drift_dps = form_columns(check_truth, sensor) @ coef[:-n_runs] + coef[-n_runs:].mean(axis=0)
    return check.gyro_dps - drift_dps


def score_form_bound(train: Sequence[tuple[Recording, Mapping[str, np.ndarray]]], check: Recording,
                     check_truth: Mapping[str, np.ndarray], sensor: Mapping[str, Any], startup_s: float,
                     turn_on_difference_dps: np.ndarray) -> dict[str, list[float]]:
    """``form-bound`` scored as :func:`.scoring.score_bundle` scores a method (no error bar)."""
    plain_dps = form_bound_rate_dps(train, check, check_truth, sensor)
    deployed_dps = with_startup_offset(check, plain_dps, startup_s)
    return score_rates(check, check_truth, kept_rows(check, startup_s), deployed_dps, plain_dps, turn_on_difference_dps)
