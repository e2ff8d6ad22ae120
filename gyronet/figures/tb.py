"""TensorBoard helpers: scalars, figures and hparams, so every run's curves sit beside its config."""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Mapping

log = logging.getLogger(__name__)


def make_writer(log_dir: str | Path, fresh: bool = False):
    """A ``SummaryWriter`` writing event files into ``log_dir``; ``fresh``: an earlier run's event files there are
    removed first (a run again into the same folder drew two runs as one, two values at each step)."""
    from torch.utils.tensorboard import SummaryWriter

    earlier = sorted(Path(log_dir).rglob("events.out.tfevents.*")) if fresh else []
    for path in earlier:
        path.unlink()
    if earlier:
        log.info("%s: the earlier run's TensorBoard files removed (%d)", log_dir, len(earlier))
    return SummaryWriter(log_dir=str(log_dir))


def log_scalars(writer: Any, metrics: Mapping[str, float], step: int = 0) -> None:
    """One scalar per ``split/name`` tag."""
    for tag, value in metrics.items():
        writer.add_scalar(tag, float(value), step)


def log_figure(writer: Any, tag: str, figure: Any, step: int = 0) -> None:
    """A matplotlib figure as an image, closed afterwards."""
    import matplotlib.pyplot as plt

    writer.add_figure(tag, figure, step, close=True)
    plt.close(figure)


def log_hparams(writer: Any, hparams: Mapping[str, Any], metrics: Mapping[str, float]) -> None:
    """hparams of the run next to its final metrics, so sweep runs compare side by side."""
    clean = {k: (v if isinstance(v, (int, float, str, bool)) else str(v)) for k, v in hparams.items()}
    writer.add_hparams(clean, {k: float(v) for k, v in metrics.items()}, run_name=".")
