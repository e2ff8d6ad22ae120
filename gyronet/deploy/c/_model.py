"""A bundle's model (its TorchScript buffers and parameters) as C constants and the body of ``model_drift``.

Each known class has a reader that turns the module into plain arrays (constants folded: 1/std,
-1/(2 w^2), the output scale in the weights) and a numpy function that computes from those arrays
exactly what the C does, in float64. ``model_code`` checks that function against the module's own
``forward`` on probe inputs inside and outside the trained box: if a model's form changes (a new
term in ``RBFNet.parts``), the export fails in one line instead of writing C that computes
something else.
"""
from __future__ import annotations

from typing import Any, Callable, NamedTuple

import numpy as np

from gyronet.deploy.c import c_array, c_float
from gyronet.errors import BundleError

PROBE_ROWS = 512
CHECK_TOL = 1e-9  # relative to the largest drift on the probe: float64 against float64


class ModelCode(NamedTuple):
    """The C of a model, what it is, and how many numbers it stores."""

    kind: str
    constants: str
    body: str
    n_numbers: int


def _array(module: Any, name: str) -> np.ndarray:
    tensor = module
    for part in name.split("."):
        tensor = getattr(tensor, part)
    return tensor.detach().cpu().double().numpy().copy()


def _softplus(x: np.ndarray) -> np.ndarray:
    # torch's softplus: x itself above its threshold of 20
    return np.where(x > 20.0, x, np.log1p(np.exp(np.minimum(x, 20.0))))


def _rbf(module: Any) -> tuple[dict[str, Any], Callable[[np.ndarray], np.ndarray]]:
    """RBFNet.parts and forward: normalise, clamp to the box, Gaussians, linear, powers of T, de-normalise."""
    y_std, y_mean = _array(module, "y_std"), _array(module, "y_mean")
    widths = _softplus(_array(module, "raw_width")) + float(module.min_width)
    head = _array(module, "head.weight") * y_std[:, None]
    linear = _array(module, "linear.weight") * y_std[:, None]
    poly = _array(module, "poly.weight") * y_std[:, None]
    p = {"mean": _array(module, "x_mean"), "inv_std": 1.0 / _array(module, "x_std"),
         "low": _array(module, "z_low"), "high": _array(module, "z_high"), "clamp": bool(module.clamp),
         "t": int(module.temp_index), "index": [int(i) for i in module.rbf_index.tolist()],
         "centers": _array(module, "centers"), "neg_half_inv_w2": -0.5 / widths ** 2, "head": head,
         "bias": _array(module, "head.bias") * y_std + y_mean,
         "linear": linear if np.any(linear) else None, "poly": poly if np.any(poly) else None,
         "groups": None}
    if hasattr(module, "group_columns") and not bool(module.identity_columns):  # RBFNet.axis_columns
        p["groups"] = _array(module, "group_columns").astype(int).tolist()
        p["axis_group"] = _array(module, "axis_group").astype(int).tolist()

    def reference(x: np.ndarray) -> np.ndarray:
        if p["groups"] is None:
            return one_group(x)
        outputs = [one_group(x[:, columns], columns) for columns in p["groups"]]
        return np.column_stack([outputs[g][:, a] for a, g in enumerate(p["axis_group"])])

    def one_group(x: np.ndarray, columns: list[int] | None = None) -> np.ndarray:
        z = (x - p["mean"]) * p["inv_std"]
        zc = np.clip(z, p["low"], p["high"]) if p["clamp"] else z
        t = p["t"]
        for i in [] if columns is None or not p["clamp"] else range(len(columns)):
            if i != t and columns[i] == columns[t]:  # a lag slot reading the temperature too (RBFNet._inputs)
                z[:, i] += (zc[:, t] - z[:, t]) * p["inv_std"][i] / p["inv_std"][t]
        z[:, t] = zc[:, t]
        r = zc[:, p["index"]]
        phi = np.exp(((r[:, None, :] - p["centers"][None]) ** 2).sum(2) * p["neg_half_inv_w2"])
        y = p["bias"] + phi @ p["head"].T
        if p["linear"] is not None:
            y = y + z @ p["linear"].T
        if p["poly"] is not None:
            temp = zc[:, p["t"]:p["t"] + 1]
            y = y + sum(p["poly"][:, k] * temp ** (k + 2) for k in range(p["poly"].shape[1]))
        return y

    return p, reference


def _rbf_c(p: dict[str, Any], prefix: str = "M_", n_out: int = 3, out: str = "drift") -> tuple[str, str]:
    """Constants and body of ``p``'s forward into ``out[0..n_out)``, its constants named ``prefix*``
    (the error bar's members network is one more RBFNet, ``gyronet.deploy.c._error_bar``)."""
    if p["groups"] is None:
        return _rbf_group_c(p, prefix, n_out, out)
    # per-axis inputs (RBFNet.axis_columns): the network once per group on its columns, each axis its group's
    n_in, n_g, m = len(p["mean"]), len(p["groups"]), prefix
    constants, body = _rbf_group_c(p, prefix, n_out, "y_g")
    constants += (f"\nstatic const unsigned char {m}GROUP_COLUMNS[{n_g}][{n_in}] = "
                  f"{{{', '.join('{' + ', '.join(map(str, g)) + '}' for g in p['groups'])}}};"
                  f"\nstatic const unsigned char {m}AXIS_GROUP[{n_out}] = {{{', '.join(map(str, p['axis_group']))}}};")
    body = body.replace("(x[i] - ", "(x_g[i] - ")
    if p["clamp"]:  # a lag slot reading the temperature too moves with it to the edge (RBFNet._inputs)
        t, marker = p["t"], "    /* the linear term sees temperature clamped"
        body = body.replace(marker, f"    for (i = 0; i < {n_in}; ++i) {{\n        if (i != {t} && {m}GROUP_COLUMNS[g][i] == "
                            f"{m}GROUP_COLUMNS[g][{t}]) z[i] += (zc[{t}] - z[{t}]) * {m}INV_STD[i] / {m}INV_STD[{t}];"
                            f"\n    }}\n{marker}", 1)
    wrapped = ["    {", "        int g, i_g, a_g;", f"        for (g = 0; g < {n_g}; ++g) {{",
               f"            float x_g[{n_in}], y_g[{n_out}];", f"            for (i_g = 0; i_g < {n_in}; ++i_g) {{",
               f"                x_g[i_g] = x[{m}GROUP_COLUMNS[g][i_g]];", "            }", "            {",
               *["        " + line for line in body.split("\n")], "            }",
               f"            for (a_g = 0; a_g < {n_out}; ++a_g) {{",
               f"                if ({m}AXIS_GROUP[a_g] == g) {out}[a_g] = y_g[a_g];", "            }", "        }", "    }"]
    return constants, "\n".join(wrapped)


def head_spans(head: np.ndarray) -> tuple[np.ndarray, list[int], list[int]]:
    """The output weights (rows, centres) as each row's span from its first to its last nonzero weight, end to end:
    the weights, each row's first centre, and where each row starts in the weights (rows + 1 offsets).

    The error bar's members sit side by side, each reading only its own start's Gaussians: stored
    dense, two thirds of their weights were zeros (1.6 KB of a 9.7 KB object). The C sums only the
    spans, in the order of the centres, so it skips zero terms only: the same drift to the last bit.
    """
    first, at, parts = [], [0], []
    for row in head:
        nonzero = np.flatnonzero(row)
        lo, hi = (int(nonzero[0]), int(nonzero[-1]) + 1) if len(nonzero) else (0, 0)
        first.append(lo)
        at.append(at[-1] + hi - lo)
        parts.append(row[lo:hi])
    return np.concatenate([*parts, np.zeros(0)]), first, at


def _rbf_group_c(p: dict[str, Any], prefix: str, n_out: int, out: str) -> tuple[str, str]:
    n_in, (n_c, n_r) = len(p["mean"]), p["centers"].shape
    m = prefix
    weights, first, at = head_spans(p["head"])
    constants = [f"static const float {m}MEAN[{n_in}] = {c_array(p['mean'])};",
                 f"static const float {m}INV_STD[{n_in}] = {c_array(p['inv_std'])};",
                 f"static const unsigned char {m}RBF_INDEX[{n_r}] = {{{', '.join(map(str, p['index']))}}};",
                 f"static const float {m}CENTERS[{n_c}][{n_r}] = {c_array(p['centers'])};",
                 f"static const float {m}NEG_HALF_INV_W2[{n_c}] = {c_array(p['neg_half_inv_w2'])};",
                 f"static const float {m}HEAD[{max(len(weights), 1)}] = {c_array(weights)};",
                 f"static const unsigned short {m}HEAD_FROM[{n_out}] = {{{', '.join(map(str, first))}}};",
                 f"static const unsigned short {m}HEAD_AT[{n_out + 1}] = {{{', '.join(map(str, at))}}};",
                 f"static const float {m}BIAS[{n_out}] = {c_array(p['bias'])};"]
    body = [f"    float z[{n_in}], zc[{n_in}], r, sq, phi[{n_c}];", "    int i, j, k, a;",
            f"    for (i = 0; i < {n_in}; ++i) {{", f"        z[i] = (x[i] - {m}MEAN[i]) * {m}INV_STD[i];"]
    if p["clamp"]:
        constants += [f"static const float {m}Z_LOW[{n_in}] = {c_array(p['low'])};",
                      f"static const float {m}Z_HIGH[{n_in}] = {c_array(p['high'])};"]
        body += [f"        zc[i] = clampf(z[i], {m}Z_LOW[i], {m}Z_HIGH[i]);", "    }",
                 "    /* the linear term sees temperature clamped, the other inputs as they are */",
                 f"    z[{p['t']}] = zc[{p['t']}];"]
    else:
        body += ["        zc[i] = z[i];", "    }"]
    body += [f"    for (a = 0; a < {n_out}; ++a) {{", f"        {out}[a] = {m}BIAS[a];", "    }",
             "    /* phi_k = exp(-|r - c_k|^2 / (2 w_k^2)) */",
             f"    for (k = 0; k < {n_c}; ++k) {{", "        sq = 0.0f;",
             f"        for (j = 0; j < {n_r}; ++j) {{", f"            r = zc[{m}RBF_INDEX[j]] - {m}CENTERS[k][j];",
             "            sq += r * r;", "        }", f"        phi[k] = expf(sq * {m}NEG_HALF_INV_W2[k]);", "    }",
             "    /* each output's weights over its span of Gaussians, in the order of k */",
             f"    for (a = 0; a < {n_out}; ++a) {{", f"        for (k = {m}HEAD_AT[a]; k < {m}HEAD_AT[a + 1]; ++k) {{",
             f"            {out}[a] += {m}HEAD[k] * phi[{m}HEAD_FROM[a] + k - {m}HEAD_AT[a]];", "        }", "    }"]
    if p["linear"] is not None:
        constants.append(f"static const float {m}LINEAR[{n_out}][{n_in}] = {c_array(p['linear'])};")
        body += [f"    for (a = 0; a < {n_out}; ++a) {{", f"        for (i = 0; i < {n_in}; ++i) {{",
                 f"            {out}[a] += {m}LINEAR[a][i] * z[i];", "        }", "    }"]
    if p["poly"] is not None:
        n_p = p["poly"].shape[1]
        constants.append(f"static const float {m}POLY[{n_out}][{n_p}] = {c_array(p['poly'])};")
        body += ["    /* powers 2..degree of the clamped, normalised temperature */",
                 "    {", f"        float t = zc[{p['t']}], power = t;", f"        for (k = 0; k < {n_p}; ++k) {{",
                 "            power *= t;", f"            for (a = 0; a < {n_out}; ++a) {{",
                 f"                {out}[a] += {m}POLY[a][k] * power;", "            }", "        }", "    }"]
    return "\n".join(constants), "\n".join(body)


def _poly(module: Any) -> tuple[dict[str, Any], Callable[[np.ndarray], np.ndarray]]:
    """TempPolynomial: a polynomial in the clamped temperature minus T_ref."""
    p = {"coef": _array(module, "coef"), "t": int(module.temp_index), "ref": float(_array(module, "temp_ref_c")),
         "min": float(_array(module, "temp_min_c")), "max": float(_array(module, "temp_max_c"))}

    def reference(x: np.ndarray) -> np.ndarray:
        temp = np.clip(x[:, p["t"]], p["min"], p["max"]) - p["ref"]
        return sum(np.outer(temp ** k, p["coef"][k]) for k in range(len(p["coef"])))

    return p, reference


def _poly_c(p: dict[str, Any]) -> tuple[str, str]:
    n = len(p["coef"])
    constants = f"static const float M_COEF[{n}][3] = {c_array(p['coef'])};"
    body = [f"    float t = clampf(x[{p['t']}], {c_float(p['min'])}, {c_float(p['max'])}) - {c_float(p['ref'])};",
            "    float power = 1.0f;", "    int k, a;", "    for (a = 0; a < 3; ++a) {",
            "        drift[a] = M_COEF[0][a];", "    }", f"    for (k = 1; k < {n}; ++k) {{", "        power *= t;",
            "        for (a = 0; a < 3; ++a) {", "            drift[a] += M_COEF[k][a] * power;", "        }", "    }"]
    return constants, "\n".join(body)


def _lsq(module: Any) -> tuple[dict[str, Any], Callable[[np.ndarray], np.ndarray]]:
    """LinearFeatures: (x - mean) W + b."""
    p = {"weight": _array(module, "weight"), "bias": _array(module, "bias"), "mean": _array(module, "x_mean")}
    return p, lambda x: (x - p["mean"]) @ p["weight"] + p["bias"]


def _lsq_c(p: dict[str, Any]) -> tuple[str, str]:
    n = len(p["mean"])
    constants = "\n".join([f"static const float M_MEAN[{n}] = {c_array(p['mean'])};",
                           f"static const float M_WEIGHT[{n}][3] = {c_array(p['weight'])};",
                           f"static const float M_BIAS[3] = {c_array(p['bias'])};"])
    body = ["    int i, a;", "    for (a = 0; a < 3; ++a) {", "        drift[a] = M_BIAS[a];",
            f"        for (i = 0; i < {n}; ++i) {{", "            drift[a] += (x[i] - M_MEAN[i]) * M_WEIGHT[i][a];",
            "        }", "    }"]
    return constants, "\n".join(body)


KNOWN = {"RBFNet": (_rbf, _rbf_c), "TempPolynomial": (_poly, _poly_c), "LinearFeatures": (_lsq, _lsq_c),
         "Px4Cubic": (_poly, _poly_c), "Px4Onboard": (_poly, _poly_c)}  # PX4's two: a TempPolynomial fitted its way


def model_code(module: Any, x_scale: np.ndarray, x_centre: np.ndarray, source: str) -> ModelCode:
    """The C of ``module`` (a non-frozen TorchScript module), checked against its forward.

    ``x_centre`` and ``x_scale`` (per feature) place the probe inputs: centre +- 3 scales, beyond
    the trained box, so the clamps are checked too.
    """
    import torch

    kind = str(module.original_name)
    if kind not in KNOWN:
        raise BundleError(f"{source}: a {kind} model, which the C export does not know (it knows "
                          f"{', '.join(KNOWN)})")
    read, to_c = KNOWN[kind]
    params, reference = read(module)
    rng = np.random.default_rng(0)
    x = x_centre + x_scale * rng.uniform(-3.0, 3.0, (PROBE_ROWS, len(x_centre)))
    with torch.no_grad():
        expected = module(torch.from_numpy(x)).double().numpy()
    ours = reference(x.copy())
    error = float(np.max(np.abs(ours - expected)))
    if not error <= CHECK_TOL * max(1.0, float(np.max(np.abs(expected)))):
        raise BundleError(f"{source}: its {kind} computes something the C export does not (max difference "
                          f"{error:.3g} deg/s on probe inputs): the model's form changed; update "
                          "gyronet/deploy/c/_model.py")
    constants, body = to_c(params)
    n_numbers = sum(np.size(v) for v in params.values() if isinstance(v, np.ndarray))
    return ModelCode(kind, constants, body, int(n_numbers))
