"""The compensators gyronet must beat, as good versions of themselves.

- ``TempPolynomial``: PX4's thermal calibration (``process_sensor_caldata.py`` and the
  ``TC_G*`` parameters): per axis, a cubic in (T - T_ref) with T_ref the middle of the
  calibrated range, and the temperature clamped to [T_min, T_max] before evaluation.
- ``LinearFeatures``: ordinary least squares on the paper's three inputs (T, dT/dt, T*dT/dt).

Both are ``nn.Module``s fitted in closed form, so they export and deploy like the network.
"""
from __future__ import annotations

import torch
from torch import Tensor, nn


def lstsq(design: Tensor, target: Tensor) -> Tensor:
    """Least squares that repeat bit for bit (MKL's default driver, gelsy, varies in the last bit between calls)."""
    return torch.linalg.lstsq(design, target, driver="gelsd").solution


class TempPolynomial(nn.Module):
    """PX4-style polynomial in temperature, with a reference temperature and range clamping.

    Parameters
    ----------
    n_inputs
        Number of input features; only ``temp_index`` is read.
    n_outputs
        Number of gyro axes.
    degree
        Polynomial degree (PX4 uses 3).
    temp_index
        Which input is the temperature, degC.
    """

    def __init__(self, n_inputs: int, n_outputs: int = 3, degree: int = 3, temp_index: int = 0):
        super().__init__()
        self.degree, self.temp_index = int(degree), int(temp_index)
        self.register_buffer("coef", torch.zeros(self.degree + 1, n_outputs, dtype=torch.float64))
        self.register_buffer("temp_ref_c", torch.zeros((), dtype=torch.float64))
        self.register_buffer("temp_min_c", torch.full((), -1e6, dtype=torch.float64))
        self.register_buffer("temp_max_c", torch.full((), 1e6, dtype=torch.float64))

    def _powers(self, x: Tensor) -> Tensor:
        temp = x[:, self.temp_index].clamp(self.temp_min_c, self.temp_max_c) - self.temp_ref_c
        return torch.stack([temp.pow(k) for k in range(self.degree + 1)], dim=1)

    def forward(self, x: Tensor) -> Tensor:
        """Drift (deg/s), shape (n, n_outputs), from features (n, n_inputs)."""
        return self._powers(x) @ self.coef

    @torch.no_grad()
    def fit_closed_form(self, x: Tensor, y: Tensor) -> None:
        """Least-squares fit; T_ref, T_min, T_max from the training temperatures, as PX4 does."""
        temp = x[:, self.temp_index]
        self.temp_min_c.copy_(temp.min())
        self.temp_max_c.copy_(temp.max())
        self.temp_ref_c.copy_(0.5 * (self.temp_min_c + self.temp_max_c))
        self.coef.copy_(lstsq(self._powers(x), y))


class LinearFeatures(nn.Module):
    """Ordinary least squares: drift = a + sum_i b_i * feature_i, per axis."""

    def __init__(self, n_inputs: int, n_outputs: int = 3):
        super().__init__()
        self.register_buffer("weight", torch.zeros(n_inputs, n_outputs, dtype=torch.float64))
        self.register_buffer("bias", torch.zeros(n_outputs, dtype=torch.float64))
        self.register_buffer("x_mean", torch.zeros(n_inputs, dtype=torch.float64))

    def forward(self, x: Tensor) -> Tensor:
        """Drift (deg/s), shape (n, n_outputs), from features (n, n_inputs)."""
        return (x - self.x_mean) @ self.weight + self.bias

    @torch.no_grad()
    def fit_closed_form(self, x: Tensor, y: Tensor) -> None:
        """Least squares on centred inputs (better conditioned than raw T and T*dT/dt)."""
        self.x_mean.copy_(x.mean(0))
        design = torch.cat([x - self.x_mean, torch.ones(len(x), 1, dtype=x.dtype)], dim=1)
        solution = lstsq(design, y)
        self.weight.copy_(solution[:-1])
        self.bias.copy_(solution[-1])
