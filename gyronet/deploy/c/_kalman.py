"""The bundle's Kalman stage as C: per axis ``x = F x; x += K (z - H x); y = C x + D z``.

The gain sequence does not depend on the data, so it is computed here, in float64, by the same
``gyronet.kalman.KalmanStage`` that ``Compensator`` runs: the C holds the gains of the first
samples until they agree with the steady gain (the one the stage freezes when it switches to its
LTI form) within ``GAIN_TOL``, then the steady gain. No covariance is propagated on the target,
so float32 cannot make the Riccati recursion drift.
"""
from __future__ import annotations

from typing import Any, Mapping, NamedTuple

import numpy as np

from gyronet.deploy.c import c_array, c_float
from gyronet.errors import BundleError

GAIN_TOL = 1e-9  # a gain this close to the steady one changes the output by < 1e-9 x the innovation
MAX_GAIN_ROWS = 4096
MAX_TRANSIENT_SAMPLES = 1_000_000


class KalmanCode(NamedTuple):
    """The C of a Kalman stage (or a copy when there is none) and its state size."""

    constants: str
    body: str
    n_states: int
    n_gain_rows: int


def no_kalman() -> KalmanCode:
    """The output stage of a bundle without a Kalman stage: the compensated rate as it is."""
    body = "    (void)s;\n    memcpy(out_dps, rate_dps, 3 * sizeof *out_dps);"
    return KalmanCode("", body, 1, 0)


def gain_sequence(stage: Any) -> tuple[list[np.ndarray], np.ndarray]:
    """Per-sample gains (each (n_states,), the axes side by side) until the stage's switch, and the steady gain."""
    stage.reset()
    zeros = np.zeros((1, len(stage._blocks)))
    gains = []
    while not stage.steady:
        if len(gains) >= MAX_TRANSIENT_SAMPLES:
            raise BundleError(f"kalman.json: the gain has not settled after {MAX_TRANSIENT_SAMPLES} samples")
        stage.process(zeros)
        gains.append(np.concatenate([stage.kf.K[s, i] for i, s in enumerate(stage._slices)]))
    stage.reset()
    return gains, gains[-1]


def kalman_code(kalman: Mapping[str, Any], source: str) -> KalmanCode:
    """C constants and body for the ``kalman.json`` content ``kalman``."""
    from gyronet.kalman import KalmanStage

    stage = KalmanStage.from_dict(kalman)
    gains, steady = gain_sequence(stage)
    far = [k for k, gain in enumerate(gains) if np.max(np.abs(gain - steady)) > GAIN_TOL]
    n_rows = max(far[-1] + 1 if far else 0, 1)
    if n_rows > MAX_GAIN_ROWS:
        raise BundleError(f"{source}: its gain takes {n_rows} samples to settle, more than the {MAX_GAIN_ROWS} "
                          "rows the C export stores")
    blocks = stage._blocks
    dims = [len(b["F"]) for b in blocks]
    offsets = np.cumsum([0, *dims[:-1]]).tolist()
    f_offsets = np.cumsum([0, *[d * d for d in dims[:-1]]]).tolist()
    n_x = sum(dims)
    constants = "\n".join([
        f"static const unsigned char K_DIM[3] = {{{', '.join(map(str, dims))}}};",
        f"static const unsigned char K_OFFSET[3] = {{{', '.join(map(str, offsets))}}};",
        f"static const unsigned char K_F_OFFSET[3] = {{{', '.join(map(str, f_offsets))}}};",
        f"static const float K_F[{sum(d * d for d in dims)}] = {c_array(np.concatenate([b['F'].ravel() for b in blocks]))};",
        f"static const float K_H[{n_x}] = {c_array(np.concatenate([b['H'] for b in blocks]))};",
        f"static const float K_C[{n_x}] = {c_array(np.concatenate([b['C'] for b in blocks]))};",
        f"static const float K_D[3] = {{{', '.join(c_float(b['D']) for b in blocks)}}};",
        f"#define K_N_GAINS {n_rows}u",
        f"static const float K_GAIN[K_N_GAINS][{n_x}] = {c_array(np.array(gains[:n_rows]))};",
        f"static const float K_GAIN_STEADY[{n_x}] = {c_array(steady)};"])
    body = f"""    const float *gain = s->kalman_n < K_N_GAINS ? K_GAIN[s->kalman_n] : K_GAIN_STEADY;
    float predicted[{max(dims)}], innovation, y, *x;
    const float *f;
    int a, i, j, n;
    if (s->kalman_n < K_N_GAINS) {{
        s->kalman_n += 1;
    }}
    for (a = 0; a < 3; ++a) {{
        n = K_DIM[a];
        x = s->kalman_x + K_OFFSET[a];
        f = K_F + K_F_OFFSET[a];
        /* x = F x; innovation = z - H x */
        innovation = rate_dps[a];
        for (i = 0; i < n; ++i) {{
            predicted[i] = 0.0f;
            for (j = 0; j < n; ++j) {{
                predicted[i] += f[i * n + j] * x[j];
            }}
            innovation -= K_H[K_OFFSET[a] + i] * predicted[i];
        }}
        /* x = x + K innovation; y = C x + D z */
        y = K_D[a] * rate_dps[a];
        for (i = 0; i < n; ++i) {{
            x[i] = predicted[i] + gain[K_OFFSET[a] + i] * innovation;
            y += K_C[K_OFFSET[a] + i] * x[i];
        }}
        out_dps[a] = y;
    }}"""
    return KalmanCode(constants, body, n_x, n_rows)
