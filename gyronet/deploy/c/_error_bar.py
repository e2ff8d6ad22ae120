"""A bundle's error bar (``gyronet.model.error_bar``) as C constants and the body of ``drift_sigma``.

The members network is one more RBFNet (``_model._rbf_c`` with its own prefix and ``3 n_members``
outputs); the spread, the box term and the floor follow ``ErrorBar.sigma``. The generated C is
checked against ``ErrorBar.sigma`` on probe inputs inside and outside the box, as the model is.
"""
from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np

from gyronet.deploy.c import c_array
from gyronet.errors import BundleError

CHECK_TOL = 1e-9  # relative to the largest sigma on the probe: float64 against float64


class ErrorBarCode(NamedTuple):
    """The C of an error bar: constants, the members function's body (or ""), ``drift_sigma``'s body."""

    constants: str
    members_body: str
    body: str
    n_numbers: int


def _reference(bar: Any, params: dict[str, Any] | None, members_ref, x: np.ndarray) -> np.ndarray:
    """What the C computes, in float64 numpy."""
    var = np.tile(bar.floor_dps ** 2, (len(x), 1))
    if params is not None:
        out = members_ref(x.copy()).reshape(len(x), bar.n_members, 3)
        var = var + bar.spread_scale ** 2 * out.var(axis=1)
    z = (x - bar.box_mean) / bar.box_std
    below, above = np.maximum(bar.box_low - z, 0.0), np.maximum(z - bar.box_high, 0.0)
    var = var + below ** 2 @ (bar.slope_low_dps ** 2).T + above ** 2 @ (bar.slope_high_dps ** 2).T
    return np.sqrt(var)


def error_bar_code(bar: Any, n_features: int, source: str) -> ErrorBarCode:
    """The C of ``bar`` (an ``ErrorBar``, or None: every sigma NaN), checked against ``bar.sigma``."""
    if bar is None:
        return ErrorBarCode("", "", "    int a;\n    (void)x;\n    for (a = 0; a < 3; ++a) {\n"
                                    "        sigma[a] = NAN; /* the bundle has no error bar */\n    }", 0)
    from gyronet.deploy.c._model import _rbf, _rbf_c

    params = members_ref = None
    constants = [f"static const float E_FLOOR2[3] = {c_array(bar.floor_dps ** 2)};",
                 f"static const float E_BOX_MEAN[{n_features}] = {c_array(bar.box_mean)};",
                 f"static const float E_BOX_INV_STD[{n_features}] = {c_array(1.0 / bar.box_std)};",
                 f"static const float E_BOX_LOW[{n_features}] = {c_array(bar.box_low)};",
                 f"static const float E_BOX_HIGH[{n_features}] = {c_array(bar.box_high)};",
                 f"static const float E_SLOPE_LOW2[3][{n_features}] = {c_array(bar.slope_low_dps ** 2)};",
                 f"static const float E_SLOPE_HIGH2[3][{n_features}] = {c_array(bar.slope_high_dps ** 2)};"]
    members_body = ""
    body = ["    float var[3], z, d;", "    int a, f;"]
    if bar.members is not None:
        params, members_ref = _rbf(bar.members)
        m = bar.n_members
        member_constants, members_body = _rbf_c(params, prefix="E_M_", n_out=3 * m, out="members")
        constants += [member_constants, f"static const float E_SCALE2[3] = {c_array(bar.spread_scale ** 2)};"]
        body += ["    {", f"        float members[{3 * m}], mean, sq;", "        int k;",
                 "        members_drift(x, members);",
                 "        /* the members' variance per axis (their drift side by side: member k's axis a at 3 k + a) */",
                 "        for (a = 0; a < 3; ++a) {", "            mean = 0.0f;",
                 f"            for (k = 0; k < {m}; ++k) {{", "                mean += members[3 * k + a];", "            }",
                 f"            mean /= {m}.0f;", "            sq = 0.0f;",
                 f"            for (k = 0; k < {m}; ++k) {{", "                d = members[3 * k + a] - mean;",
                 "                sq += d * d;", "            }",
                 f"            var[a] = E_FLOOR2[a] + E_SCALE2[a] * (sq / {m}.0f);", "        }", "    }"]
    else:
        body += ["    for (a = 0; a < 3; ++a) {", "        var[a] = E_FLOOR2[a];", "    }"]
    body += ["    /* outside the trained box: the drift's slope at that edge times the distance */",
             f"    for (f = 0; f < {n_features}; ++f) {{", "        z = (x[f] - E_BOX_MEAN[f]) * E_BOX_INV_STD[f];",
             "        if (z < E_BOX_LOW[f]) {", "            d = E_BOX_LOW[f] - z;",
             "            for (a = 0; a < 3; ++a) {", "                var[a] += E_SLOPE_LOW2[a][f] * d * d;", "            }",
             "        } else if (z > E_BOX_HIGH[f]) {", "            d = z - E_BOX_HIGH[f];",
             "            for (a = 0; a < 3; ++a) {", "                var[a] += E_SLOPE_HIGH2[a][f] * d * d;", "            }",
             "        }", "    }", "    for (a = 0; a < 3; ++a) {", "        sigma[a] = sqrtf(var[a]);", "    }"]
    rng = np.random.default_rng(1)
    x = bar.box_mean + bar.box_std * rng.uniform(-3.0, 3.0, (512, n_features))
    expected = bar.sigma(x)
    ours = _reference(bar, params, members_ref, x)
    error = float(np.max(np.abs(ours - expected)))
    if not error <= CHECK_TOL * max(1.0, float(np.max(np.abs(expected)))):
        raise BundleError(f"{source}: its error bar computes something the C export does not (max difference "
                          f"{error:.3g} deg/s on probe inputs); update gyronet/deploy/c/_error_bar.py")
    n_numbers = 3 + 4 * n_features + 6 * n_features + (0 if params is None else 3 + sum(
        np.size(v) for v in params.values() if isinstance(v, np.ndarray)))
    return ErrorBarCode("\n".join(constants), members_body, "\n".join(body), int(n_numbers))


__all__ = ["ErrorBarCode", "error_bar_code"]
