"""``plot_allan``: the Allan curves as a figure, apart from the report so that only it loads matplotlib."""
from __future__ import annotations

import math
from typing import Mapping

import numpy as np

from gyronet.allan.noise import BIAS_INSTABILITY_FACTOR
from gyronet.allan.report import AXES, axes_of, num


def plot_allan(report_or_curves: Mapping, path=None, title: str = "Allan deviation"):
    """Log-log Allan curves per axis, the fitted -1/2, 0 and +1/2 lines marked where read; N, B, K in the legend.

    Parameters
    ----------
    report_or_curves
        One :func:`allan_report` result, or several by label, e.g.
        ``{"raw": report, "compensated": report2}``.
    path
        Also save the figure here (PNG by suffix) when given.
    title
        Figure title.

    Returns
    -------
    matplotlib.figure.Figure
        Drawn on an Agg canvas, never shown; the caller may log it (TensorBoard) or close it.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.ticker import NullLocator

    curves = {None: report_or_curves} if axes_of(report_or_curves) else dict(report_or_curves)
    axis_names = [a for a in AXES if any(a in r for r in curves.values())]
    axis_names += [a for r in curves.values() for a in axes_of(r) if a not in axis_names]
    n_panels = max(1, len(axis_names))
    # A fixed layout: constrained layout measures every log tick and takes seconds.
    fig = Figure(figsize=(4.6 * n_panels, 4.4))
    FigureCanvasAgg(fig)
    fig.subplots_adjust(left=0.08 if n_panels > 1 else 0.18, right=0.98, bottom=0.12, top=0.86, wspace=0.08)
    panels = fig.subplots(1, n_panels, squeeze=False, sharey=True)[0]
    ranges = []
    for panel, axis in zip(panels, axis_names):
        ranges += [_plot_curve(panel, report[axis], f"C{index % 10}", label,
                               report.get("segments", {}).get("max_fit_tau_s", math.inf))
                   for index, (label, report) in enumerate(curves.items()) if axis in report]
        panel.set_title(f"{axis} axis")
        panel.set_xlabel("tau (s)")
        panel.grid(True, which="major", alpha=0.4)
        panel.xaxis.set_minor_locator(NullLocator())  # minor log ticks cost most of the drawing time
        panel.yaxis.set_minor_locator(NullLocator())
        panel.legend(fontsize=7, loc="lower left")
    ranges = [r for r in ranges if r is not None]
    if ranges:  # the fitted lines run over all taus; keep the view on the data
        panels[0].set_ylim(min(r[0] for r in ranges) / 3.0, max(r[1] for r in ranges) * 3.0)
    panels[0].set_ylabel("Allan deviation (deg/s)")
    fig.suptitle(title)
    if path is not None:
        fig.savefig(path, dpi=110)
    return fig


def _plot_curve(panel, curve: Mapping, color: str, label: str | None,
                max_fit_tau_s: float = math.inf) -> tuple[float, float] | None:
    """Draw one axis' curve (faint past the taus N, B and K are read at) and its fitted lines; return the range
    of the positive ADEV values."""
    taus = np.asarray(curve["taus_s"], dtype=np.float64)
    dev = np.asarray(curve["adev_dps"], dtype=np.float64)
    arw, bias, rrw = (_finite(curve.get(k)) for k in ("arw_deg_rthr", "bias_instability_deg_hr", "rrw_deg_hr_rthr"))
    bound = "<=" if curve.get("bias_instability_upper_bound") else ""
    terms = f"N={num(arw)} deg/rt(h), B={bound}{num(bias)} deg/h, K={num(rrw)} deg/h/rt(h)"
    read = taus <= max_fit_tau_s
    panel.loglog(taus[read], dev[read], color=color, lw=1.6, label=f"{label}: {terms}" if label else terms)
    if not read.all():  # too few clusters (noise.MIN_CLUSTERS): shown, not read (joined to the last read tau)
        tail = max(int(read.sum()) - 1, 0)
        panel.loglog(taus[tail:], dev[tail:], color=color, lw=1.0, alpha=0.35)
    # sigma = N / sqrt(tau), sigma = 0.664 B, sigma = K sqrt(tau / 3), all back in deg/s.
    if math.isfinite(arw):
        _line_and_mark(panel, taus, lambda t: arw / 60.0 / np.sqrt(t), curve.get("arw_tau_s"), color, "--", "s")
    if math.isfinite(bias):
        flat_dps = bias / 3600.0 * BIAS_INSTABILITY_FACTOR
        panel.axhline(flat_dps, color=color, ls=":", lw=0.8)
        panel.plot([_finite(curve.get("bias_instability_tau_s"))], [flat_dps], marker="o", color=color, ms=4)
    if math.isfinite(rrw):
        _line_and_mark(panel, taus, lambda t: rrw / 216000.0 * np.sqrt(t / 3.0), curve.get("rrw_tau_s"), color,
                       "-.", "^")
    positive = dev[np.isfinite(dev) & (dev > 0)]
    return (float(positive.min()), float(positive.max())) if len(positive) else None


def _line_and_mark(panel, taus: np.ndarray, line, read_s, color: str, style: str, marker: str) -> None:
    """A fitted noise line (``line(tau)``, deg/s) over the taus, and a mark on it where it was read."""
    panel.loglog(taus, line(taus), color=color, ls=style, lw=0.8)
    read_s = _finite(read_s)
    panel.plot([read_s], [float(line(read_s))], marker=marker, color=color, ms=4)


def _finite(value) -> float:
    return float(value) if value is not None and math.isfinite(float(value)) else math.nan
