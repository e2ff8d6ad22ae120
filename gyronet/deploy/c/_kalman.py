"""The bundle's Kalman stage as C: per axis ``x = F x; x += K (z - H x); y = C x + D z``.

The gain does not depend on the data. For the first samples, until it agrees with the steady gain
(the one ``gyronet.model.kalman.KalmanStage`` freezes when it switches to its LTI form) within
``GAIN_TOL``, the C propagates the covariance as filterpy does (``P = F P F^T + Q``, Joseph-form
update), per axis since the axes are independent blocks; from then on it uses the steady gain,
computed here in float64. The recursion forgets its roundings, so float32 serves (the tests
compare the whole output, transient included), and a long transient (a narrow bandwidth, a high
rate) costs no flash.
"""
from __future__ import annotations

from typing import Any, Mapping, NamedTuple

import numpy as np

from gyronet.deploy.c import c_array, c_float
from gyronet.errors import BundleError

GAIN_TOL = 1e-9  # a gain this close to the steady one changes the output by < 1e-9 x the innovation
MAX_TRANSIENT_SAMPLES = 10_000_000


class KalmanCode(NamedTuple):
    """The C of a Kalman stage (or a copy when there is none) and its state size."""

    constants: str
    body: str
    n_states: int
    n_covariance: int  # floats of covariance (the per-axis blocks)
    n_transient: int  # samples that propagate the covariance before the steady gain


def no_kalman() -> KalmanCode:
    """The output stage of a bundle without a Kalman stage: the compensated rate as it is (in ``gyronet_step``)."""
    return KalmanCode("", "", 1, 1, 0)


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


def _blocks(stage: Any, name: str) -> list[np.ndarray]:
    """The per-axis diagonal blocks of one of the stage's filterpy matrices (at reset)."""
    matrix = getattr(stage.kf, name)
    return [matrix[s, s] for s in stage._slices]


def kalman_code(kalman: Mapping[str, Any]) -> KalmanCode:
    """C constants and body for the ``kalman.json`` content ``kalman``."""
    from gyronet.model.kalman import KalmanStage

    stage = KalmanStage.from_dict(kalman)
    gains, steady = gain_sequence(stage)
    far = [k for k, gain in enumerate(gains) if np.max(np.abs(gain - steady)) > GAIN_TOL]
    n_transient = far[-1] + 1 if far else 1  # (at least 1: `kalman_n < 0` would be a warning)
    blocks = stage._blocks
    dims = [len(b["F"]) for b in blocks]
    offsets = np.cumsum([0, *dims[:-1]]).tolist()
    p_offsets = np.cumsum([0, *[d * d for d in dims[:-1]]]).tolist()
    n_x, n_p, m = sum(dims), sum(d * d for d in dims), max(dims)

    def flat(matrices) -> str:
        return c_array(np.concatenate([np.asarray(a, dtype=np.float64).ravel() for a in matrices]))

    r_dps2 = [float(stage.kf.R[i, i]) for i in range(len(blocks))]
    constants = "\n".join([
        f"static const unsigned char K_DIM[3] = {{{', '.join(map(str, dims))}}};",
        f"static const unsigned char K_OFFSET[3] = {{{', '.join(map(str, offsets))}}};",
        f"static const unsigned char K_P_OFFSET[3] = {{{', '.join(map(str, p_offsets))}}};",
        f"static const float K_F[{n_p}] = {flat(b['F'] for b in blocks)};",
        f"static const float K_Q[{n_p}] = {flat(_blocks(stage, 'Q'))};",
        f"static const float K_P0[{n_p}] = {flat(_blocks(stage, 'P'))};",
        f"static const float K_H[{n_x}] = {flat(b['H'] for b in blocks)};",
        f"static const float K_R[3] = {c_array(r_dps2)};",
        f"static const float K_C[{n_x}] = {flat(b['C'] for b in blocks)};",
        f"static const float K_D[3] = {{{', '.join(c_float(b['D']) for b in blocks)}}};",
        f"#define K_N_TRANSIENT {n_transient}ul",
        f"static const float K_GAIN_STEADY[{n_x}] = {c_array(steady)};"])
    body = f"""    float predicted[{m}], gain[{m}], a_p[{m * m}], innovation, y, r, *x, *p;
    const float *f, *h;
    int a, i, j, l, n, transient = s->kalman_n < K_N_TRANSIENT;
    if (s->kalman_n == 0) {{
        memcpy(s->kalman_p, K_P0, sizeof K_P0);
    }}
    for (a = 0; a < 3; ++a) {{
        n = K_DIM[a];
        x = s->kalman_x + K_OFFSET[a];
        p = s->kalman_p + K_P_OFFSET[a];
        f = K_F + K_P_OFFSET[a];
        h = K_H + K_OFFSET[a];
        /* x = F x */
        for (i = 0; i < n; ++i) {{
            predicted[i] = 0.0f;
            for (j = 0; j < n; ++j) {{
                predicted[i] += f[i * n + j] * x[j];
            }}
        }}
        if (transient) {{
            /* P = F P F^T + Q */
            for (i = 0; i < n * n; ++i) {{
                a_p[i] = 0.0f;
                for (l = 0; l < n; ++l) {{
                    a_p[i] += f[(i / n) * n + l] * p[l * n + i % n];
                }}
            }}
            for (i = 0; i < n * n; ++i) {{
                p[i] = K_Q[K_P_OFFSET[a] + i];
                for (l = 0; l < n; ++l) {{
                    p[i] += a_p[(i / n) * n + l] * f[(i % n) * n + l];
                }}
            }}
            /* K = P H^T (H P H^T + R)^-1 */
            r = K_R[a];
            for (i = 0; i < n; ++i) {{
                gain[i] = 0.0f;
                for (j = 0; j < n; ++j) {{
                    gain[i] += p[i * n + j] * h[j];
                }}
                r += h[i] * gain[i];
            }}
            r = 1.0f / r;
            for (i = 0; i < n; ++i) {{
                gain[i] *= r;
            }}
            /* P = (I - K H) P (I - K H)^T + K R K^T */
            for (i = 0; i < n * n; ++i) {{
                a_p[i] = 0.0f;
                for (l = 0; l < n; ++l) {{
                    a_p[i] += ((float)(i / n == l) - gain[i / n] * h[l]) * p[l * n + i % n];
                }}
            }}
            for (i = 0; i < n * n; ++i) {{
                p[i] = 0.0f;
                for (l = 0; l < n; ++l) {{
                    p[i] += a_p[(i / n) * n + l] * ((float)(i % n == l) - gain[i % n] * h[l]);
                }}
                p[i] += gain[i / n] * K_R[a] * gain[i % n];
            }}
        }} else {{
            for (i = 0; i < n; ++i) {{
                gain[i] = K_GAIN_STEADY[K_OFFSET[a] + i];
            }}
        }}
        /* x = x + K (z - H x); y = C x + D z */
        innovation = rate_dps[a];
        for (i = 0; i < n; ++i) {{
            innovation -= h[i] * predicted[i];
        }}
        y = K_D[a] * rate_dps[a];
        for (i = 0; i < n; ++i) {{
            x[i] = predicted[i] + gain[i] * innovation;
            y += K_C[K_OFFSET[a] + i] * x[i];
        }}
        out_dps[a] = y;
    }}
    s->kalman_n += (uint32_t)transient;"""
    return KalmanCode(constants, body, n_x, n_p, n_transient)
