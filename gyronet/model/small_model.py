"""The bundle's model on one row, for chunks of a few rows: a live frame without TorchScript's per-op cost.

At 1 kHz frames arrive one at a time, and one TorchScript call on one row costs about 30 ops of
interpreter overhead (~80 us on the project VM) for a few hundred flops. The same forward, written
for one row from the parameters of the bundle's own ``model.pt``, costs a fraction of that: in
Python floats for the polynomials and the linear model, in six NumPy calls (~1 us each) for an RBF
network, whose Gaussians cost ~0.4 us each in floats. It is used only for chunks of at
most ``SMALL_ROWS`` rows, and only when the caller asks (``Compensator.use_small_chunks``: the live
path does, ``compensate.py`` does not, so offline output stays TorchScript's to the bit); it
equals TorchScript to rounding (a test checks 1e-12 for every model kind). A model class it does
not know keeps TorchScript for every chunk.
"""
from __future__ import annotations

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
    """``RBFNet.forward`` (gyronet.model.rbf), to rounding: its three output layers as one matrix.

    The error bar's members (three networks side by side, 60 Gaussians) cost 8 us so, 25 us in floats.
    """
    mean, std, low, high = (state[k] for k in ("x_mean", "x_std", "z_low", "z_high"))
    rbf_index, centers = state["rbf_index"].astype(int), state["centers"]
    # the widths as torch computes them: softplus(raw) + min, squared
    with torch.no_grad():
        width_sq = ((torch.nn.functional.softplus(torch.from_numpy(state["raw_width"]))
                     + float(module.min_width)) ** 2).numpy()
    scale = -0.5 / width_sq  # phi_k = exp(|r - c_k|^2 * scale_k)
    # (head | linear | poly) on (phi | z | powers), scaled to deg/s: one product per row
    weights = np.hstack([state["head.weight"], state["linear.weight"], state["poly.weight"]]) * state["y_std"][:, None]
    offset = state["head.bias"] * state["y_std"] + state["y_mean"]
    clamp, temp, degree = bool(module.clamp), int(module.temp_index), int(module.temp_degree)
    exponents = np.arange(2, max(degree, 2) + 1, dtype=np.float64)
    single = len(rbf_index) == 1
    gaussian_input, centers_1 = int(rbf_index[0]), centers[:, 0].copy()

    def forward_all(x: list, copies: np.ndarray | None = None) -> list:
        z = (np.array(x) - mean) / std
        zc = np.minimum(np.maximum(z, low), high) if clamp else z
        if clamp and copies is not None and len(copies):  # slots reading the temperature too (RBFNet._inputs)
            z[copies] = z[copies] + (zc[temp] - z[temp]) * (std[temp] / std[copies])
        z[temp] = zc[temp]
        if single:  # one Gaussian input (the default model)
            distance_sq = (zc[gaussian_input] - centers_1) ** 2
        else:
            distance_sq = ((zc[rbf_index] - centers) ** 2).sum(1)
        basis = np.concatenate((np.exp(distance_sq * scale), z, zc[temp] ** exponents))
        return (weights @ basis + offset).tolist()

    if "group_columns" not in state or module.identity_columns:
        return forward_all
    # per-axis inputs (RBFNet.axis_columns): each group's slots read their columns, each axis its group's output
    groups = state["group_columns"].astype(int).tolist()
    axis_group = state["axis_group"].astype(int).tolist()
    copies = [np.array([i for i, c in enumerate(columns) if c == columns[temp] and i != temp], dtype=int)
              for columns in groups]

    def forward(x: list) -> list:
        outputs = [forward_all([x[c] for c in columns], own) for columns, own in zip(groups, copies)]
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
