"""Figures people would rather look at than read: raw versus compensated, residual versus temperature, the survey."""
from __future__ import annotations

from typing import Any, Mapping, Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
from matplotlib import ticker  # noqa: E402
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


def survey_figure(results: Sequence[Mapping[str, Any]], ours: str, goals: Mapping[str, float],
                  coverage: tuple[np.ndarray, np.ndarray] | None, sigma_goal: tuple[float, float]) -> plt.Figure:
    """The survey at a glance: every method's worst axis over the sensors, and ``ours``' error bar per sensor-axis.

    Each method's worst axis as deployed, sorted (a quantile curve), ``ours`` also with the truth's turn-on
    bias: against the goals as a staircase (the 90th percentile, then the worst; a curve under it meets
    both), and, when some method is far off them, every method on a log scale beside it. With ``coverage``
    (each sensor-axis's share of 60 s blocks within 1 sigma and the range a bar that holds gives that run,
    ``gyronet.analysis.survey.table.error_bar_arrays``): the shares sorted against their ranges and
    ``sigma_goal`` (the pooled share's goal); red where a share is below its range.
    """
    results = [r for r in results if "error" not in r]
    curves = {}  # label -> (sorted worst axis, style, colour index)
    for k, method in enumerate(results[0]["methods"]):
        curves[method] = (np.sort([max(r["methods"][method]["deployed"]) for r in results]), "-", k)
        if method == ours:
            curves[f"{ours}, turn-on bias from the truth"] = (
                np.sort([max(r["methods"][ours]["turn_on_removed"]) for r in results]), "--", k)
    near = {label: c for label, c in curves.items() if c[0][-1] <= 3 * goals["worst_max"]}
    n_panels = 1 + (len(near) < len(curves)) + (coverage is not None)
    fig, axes = plt.subplots(1, n_panels, figsize=(5.5 * n_panels, 4.4), squeeze=False)
    _survey_curves(axes[0, 0], near, goals, len(results))
    if len(near) < len(curves):
        _survey_curves(axes[0, 1], curves, None, len(results))
    if coverage is not None:
        _survey_error_bar(axes[0, -1], *coverage, ours, sigma_goal)
    fig.tight_layout()
    return fig


def _survey_curves(ax: plt.Axes, curves: Mapping[str, tuple], goals: Mapping[str, float] | None, n: int) -> None:
    """Quantile curves of the worst axis; with ``goals``, a linear scale and the goals' staircase, else log."""
    share = 100.0 * np.arange(n + 1) / n  # the k-th sorted value holds from k-1 to k sensors
    for label, (worst, style, colour) in curves.items():
        ax.plot(share, np.append(worst, worst[-1]), style, color=f"C{colour}", drawstyle="steps-post", lw=1.5,
                label=label)
    if goals is not None:
        ax.plot([0, 90, 90, 100], [goals["p90_max"], goals["p90_max"], goals["worst_max"], goals["worst_max"]],
                "k:", lw=1.2, label=f"goals ({goals['p90_max']:g}x at 90 %, {goals['worst_max']:g}x at worst)")
        ax.set_title(f"{n} sensors, as deployed, against the goals")
    else:
        ax.set_yscale("log")
        ax.yaxis.set_major_formatter(ticker.FormatStrFormatter("%g"))
        ax.set_title(f"{n} sensors, as deployed, every method")
    ax.set_xlim(0, 100)
    ax.set_xlabel("sensors at or below, %")
    ax.set_ylabel("worst axis, residual / noise floor")
    ax.grid(alpha=0.3, which="both")
    ax.legend(loc="best", fontsize=8)


def _survey_error_bar(ax: plt.Axes, within: np.ndarray, ranges: np.ndarray, ours: str, goal: tuple[float, float]) -> None:
    """Each sensor-axis's share of blocks within 1 sigma, sorted, with the range a bar that holds gives it."""
    within, ranges = within.ravel(), ranges.reshape(-1, 2)
    order = np.argsort(within)
    within, ranges = 100.0 * within[order], 100.0 * ranges[order]
    rank = np.arange(len(within))
    below = within < ranges[:, 0]
    ax.axhspan(100 * goal[0], 100 * goal[1], color="tab:green", alpha=0.15, lw=0, label="goal, pooled")
    ax.vlines(rank, ranges[:, 0], ranges[:, 1], color="0.85", lw=0.8, label="a bar that holds, 9 runs in 10")
    ax.plot(rank[~below], within[~below], ".", color="tab:blue", ms=3, label="share within 1 sigma")
    ax.plot(rank[below], within[below], ".", color="tab:red", ms=4, label=f"below that range ({below.sum()})")
    ax.set_ylim(0, 100)
    ax.set_xlabel("sensor-axes, sorted")
    ax.set_ylabel("60 s blocks within 1 sigma, %")
    ax.set_title(f"{ours}'s error bar as deployed: {within.mean():.0f} % pooled")
    ax.grid(alpha=0.3)
    ax.legend(loc="lower right", fontsize=8)
