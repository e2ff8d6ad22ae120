"""``diagnose.py`` on several runs: train by leave-one-run-out and report it; the run-level screen is issue #12.

The single-record screen tests candidates against circular time shifts of one record, which is no
null for an effect that changes between runs (a turn-on bias, an orientation). Until a run-level
screen exists, several runs are trained on (leave-one-run-out, as ``train.py`` does), both bundles
are written, and ``effects`` stays empty with a note that says why.
"""
from __future__ import annotations

import json
import logging
import shutil
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import torch

from gyronet.data import AXES
from gyronet.pipeline import _jsonable, train_run

log = logging.getLogger(__name__)

NOTE = ("several runs: trained and scored by leave-one-run-out; the candidate screen works within one record "
        "and is not run across runs (issue #12), so no effect was searched")


def diagnose_runs(paths: Sequence[str], data_options: Mapping[str, Any], make_model: Callable[[int], torch.nn.Module],
                  out_dir: str | Path, optim: Callable | None = None, train_cfg: Mapping[str, Any] | None = None,
                  seed: int = 0) -> dict[str, Any]:
    """Train on every run by leave-one-run-out; write ``diagnosis.json`` and the two (equal) bundles."""
    from gyronet.runs import training_data

    out_dir = Path(out_dir)
    data = training_data(paths=list(paths), **dict(data_options))
    metrics = train_run(data, make_model(data.n_features), optim, out_dir / "baseline", dict(train_cfg or {}),
                        seed=seed)
    if (out_dir / "compensator").exists():
        shutil.rmtree(out_dir / "compensator")
    shutil.copytree(out_dir / "baseline" / "compensator", out_dir / "compensator")
    folds = json.loads((out_dir / "baseline" / "report.json").read_text())["folds"]
    stage = {"inputs": data.feature_names, "val_rmse_dps": {a: metrics[f"val/rmse_{a}_dps"] for a in AXES}}
    diagnosis = {"baseline": stage, "effects": [], "final": dict(stage), "runs": folds, "note": NOTE}
    (out_dir / "diagnosis.json").write_text(json.dumps(_jsonable(diagnosis), indent=2) + "\n")
    log.info("%s", NOTE)
    return diagnosis
