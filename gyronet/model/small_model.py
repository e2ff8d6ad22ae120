"""The bundle's model in plain floats for a chunk of a few rows: a live frame without TorchScript's per-op cost.

At 1 kHz frames arrive one at a time, and one TorchScript call on one row costs about 30 ops of
interpreter overhead (~80 us on the project VM) for a few hundred flops. The same forward, written
row by row in Python floats from the parameters of the bundle's own ``model.pt``, costs a fraction
of that (NumPy on one row is slower still: ~20 calls of ~1 us). It is used only for chunks of at
most ``SMALL_ROWS`` rows, and only when the caller asks (``Compensator.use_small_chunks``: the live
path does, ``compensate.py`` does not, so offline output stays TorchScript's to the bit); it
equals TorchScript to rounding (a test checks 1e-12 for every model kind). A model class it does
not know keeps TorchScript for every chunk.
"""
from __future__ import annotations

import math
from operator import mul
from typing import Callable

import numpy as np
import torch

SMALL_ROWS = 8  # chunks up to this many rows go row by row in floats (past it one TorchScript call is cheaper)

RowModel = Callable[[list], list]  # one row of features -> drift per axis, deg/s


def row_model(module: torch.nn.Module) -> RowModel | None:
    """``module``'s forward on one row of plain floats (features -> drift per axis, deg/s), or None.

    ``module`` is the unfrozen TorchScript model (``gyronet.bundle.io.load_unfrozen``) or the eager
    ``nn.Module``; None for a class not known here, or a frozen model (its parameters are folded away).
    """
    name = str(getattr(module, "original_name", type(module).__name__))
    try:
        state = {key: value.detach().cpu().to(torch.float64).numpy().copy()
                 for key, value in module.state_dict().items()}
        if name == "RBFNet":
            return _rbf(module, state)
        if name in ("TempPolynomial", "Px4Cubic", "Px4Onboard"):
            return _polynomial(module, state)
        if name == "LinearFeatures":
            return _linear(state)
    except (AttributeError, KeyError, RuntimeError):  # not the layout this module knows: TorchScript it is
        return None
    return None


def _rbf(module: torch.nn.Module, state: dict[str, np.ndarray]) -> RowModel:
    """``RBFNet.forward`` (gyronet.model.rbf), to rounding: its three output layers summed as one."""
    mean, std, low, high = (state[k].tolist() for k in ("x_mean", "x_std", "z_low", "z_high"))
    y_mean, y_std = state["y_mean"].tolist(), state["y_std"].tolist()
    rbf_index, centers = state["rbf_index"].astype(int).tolist(), state["centers"].tolist()
    # the widths as torch computes them: softplus(raw) + min, squared
    with torch.no_grad():
        width_sq = ((torch.nn.functional.softplus(torch.from_numpy(state["raw_width"]))
                     + float(module.min_width)) ** 2).tolist()
    head, head_bias = state["head.weight"].tolist(), state["head.bias"].tolist()
    linear, poly = state["linear.weight"].tolist(), state["poly.weight"].tolist()
    clamp, temp, degree = bool(module.clamp), int(module.temp_index), int(module.temp_degree)
    exponents = list(range(2, max(degree, 2) + 1))
    # per axis: the head, linear and polynomial weights side by side (one sum per axis, not three)
    outputs = [(h + lin + p, b, s, m) for h, b, lin, p, s, m in zip(head, head_bias, linear, poly, y_std, y_mean)]
    units = list(zip(centers, width_sq))
    single = len(rbf_index) == 1
    units_1 = [(center[0], w_sq) for center, w_sq in units] if single else []
    exp = math.exp

    def forward_all(x: list) -> list:
        z = [(v - m) / s for v, m, s in zip(x, mean, std)]
        zc = [min(max(v, lo), hi) for v, lo, hi in zip(z, low, high)] if clamp else z
        if clamp:
            z[temp] = zc[temp]
        r = [zc[i] for i in rbf_index]
        # phi_k = exp(-|r - c_k|^2 / (2 w_k^2))
        if single:  # one Gaussian input (the default model): no sum over inputs
            phi = [exp((r[0] - c) ** 2 * -0.5 / w_sq) for c, w_sq in units_1]
        else:
            phi = [exp(sum([(a - c) ** 2 for a, c in zip(r, center)]) * -0.5 / w_sq) for center, w_sq in units]
        basis = phi + z + [zc[temp] ** k for k in exponents]
        return [(sum(map(mul, basis, weights)) + b) * s + m for weights, b, s, m in outputs]

    if "group_columns" not in state or module.identity_columns:
        return forward_all
    # per-axis inputs (RBFNet.axis_columns): each group's slots read their columns, each axis its group's output
    groups = state["group_columns"].astype(int).tolist()
    axis_group = state["axis_group"].astype(int).tolist()

    def forward(x: list) -> list:
        outputs = [forward_all([x[c] for c in columns]) for columns in groups]
        return [outputs[g][a] for a, g in enumerate(axis_group)]

    return forward


def _polynomial(module: torch.nn.Module, state: dict[str, np.ndarray]) -> RowModel:
    """``TempPolynomial.forward`` (gyronet.model.baselines; PX4's cubics share it)."""
    coef = state["coef"].T.tolist()  # per axis, lowest power first
    ref, low, high = (float(state[k]) for k in ("temp_ref_c", "temp_min_c", "temp_max_c"))
    temp, exponents = int(module.temp_index), list(range(int(module.degree) + 1))

    def forward(x: list) -> list:
        t = min(max(x[temp], low), high) - ref
        powers = [t ** k for k in exponents]
        return [sum(map(mul, powers, c)) for c in coef]

    return forward


def _linear(state: dict[str, np.ndarray]) -> RowModel:
    """``LinearFeatures.forward`` (gyronet.model.baselines)."""
    weight, bias, mean = state["weight"].T.tolist(), state["bias"].tolist(), state["x_mean"].tolist()

    def forward(x: list) -> list:
        centred = [v - m for v, m in zip(x, mean)]
        return [sum(map(mul, centred, w)) + b for w, b in zip(weight, bias)]

    return forward
