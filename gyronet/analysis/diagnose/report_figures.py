"""The report's PNG figures (residual before and after), apart from the text so that report.py stays short."""
from __future__ import annotations

import re
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from gyronet.recordings.data import AXES
from gyronet.analysis.diagnose.candidates import describe
from gyronet.analysis.diagnose.rows import ScreenRows


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", name)


def _held_out_hours(stage: Any, record: int) -> list[tuple[float, float]]:
    """Spans (h from the start) of the time blocks the networks were validated on (none with a
    separate recording)."""
    from gyronet.recordings.data import split_by_time

    data = stage.data
    if record or data.val_path:
        return []
    time_s = data.recording.time_s
    _, val = split_by_time(time_s, data.val_fraction, data.n_blocks, data.val_fold)
    edges = np.flatnonzero(np.diff(np.concatenate([[0], val.astype(int), [0]])))
    hours = (time_s - time_s[0]) / 3600.0
    return [(hours[a], hours[b - 1]) for a, b in zip(edges[::2], edges[1::2])]


def write_figures(out_dir: Path, rows: ScreenRows, stages: Sequence[Any], record: int) -> list[str]:
    """Write the baseline and final residual figures of recording ``record`` into ``out_dir``; their file names."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    mask = rows.recording == record
    hours = (rows.time_s[mask] - rows.time_s[mask][0]) / 3600.0
    residual = {label: (rows.target - rows.predict(s.model, s.data.features))[mask]
                for label, s in (("baseline", stages[0]), ("final", stages[-1]))}
    temp = rows.features([{"kind": "temp"}])[mask, 0]
    written = []

    fig, axes = plt.subplots(4, 1, figsize=(9, 9), sharex=True)
    for i, axis in enumerate(AXES):
        for label, values in residual.items():
            axes[i].plot(hours, values[:, i], lw=0.8, label=label)
        axes[i].set_ylabel(f"{axis} residual, deg/s")
        axes[i].grid(alpha=0.3)
    for k, (start_h, stop_h) in enumerate(_held_out_hours(stages[0], record)):
        for ax in axes[:3]:
            ax.axvspan(start_h, stop_h, color="0.85", zorder=0, label="held out" if k == 0 and ax is axes[0] else None)
    axes[0].legend(loc="best")
    axes[3].plot(hours, temp, color="tab:red")
    axes[3].set_ylabel("temp_c")
    axes[3].set_xlabel("time, h")
    fig.suptitle(f"residual ({rows.block_s:g} s means) versus time")
    written.append(_save(fig, out_dir / "residual_vs_time.png"))

    written.append(_scatter(out_dir / "residual_vs_temperature.png", temp, "temperature, degC", residual))
    for spec in stages[-1].data.features[len(stages[0].data.features):]:
        x = rows.features([spec])[mask, 0]
        label = describe(spec)
        if spec["kind"] == "lag" and spec.get("source", "temp_c") == "temp_c":
            x, label = x - temp, f"{label} minus temp_c"
        elif spec["kind"] == "time":
            x, label = hours, "time since the start, h"
        from gyronet.model.features import feature_name

        written.append(_scatter(out_dir / f"residual_vs_{_safe(feature_name(spec))}.png", x, label, residual))
    return written


def write_runs_figures(out_dir: Path, rows: ScreenRows, stages: Sequence[Any], names: Sequence[str]) -> list[str]:
    """A campaign's baseline and final residual, run by run and versus temperature, into ``out_dir``; file names."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    residual = {label: rows.target - rows.predict(s.model, s.data.features)
                for label, s in (("baseline", stages[0]), ("final", stages[-1]))}
    temp = rows.features([{"kind": "temp"}])[:, 0]
    fig, axes = plt.subplots(4, len(names), figsize=(1 + min(4 * len(names), 16), 9), sharex="col", sharey="row",
                             squeeze=False)
    for run, name in enumerate(names):
        mask = rows.recording == run
        hours = (rows.time_s[mask] - rows.time_s[mask][0]) / 3600.0
        for i, axis in enumerate(AXES):
            for label, values in residual.items():
                line, = axes[i, run].plot(hours, values[mask, i], lw=0.8, label=label)
                axes[i, run].axhline(values[mask, i].mean(), color=line.get_color(), ls="--", lw=0.8)
            axes[i, run].grid(alpha=0.3)
            axes[i, 0].set_ylabel(f"{axis} residual, deg/s")
        axes[0, run].set_title(name)
        axes[3, run].plot(hours, temp[mask], color="tab:red")
        axes[3, run].set_xlabel("time since the run's start, h")
    axes[3, 0].set_ylabel("temp_c")
    axes[0, 0].legend(loc="best")
    fig.suptitle(f"residual ({rows.block_s:g} s means) in each run; dashed: the run's mean (turn-on bias, orientation)")
    return [_save(fig, out_dir / "residual_by_run.png"),
            _scatter(out_dir / "residual_vs_temperature.png", temp, "temperature, degC", residual)]


def _scatter(path: Path, x: np.ndarray, label: str, residual: Mapping[str, np.ndarray]) -> str:
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(12, 3.6), sharey=True)
    for i, axis in enumerate(AXES):
        for name, values in residual.items():
            axes[i].scatter(x, values[:, i], s=4, alpha=0.5, label=name)
        axes[i].axhline(0, color="k", lw=0.5)
        axes[i].set_title(axis)
        axes[i].set_xlabel(label)
        axes[i].grid(alpha=0.3)
    axes[0].set_ylabel("residual, deg/s")
    axes[0].legend(loc="best", markerscale=3)
    fig.suptitle(f"residual versus {label}")
    return _save(fig, path)


def _save(fig: Any, path: Path) -> str:
    import matplotlib.pyplot as plt

    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path.name
