"""Figures people would rather look at than read: raw versus compensated, residual versus temperature."""
from __future__ import annotations

from typing import Mapping

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from gyronet.recordings.data import AXES, block_means  # noqa: E402


def raw_vs_compensated(arrays: Mapping[str, np.ndarray], block_s: float = 60.0, title: str = "") -> plt.Figure:
    """Per axis, 60 s means of the raw and compensated rate over time, with the temperature."""
    time_s = arrays["time_s"]
    hours = block_means(time_s, time_s, block_s) / 3600.0
    fig, axes = plt.subplots(4, 1, figsize=(9, 9), sharex=True)
    for i, axis in enumerate(AXES):
        ax = axes[i]
        ax.plot(hours, block_means(arrays["raw_dps"][:, i], time_s, block_s), label="raw", lw=1)
        ax.plot(hours, block_means(arrays["compensated_dps"][:, i], time_s, block_s), label="compensated", lw=1)
        ax.set_ylabel(f"{axis} rate, deg/s")
        ax.grid(alpha=0.3)
    axes[0].legend(loc="best")
    axes[3].plot(hours, block_means(arrays["temp_c"], time_s, block_s), color="tab:red")
    axes[3].set_ylabel("temperature, degC")
    axes[3].set_xlabel("time, h")
    axes[3].grid(alpha=0.3)
    fig.suptitle(title or f"raw vs compensated ({block_s:g} s means)")
    fig.tight_layout()
    return fig


def residual_vs_temperature(arrays: Mapping[str, np.ndarray], block_s: float = 60.0, title: str = "") -> plt.Figure:
    """Per axis, the 60 s residual against temperature: drift left after compensation.

    With ground truth the residual is the drift estimate's error; without, compensated minus its mean.
    """
    time_s = arrays["time_s"]
    temp = block_means(arrays["temp_c"], time_s, block_s)
    if "drift_true_dps" in arrays:
        residual = arrays["drift_hat_dps"] - arrays["drift_true_dps"]
        label = "drift estimate - true drift, deg/s"
    else:
        residual = arrays["compensated_dps"] - arrays["compensated_dps"].mean(0)
        label = "compensated - mean, deg/s"
    fig, axes = plt.subplots(1, 3, figsize=(12, 3.6), sharey=True)
    for i, axis in enumerate(AXES):
        axes[i].scatter(temp, block_means(residual[:, i], time_s, block_s), s=4, alpha=0.6)
        axes[i].axhline(0, color="k", lw=0.5)
        axes[i].set_title(axis)
        axes[i].set_xlabel("temperature, degC")
        axes[i].grid(alpha=0.3)
    axes[0].set_ylabel(label)
    fig.suptitle(title or f"residual vs temperature ({block_s:g} s means)")
    fig.tight_layout()
    return fig


def drift_sigma_band(arrays: Mapping[str, np.ndarray], block_s: float = 60.0, title: str = "") -> plt.Figure:
    """Per axis, the removed drift's error with its +-1 sigma band (60 s means): is the error bar honest?

    With ground truth the error is drift estimate minus true drift; without (a still run), the
    compensated rate minus its mean. The band is the bundle's ``drift_sigma`` (``gyronet.model.error_bar``).
    """
    time_s = arrays["time_s"]
    hours = block_means(time_s, time_s, block_s) / 3600.0
    if "drift_true_dps" in arrays:
        error, label = arrays["drift_hat_dps"] - arrays["drift_true_dps"], "drift error, deg/s"
    else:
        error, label = arrays["compensated_dps"] - arrays["compensated_dps"].mean(0), "compensated - mean, deg/s"
    sigma = arrays["drift_sigma_dps"]
    fig, axes = plt.subplots(3, 1, figsize=(9, 7), sharex=True)
    for i, axis in enumerate(AXES):
        band = block_means(sigma[:, i], time_s, block_s)
        axes[i].fill_between(hours, -band, band, color="tab:orange", alpha=0.3, lw=0, label="+-1 sigma")
        axes[i].plot(hours, block_means(error[:, i], time_s, block_s), lw=1, label=label)
        axes[i].set_ylabel(f"{axis}, deg/s")
        axes[i].grid(alpha=0.3)
    axes[0].legend(loc="best")
    axes[2].set_xlabel("time, h")
    fig.suptitle(title or f"removed drift's error and its 1-sigma error bar ({block_s:g} s means)")
    fig.tight_layout()
    return fig
