"""How ``RBFNet`` starts its Gaussians (forward selection, k-means++) and its width floor, apart from the network."""
from __future__ import annotations

from typing import List

import torch
from torch import Tensor

from gyronet.errors import GyronetError

MIN_WIDTH = 1e-3
# forward selection's candidate Gaussians: centres every 1 degC of the trained range, these widths
# (times ``width_init``), from a sharp bias knee to a broad bend. Alone, narrower ones fit the noise: on
# one pass through the temperatures a degC is a minute of the record (2-3 degC: up to 1.37x on Table
# 1's x); but a knee 2.5 degC wide needs them (2.5x the floor without), so "ols_narrow" adds them as a
# start of its own, which the held-out stacking weighs against the others (gyronet/training/starts.py)
OLS_STEP_C = 1.0
OLS_WIDTHS_C = (4.0, 6.0, 8.0, 11.0, 16.0)
OLS_NARROW_WIDTHS_C = (2.5, 3.0) + OLS_WIDTHS_C
CENTER_INITS = ("kmeans", "ols", "ols_narrow")


def raw_width(width: Tensor) -> Tensor:
    """The inverse of ``softplus(raw) + min``: the raw parameter of a width."""
    return torch.log(torch.expm1(width - MIN_WIDTH))


class SelectionError(GyronetError, ValueError):
    """Fewer independent candidate Gaussians than centres (a narrow temperature range): no selected start."""


def forward_select(candidates: Tensor, base: Tensor, target: Tensor, k: int) -> Tensor:
    """Orthogonal least squares: the ``k`` candidate columns that, added one at a time to ``base``,
    most reduce the squared error of every target column together.

    Parameters
    ----------
    candidates
        (n, m) regressors to choose from.
    base
        (n, b) regressors always in the model (a constant, the linear terms, ...).
    target
        (n, p) targets; each column's squared error counts alike (normalise them first).
    k
        How many candidates to select.

    Returns
    -------
    Tensor
        (k,) indices into the columns of ``candidates``, in the order chosen.

    References
    ----------
    S. Chen, C. F. N. Cowan, P. M. Grant, "Orthogonal least squares learning algorithm for radial
    basis function networks", IEEE Trans. Neural Networks 2(2), 1991.
    """
    if k > candidates.shape[1]:
        raise SelectionError(f"cannot select {k} of {candidates.shape[1]} candidate Gaussians")
    q, _ = torch.linalg.qr(base)
    residual = target - q @ (q.T @ target)
    pool = candidates - q @ (q.T @ candidates)
    floor = 1e-10 * candidates.pow(2).sum(0)
    chosen: List[int] = []
    for _ in range(k):
        energy = pool.pow(2).sum(0)
        # error reduction of candidate m: sum_p (w_m . r_p)^2 / |w_m|^2, w_m orthogonal to all chosen
        gain = (pool.T @ residual).pow(2).sum(1) / energy.clamp_min(1e-300)
        gain[energy <= floor] = -1.0
        gain[chosen] = -1.0
        best = int(gain.argmax())
        if gain[best] < 0:
            raise SelectionError(f"only {len(chosen)} independent candidate Gaussians, {k} asked for")
        unit = pool[:, best] / energy[best].sqrt()
        residual = residual - unit[:, None] * (unit @ residual)[None]
        pool = pool - unit[:, None] * (unit @ pool)[None]
        chosen.append(best)
    return torch.tensor(chosen, dtype=torch.long)


def kmeans_pp(points: Tensor, k: int, generator: torch.Generator, iterations: int = 10) -> Tensor:
    """k-means++ seeding and a few Lloyd steps: centres where the data are, seeded explicitly."""
    n = len(points)
    if n <= k:
        extra = points[torch.randint(n, (k - n,), generator=generator)] if k > n else points[:0]
        return torch.cat([points, extra + 1e-3 * torch.randn(extra.shape, generator=generator, dtype=points.dtype)])
    centers = points[torch.randint(n, (1,), generator=generator)]
    for _ in range(k - 1):
        dist = torch.cdist(points, centers).min(1).values.pow(2)
        pick = torch.multinomial(dist / dist.sum() if dist.sum() > 0 else torch.ones(n, dtype=points.dtype),
                                 1, generator=generator)
        centers = torch.cat([centers, points[pick]])
    for _ in range(iterations):
        label = torch.cdist(points, centers).argmin(1)
        for j in range(k):
            members = points[label == j]
            if len(members):
                centers[j] = members.mean(0)
    return centers


@torch.no_grad()
def select_centers(net, x: Tensor, y: Tensor) -> None:
    """``net``'s (an ``RBFNet``) centres and widths by forward selection on the residual of its linear and polynomial terms."""
    t = net.temp_index
    scale_c = float(net.x_std[t])
    step = OLS_STEP_C / scale_c
    low, high = float(net.z_low[t]), float(net.z_high[t])
    grid = torch.arange(low, high + 0.5 * step, step, dtype=x.dtype)
    temp = ((x[:, t] - net.x_mean[t]) / net.x_std[t]).clamp(low, high)
    # a Gaussian centred in a gap of the training temperatures (a held-out span) is fitted by its
    # tails alone: candidates only where a training temperature lies within a grid step
    seen = torch.sort(temp).values
    after = torch.bucketize(grid, seen).clamp(1, len(seen) - 1)
    grid = grid[torch.minimum(grid - seen[after - 1], seen[after] - grid).abs() <= step]
    widths_c = OLS_NARROW_WIDTHS_C if net.center_init == "ols_narrow" else OLS_WIDTHS_C
    widths = torch.tensor(widths_c, dtype=x.dtype) * net.width_init / scale_c
    centre_of = grid.repeat(len(widths))
    width_of = widths.repeat_interleave(len(grid))
    _, lin, powers = net.parts(x)  # the other terms' regressors; the Gaussians' values are unused
    # phi_jk = exp(-(T_j - c_k)^2 / (2 w_k^2)), every candidate k
    candidates = torch.exp(-0.5 * ((temp[:, None] - centre_of[None]) / width_of[None]).pow(2))
    base = [torch.ones(len(x), 1, dtype=x.dtype)]
    if net.use_linear:
        base.append(lin)
    if net.temp_degree >= 2:
        base.append(powers)
    base = torch.cat(base, dim=1)
    q, _ = torch.linalg.qr(base)
    # each axis's misfit of the other terms counts alike, however small a share of its swing
    misfit = y - q @ (q.T @ y)
    chosen = forward_select(candidates, base, y / misfit.norm(dim=0).clamp_min(1e-300), net.n_centers)
    net.centers.copy_(centre_of[chosen].unsqueeze(1))
    net.raw_width.copy_(raw_width(width_of[chosen].clamp_min(2 * MIN_WIDTH)))
    # Adam would narrow a Gaussian onto the noise again
    net.train_min_width = float(widths.min())
