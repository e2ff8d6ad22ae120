"""A generic smoother on the survey's records: what a model that does not know the drift's form gets from one cycle.

python docs/results/generic_smoother.py FIRST LAST [PENALTY]   # e.g. 0 20 1e-2 (run by hand, not by the build)

Per axis, least squares in a cubic B-spline of the temperature (knots every 1 degC, a second-difference
penalty PENALTY per sample) plus (a + b x) dT/dt, on the survey's training record of each sensor (the cycle,
its noise as the survey draws it), scored as deployed and with the truth's turn-on bias as the survey scores
a method. It is given what gyronet must find: the true die temperature and each axis's true thermal lag.
One JSON line a sensor; the median, 90th percentile and worst of the worst axis at the end.
"""
import json
import sys

import numpy as np
from scipy.interpolate import BSpline

from gyronet.analysis.survey.scoring import kept_rows, score_rates, turn_on_bias, with_startup_offset
from gyronet.analysis.survey.sensor_run import History, noise_seed_of
from gyronet.recordings.data import Recording
from gyronet.sim import simulate
from gyronet.sim.sensor import first_order_lag

AXES, FS_HZ, STARTUP_S, KNOT_C = "xyz", 10.0, 600.0, 1.0


def record(history: History, sensor_seed: int):
    """The survey's record of this history and sensor, its noise as the survey draws it (in memory, no CSV)."""
    return simulate(profile=history.profile, seed=history.seed, sensor_seed=sensor_seed, fs_hz=FS_HZ,
                    sensor={"distribution": "survey"}, noise_seed=noise_seed_of(history, sensor_seed))


def terms(sim, axis: int, low_c: float, high_c: float) -> np.ndarray:
    """Axis ``axis``'s spline of its true lagged temperature, and its dT/dt and T * dT/dt terms, shape (n, k)."""
    time_s = sim.truth["time_s"]
    temp_c = first_order_lag(sim.truth["die_temp_c"], FS_HZ, sim.sensor.axis_lag_s[axis])
    knots = np.r_[[low_c] * 3, np.arange(low_c, high_c + KNOT_C, KNOT_C), [high_c + KNOT_C] * 3]
    spline = BSpline.design_matrix(np.clip(temp_c, low_c, high_c), knots, 3).toarray()
    x, rate_c_per_s = (temp_c - 10.0) / 50.0, np.gradient(temp_c, time_s)
    return np.column_stack([spline, rate_c_per_s, x * rate_c_per_s])


def score(sensor_seed: int, penalty: float) -> dict:
    """Fit on the sensor's cycle, score on its random history: residual / floor per axis, as the survey's variants."""
    train, check = record(History("cycle", 1), sensor_seed), record(History("random", 2), sensor_seed)
    gyro = {name: np.column_stack([sim.recording[f"gyro_{a}_dps"] for a in AXES])
            for name, sim in (("train", train), ("check", check))}
    static_dps = np.array([float(v) for v in train.meta["static_rate_dps"].split(",")])
    low_c, high_c = np.floor(train.truth["die_temp_c"].min()), np.ceil(train.truth["die_temp_c"].max())
    plain = gyro["check"].copy()
    for axis in range(3):
        design = terms(train, axis, low_c, high_c)
        n_spline = design.shape[1] - 2
        second = np.diff(np.eye(n_spline), 2, axis=0)
        gram = design.T @ design
        gram[:n_spline, :n_spline] += penalty * len(design) * second.T @ second
        coef = np.linalg.solve(gram, design.T @ (gyro["train"][:, axis] - static_dps[axis]))
        plain[:, axis] -= terms(check, axis, low_c, high_c) @ coef
    recording = Recording(check.recording, check.meta)
    deployed = with_startup_offset(recording, plain, STARTUP_S)
    difference = turn_on_bias(check.truth) - turn_on_bias(train.truth)
    scores = score_rates(recording, check.truth, kept_rows(recording, STARTUP_S), deployed, plain, difference)
    return {"sensor": sensor_seed, **scores}


if __name__ == "__main__":
    first, last = int(sys.argv[1]), int(sys.argv[2])
    penalty = float(sys.argv[3]) if len(sys.argv) > 3 else 1e-2
    rows = []
    for seed in range(first, last):
        rows.append(score(seed, penalty))
        print(json.dumps(rows[-1]), flush=True)
    for variant in ("deployed", "turn_on_removed"):
        worst = np.array([max(r[variant]) for r in rows])
        print(f"{variant}: median {np.median(worst):.3f}, 90th percentile {np.percentile(worst, 90):.3f}, "
              f"worst {worst.max():.3f} (sensor {rows[int(worst.argmax())]['sensor']})")
