"""The Gaussians on one input with their gradient by hand (a third of autograd's operations), for a fit's inner loop."""
from __future__ import annotations

import torch
from torch import Tensor


class Gaussians1D(torch.autograd.Function):
    """``RBFNet._gaussians`` on one input, (n, 1) -> (n, K), with its gradient by hand (training only)."""

    @staticmethod
    def forward(ctx, r: Tensor, centers: Tensor, widths: Tensor) -> Tensor:
        diff = r - centers.t()
        scale = -0.5 / (widths * widths)
        phi = torch.exp(diff * diff * scale)
        ctx.save_for_backward(diff, scale, phi, widths)
        return phi

    @staticmethod
    def backward(ctx, grad_phi: Tensor):
        # phi = exp(scale d^2), d = r - c, scale = -1 / (2 w^2): dphi/dc = -2 scale d phi, dphi/dw = d^2 phi / w^3
        diff, scale, phi, widths = ctx.saved_tensors
        weighted = grad_phi * phi * diff
        grad_centers = (-2.0 * scale * weighted.sum(0)).unsqueeze(1)
        grad_widths = (weighted * diff).sum(0) / (widths * widths * widths)
        return None, grad_centers, grad_widths
