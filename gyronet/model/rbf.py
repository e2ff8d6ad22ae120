"""Gaussian radial-basis network for gyro drift: features in, drift per axis out (deg/s).

Two ways to use it:

- the paper's RBF network: every input feeds the Gaussians, nothing else
  (``linear=False, temp_degree=0, clamp=False``);
- gyronet's default, a hybrid: a linear term in every input, a polynomial in temperature, and the
  Gaussians on the inputs a thermal history fully covers (temperature), all evaluated inside the
  trained box. A Gaussian fades to zero outside the data, so a plain RBF trained on a cooling run
  has no idea what heating does; the linear rate terms carry that over.

The default also lets training choose each axis's capacity (``select_capacity``): a lower level only
zeroes weights in the axis's row of the output layers, so an export of the state needs nothing new.
"""
from __future__ import annotations

import logging
from typing import List, Optional, Tuple

import torch
from torch import Tensor, nn
from torch.nn import functional

from gyronet.model.rbf_gaussians import Gaussians1D
from gyronet.model.rbf_init import (CENTER_INITS, MIN_WIDTH, OLS_NARROW_WIDTHS_C, OLS_STEP_C, OLS_WIDTHS_C,
                                    SelectionError, forward_select, kmeans_pp, raw_width, select_centers)

__all__ = ["CENTER_INITS", "OLS_NARROW_WIDTHS_C", "OLS_STEP_C", "OLS_WIDTHS_C", "RBFNet", "SelectionError",
           "forward_select"]

log = logging.getLogger(__name__)


class RBFNet(nn.Module):
    """Gaussian RBF network with learnable centres and widths, plus optional linear and polynomial terms.

    Parameters
    ----------
    n_inputs
        Number of input features (columns of ``x``).
    n_outputs
        Number of gyro axes.
    n_centers
        Number of Gaussian units.
    width_init
        Initial width: with ``center_init="kmeans"`` a multiple of the mean distance from a centre
        to its nearest neighbour; with ``"ols"`` a factor on the candidate widths ``OLS_WIDTHS_C``
        (``OLS_NARROW_WIDTHS_C`` with ``"ols_narrow"``).
    two_way_width_init
        With ``validate_init``: the ``width_init`` the starts use instead when the record heats and
        cools through at least half its temperatures (``gyronet.training.two_way``); None: always
        ``width_init``.
    rbf_inputs
        Indices of the inputs that feed the Gaussians; all when None.
    linear
        Add a linear term in every normalised input (temperature clamped with ``clamp``, the
        others unclamped).
    temp_degree
        Add powers 2..degree of the (clamped, normalised) temperature input; 0 or 1 for none.
    temp_index
        Which input is temperature.
    clamp
        Evaluate the Gaussians, the polynomial and the linear temperature term at inputs clamped
        to the training box.
    select_capacity
        Let training choose each axis's capacity on held-out data (``gyronet.training.capacity``): it
        only zeroes rows of the output layers, so the function and its parameters stay the same.
    refit_all
        One recording split into time blocks: once validation has confirmed the fit (and chosen
        each axis's capacity), the bundle's training continues from it on every block, validation
        blocks included, for another ``max_epochs`` steps (``gyronet.training.train.fit(for_bundle=True)``),
        so that no stretch of temperature is left out of the bundle: a bias knee inside a held-out
        span is otherwise never seen. The reported validation figures are those from before.
    center_init
        How training starts the Gaussians: ``"kmeans"``, centres where the data are (k-means++)
        and one shared width; or ``"ols"``, forward selection by orthogonal least squares from
        candidates on a temperature grid at several widths, each picked for how much of the
        training target the other terms leave it explains (Gaussians on temperature only); or
        ``"ols_narrow"``, the same with candidates down to 2.5 degC wide.
    validate_init
        One recording: a validated fit from each ``center_init``, mixed per axis with the weights
        that minimise the held-out blocks' error (``gyronet.training.starts``; the bundle holds the Gaussians
        of every start with a weight on some axis); several runs and fixed-budget fits use
        ``center_init``. No start is better on every sensor: forward selection finds a sharp knee
        that k-means centres miss, k-means centres follow a broad bend with less noise, and only
        the narrow candidates follow a knee 2-3 degC wide.
    kmeans_members
        With ``validate_init``: the k-means start is the average of this many fits from different
        k-means++ seeds (bagging), since one seeding makes the held-out error depend on the seed.
    axis_lags_s
        Candidate thermal lags per axis, s (``gyronet.training.axis_lag`` chooses one per axis before
        the fit and builds the network with ``axis_columns``); None or empty: none.
    axis_columns
        Per output axis, the input column each input slot reads (None: the inputs as they are): an
        axis whose temperature, dT/dt and T*dT/dt are lagged versions reads those columns in their
        slots, with the slots' normalisation, box, centres and widths.
    """

    def __init__(self, n_inputs: int, n_outputs: int = 3, n_centers: int = 32, width_init: float = 1.0,
                 rbf_inputs: Optional[List[int]] = None, linear: bool = False, temp_degree: int = 0,
                 temp_index: int = 0, clamp: bool = False, select_capacity: bool = False,
                 refit_all: bool = False, center_init: str = "kmeans", validate_init: bool = False,
                 kmeans_members: int = 1, axis_lags_s: Optional[List[float]] = None,
                 axis_columns: Optional[List[List[int]]] = None, two_way_width_init: Optional[float] = None):
        super().__init__()
        if center_init not in CENTER_INITS:
            raise ValueError(f"center_init must be one of {', '.join(CENTER_INITS)}, got {center_init!r}")
        self.n_inputs, self.n_outputs, self.n_centers = n_inputs, n_outputs, n_centers
        self.width_init = float(width_init)
        self.two_way_width_init = None if two_way_width_init is None else float(two_way_width_init)
        self.min_width = MIN_WIDTH
        self.rbf_inputs: List[int] = list(range(n_inputs)) if rbf_inputs is None else [int(i) for i in rbf_inputs]
        self.use_linear, self.temp_degree, self.temp_index, self.clamp = linear, int(temp_degree), temp_index, clamp
        self.select_capacity, self.refit_all = bool(select_capacity), bool(refit_all)
        self.center_init, self.validate_init = center_init, bool(validate_init)
        if int(kmeans_members) < 1:
            raise ValueError(f"kmeans_members must be 1 or more, got {kmeans_members!r}")
        self.kmeans_members = int(kmeans_members)
        self.axis_lags_s = [float(t) for t in (axis_lags_s or [])]
        columns = [list(range(n_inputs))] * n_outputs if axis_columns is None else [[int(c) for c in a]
                                                                                     for a in axis_columns]
        if len(columns) != n_outputs or any(len(a) != n_inputs or not all(0 <= c < n_inputs for c in a)
                                            for a in columns):
            raise ValueError(f"axis_columns must list {n_inputs} input columns for each of {n_outputs} axes")
        groups = list(dict.fromkeys(tuple(a) for a in columns))
        self.axis_columns, self.n_groups = columns, len(groups)
        self.identity_columns = groups == [tuple(range(n_inputs))]
        self.register_buffer("group_columns", torch.tensor(groups, dtype=torch.long))
        self.register_buffer("axis_group", torch.tensor([groups.index(tuple(a)) for a in columns], dtype=torch.long))
        # training keeps every width at or above this (normalised units); ``"ols*"`` set it to their narrowest candidate
        self.train_min_width = MIN_WIDTH
        if (center_init != "kmeans" or self.validate_init) and self.rbf_inputs != [temp_index]:
            raise ValueError("center_init='ols' selects Gaussians on temperature only: set rbf_inputs to [temp_index]")
        n_rbf = len(self.rbf_inputs)
        dtype = torch.float64
        self.register_buffer("x_mean", torch.zeros(n_inputs, dtype=dtype))
        self.register_buffer("x_std", torch.ones(n_inputs, dtype=dtype))
        self.register_buffer("z_low", torch.full((n_inputs,), -1e6, dtype=dtype))
        self.register_buffer("z_high", torch.full((n_inputs,), 1e6, dtype=dtype))
        self.register_buffer("y_mean", torch.zeros(n_outputs, dtype=dtype))
        self.register_buffer("y_std", torch.ones(n_outputs, dtype=dtype))
        self.register_buffer("rbf_index", torch.tensor(self.rbf_inputs, dtype=torch.long))
        self.centers = nn.Parameter(torch.zeros(n_centers, n_rbf, dtype=dtype))
        # width = softplus(raw) + min: always positive, gradient defined everywhere
        self.raw_width = nn.Parameter(torch.zeros(n_centers, dtype=dtype))
        self.head = nn.Linear(n_centers, n_outputs, dtype=dtype)
        self.linear = nn.Linear(n_inputs, n_outputs, bias=False, dtype=dtype)
        self.poly = nn.Linear(max(self.temp_degree - 1, 1), n_outputs, bias=False, dtype=dtype)
        if not self.use_linear:
            self.linear.weight.requires_grad_(False)
            nn.init.zeros_(self.linear.weight)
        if self.temp_degree < 2:
            self.poly.weight.requires_grad_(False)
            nn.init.zeros_(self.poly.weight)

    def widths(self) -> Tensor:
        """Gaussian widths in normalised input units, shape (n_centers,)."""
        return functional.softplus(self.raw_width) + self.min_width

    def parts(self, x: Tensor, g: int = 0) -> Tuple[Tensor, Tensor, Tensor]:
        """Gaussian activations, the linear term's inputs and temperature powers 2..degree, each (n, .) (group ``g``'s ``x``).

        The linear term sees the normalised inputs, with temperature clamped to the training box
        when ``clamp`` is set, in every slot that reads it (``axis_columns``' lag slots copy it):
        outside the trained range every part holds its edge value. The rate terms stay unclamped,
        carrying dT/dt over to heating or cooling the training never saw; at a steady temperature
        (dT/dt = 0, so T * dT/dt = 0) the whole output holds.
        """
        r, z, powers = self._inputs(x, g)
        return self._gaussians(r), z, powers

    def _inputs(self, x: Tensor, g: int = 0) -> Tuple[Tensor, Tensor, Tensor]:
        """The parts' inputs, none of which depends on a parameter: the Gaussians' (clamped), the linear term's, the powers."""
        z = (x - self.x_mean) / self.x_std
        zc = torch.minimum(torch.maximum(z, self.z_low), self.z_high) if self.clamp else z
        if self.clamp:
            t = self.temp_index
            if not self.identity_columns:  # the temperature's copies move with it to the edge, in their own units
                copies = (self.group_columns[g] == self.group_columns[g][t]) & (torch.arange(self.n_inputs, device=z.device) != t)
                z = torch.where(copies, z + (zc[:, t:t + 1] - z[:, t:t + 1]) * (self.x_std[t] / self.x_std), z)
            z = torch.cat([z[:, :t], zc[:, t:t + 1], z[:, t + 1:]], dim=1)
        temp = zc[:, self.temp_index:self.temp_index + 1]
        powers = torch.cat([temp.pow(k) for k in range(2, max(self.temp_degree, 2) + 1)], dim=1)
        return zc.index_select(1, self.rbf_index), z, powers

    def _gaussians(self, r: Tensor) -> Tensor:
        # phi_k = exp(-|r - c_k|^2 / (2 w_k^2))
        # (broadcast rather than cdist: cdist's backward is slow and its forward no faster here)
        diff = r.unsqueeze(1) - self.centers.unsqueeze(0)
        widths = self.widths()
        return torch.exp((diff * diff).sum(2) * (-0.5 / (widths * widths)))

    def group_input(self, x: Tensor, group: int) -> Tensor:
        """``x`` as the axes of ``group`` see it: each slot holding the column it reads."""
        return x if self.identity_columns else x.index_select(1, self.group_columns[group])

    def per_axis(self, outputs: List[Tensor]) -> Tensor:
        """(n, n_outputs) from every group's output: each axis from its own group's."""
        if len(outputs) == 1:
            return outputs[0]
        stacked = torch.stack(outputs)
        index = self.axis_group.view(1, 1, -1).expand(1, stacked.shape[1], stacked.shape[2])
        return stacked.gather(0, index)[0]

    def on_fixed_input(self, x: Tensor):
        """``forward(x)`` as a function of the parameters alone, for a fit's inner loop on one ``x``.

        What does not depend on a parameter (normalised inputs, clamp, temperature powers) is
        computed once, and Gaussians on one input take a hand-written gradient (``Gaussians1D``,
        a third of autograd's operations): the same numbers as ``forward``, in about half the time
        a step. The buffers must not change while it is used.
        """
        with torch.no_grad():
            inputs = [self._inputs(self.group_input(x, g), g) for g in range(self.n_groups)]

        def gaussians(r: Tensor) -> Tensor:
            if r.shape[1] == 1:
                return Gaussians1D.apply(r, self.centers, self.widths())
            return self._gaussians(r)

        return lambda: self.per_axis([self._output(gaussians(r), z, powers) for r, z, powers in inputs])

    def basis(self, x: Tensor, g: int = 0) -> Tensor:
        """Every regressor the output layers combine, side by side (group ``g``'s ``x``)."""
        phi, z, powers = self.parts(x, g)
        return torch.cat([phi, z, powers], dim=1)

    def forward(self, x: Tensor) -> Tensor:
        """Drift (deg/s), shape (n, n_outputs), from features ``x`` of shape (n, n_inputs), float64."""
        outputs: List[Tensor] = []
        for g in range(self.n_groups):
            phi, z, powers = self.parts(self.group_input(x, g), g)
            outputs.append(self._output(phi, z, powers))
        return self.per_axis(outputs)

    def _output(self, phi: Tensor, z: Tensor, powers: Tensor) -> Tensor:
        """The output layers on the parts, in deg/s."""
        return (self.head(phi) + self.linear(z) + self.poly(powers)) * self.y_std + self.y_mean

    @torch.no_grad()
    def init_from_data(self, x: Tensor, y: Tensor, generator: torch.Generator, ridge: float = 1e-6) -> None:
        """Normalisation, training box, centres and widths (``center_init``) and a least-squares head."""
        self.x_mean.copy_(x.mean(0))
        self.x_std.copy_(x.std(0).clamp_min(1e-12))
        self.y_mean.copy_(y.mean(0))
        self.y_std.copy_(y.std(0).clamp_min(1e-12))
        z = (x - self.x_mean) / self.x_std
        self.z_low.copy_(z.min(0).values)
        self.z_high.copy_(z.max(0).values)
        r = z[:, self.rbf_index]
        if self.center_init != "kmeans":
            select_centers(self, x, y)
        else:
            self.centers.copy_(kmeans_pp(r, self.n_centers, generator))
            nearest = torch.cdist(self.centers, self.centers).fill_diagonal_(float("inf")).min(1).values
            width = (self.width_init * nearest.clamp_min(1e-3).mean()).clamp_min(2 * MIN_WIDTH)
            self.raw_width.fill_(float(raw_width(width)))
        self.refit_head(x, y, ridge)

    @torch.no_grad()
    def keep_widths_(self) -> None:
        """Hold every width at or above ``train_min_width`` (after an optimizer step)."""
        if self.train_min_width > 2 * MIN_WIDTH:
            self.raw_width.clamp_(min=float(raw_width(torch.tensor(self.train_min_width, dtype=torch.float64))))

    @torch.no_grad()
    def refit_head(self, x: Tensor, y: Tensor, ridge: float = 1e-6, level: int = 3,
                   axes: Optional[List[int]] = None) -> None:
        """Solve the output layer by ridge least squares for the current centres and widths.

        ``level`` is the capacity of the fitted rows (``gyronet.training.capacity.LEVELS``): 0 a constant,
        1 + the linear terms, 2 + the temperature powers, 3 + the Gaussians (everything). Only the
        rows of ``axes`` (all when None) are written; the parts above ``level`` are zero there.
        """
        rows = list(range(self.n_outputs)) if axes is None else [int(a) for a in axes]
        for g in range(self.n_groups):  # the axes that read the same columns share one design
            group_rows = [a for a in rows if int(self.axis_group[a]) == g]
            if group_rows:
                self._refit_rows(self.group_input(x, g), y, ridge, level, group_rows, g)

    def _refit_rows(self, x: Tensor, y: Tensor, ridge: float, level: int, rows: List[int], g: int) -> None:
        basis = self.basis(x, g)
        n_phi, n_lin = self.n_centers, self.n_inputs
        n_pow = basis.shape[1] - n_phi - n_lin
        keep = ([level >= 3] * n_phi + [self.use_linear and level >= 1] * n_lin
                + [self.temp_degree >= 2 and level >= 2] * n_pow)
        cols = torch.tensor(keep)
        design = torch.cat([basis[:, cols], torch.ones(len(x), 1, dtype=x.dtype)], dim=1)
        target = (y - self.y_mean) / self.y_std
        gram = design.T @ design + ridge * len(x) * torch.eye(design.shape[1], dtype=x.dtype)
        coef = torch.linalg.solve(gram, design.T @ target)
        full = torch.zeros(n_phi + n_lin + n_pow, self.n_outputs, dtype=x.dtype)
        full[cols] = coef[:-1]
        for a in rows:
            self.head.weight[a] = full[:n_phi, a]
            self.head.bias[a] = coef[-1, a]
            if self.use_linear:
                self.linear.weight[a] = full[n_phi:n_phi + n_lin, a]
            if self.temp_degree >= 2:
                self.poly.weight[a] = full[n_phi + n_lin:, a]
