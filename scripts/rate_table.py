"""The README's "Rate changes and jitter" table: python scripts/rate_table.py [--out DIR] [--skip-training].

A 2 Hz bundle (the test suite's recipe: paper profile, sensor 0, 300 steps) is trained once; the
held-out cycle profile of the same sensor is simulated at 20 Hz and damaged (gyronet/sim/timing.py),
then compensated as compensate.py runs it (gyronet/analysis/rate_table.py). Each figure is the residual
against the truth over that of the same samples with the features computed at 20 Hz, x / y / z.
The training rows train on the paper profile at 4 Hz, intact and with its rate doubled for the
last fifth, and compare the two bundles on the held-out cycle. The markdown and the JSON go to
DIR (default outputs/rate_table/).
"""
from __future__ import annotations

import argparse
import logging
from pathlib import Path

from gyronet.analysis.rate_table import rate_table, to_markdown, training_rows
from gyronet.atomic import write_json, write_text
from gyronet.sim import simulate, write_simulation

log = logging.getLogger(__name__)


def _train(csv: str, run_dir: Path) -> Path:
    """The test suite's small default bundle (tests/conftest.py ``bundle``) on ``csv``."""
    from gyronet.training.dataset import DriftData
    from gyronet.model.rbf import RBFNet
    from gyronet.training.pipeline import train_run

    data = DriftData(csv)
    model = RBFNet(data.n_features, 3, 8, rbf_inputs=[0], linear=True, temp_degree=3, clamp=True)
    train_run(data, model, None, run_dir, {"max_epochs": 300, "progress": False})
    return run_dir / "compensator"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="outputs/rate_table")
    parser.add_argument("--skip-training", action="store_true", help="only the compensate.py rows")
    args = parser.parse_args()
    logging.basicConfig(level=logging.WARNING, format="%(message)s")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    write_simulation(simulate("paper", fs_hz=2.0, seed=1, sensor_seed=0), out / "paper.csv")
    bundle = _train(str(out / "paper.csv"), out / "bundle")
    held_out = simulate("cycle", fs_hz=20.0, seed=2, sensor_seed=0)
    rows = rate_table(bundle, held_out.recording, held_out.truth, step=10)
    markdown = to_markdown(rows)
    figures = {"compensate": rows}
    if not args.skip_training:
        paper = simulate("paper", fs_hz=4.0, seed=1, sensor_seed=0)
        figures["train"] = training_rows(paper.recording, held_out.recording, held_out.truth, 2, 10, out / "train",
                                         _train)
        markdown += "\n\ntrain.py on the paper profile, held-out residual over the intact bundle's:\n" + "\n".join(
            f"- {name}: " + (got if isinstance(got, str) else " / ".join(f"{v:.2f}x" for v in got))
            for name, got in figures["train"].items())
    write_text(out / "rate_table.md", markdown + "\n")
    write_json(out / "rate_table.json", figures)
    print(markdown)


if __name__ == "__main__":
    main()
