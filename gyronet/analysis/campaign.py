"""The real-data table: each run of a campaign held out in turn, every compensator scored against its floor.

For each held-out run, every model is trained on the other runs (one run: its interleaved time
blocks; two or more: leave-one-run-out, optionally with one offset per run) and applied to the
held-out run from a fresh state through ``Compensator``, the deployed code, with and without the
start-up offset (``startup.still_s``). The score of an axis is the RMS of the 60 s block means of
the compensated rate from ``score_from_s`` on, divided by the run's floor: the overlapping Allan
deviation at 60 s of the raw rate in its cold dwell (the longest stretch within 1 degC of its
coldest point), where the temperature stands still and only the noise is left. 60 s blocks where
the device was touched (a gyro or accelerometer axis's spread over twice its median) are skipped.
A ratio of 1 means that the drift is gone down to the noise.
"""
from __future__ import annotations

import logging
from typing import Any, Callable, Mapping, Sequence

import numpy as np
import torch

from gyronet.allan import oadev
from gyronet.bundle.compensator import Compensator
from gyronet.errors import GyronetError
from gyronet.recordings.data import AXES, Recording, block_means, time_blocks
from gyronet.model.features import PAPER_FEATURES
from gyronet.training.run_data import check_long_enough, load_runs
from gyronet.training.runs import fit_by_run, training_data

log = logging.getLogger(__name__)

BLOCK_S = 60.0
TOUCH_FACTOR = 2.0  # a block is touched when an axis's spread is over this many times its median spread


def cold_dwell(recording: Recording, within_c: float = 1.0) -> np.ndarray:
    """Mask of the longest contiguous stretch within ``within_c`` of the run's coldest temperature."""
    temp = recording.temp_c
    cold = temp < temp.min() + within_c
    edges = np.flatnonzero(np.diff(np.r_[0, cold.astype(int), 0]))
    starts, stops = edges[::2], edges[1::2]
    k = int(np.argmax(stops - starts))
    mask = np.zeros(len(temp), bool)
    mask[starts[k]:stops[k]] = True
    return mask


def floor_dps(recording: Recording, tau_s: float = BLOCK_S) -> np.ndarray:
    """Overlapping Allan deviation at ``tau_s`` of the raw rate in the cold dwell, per axis, deg/s."""
    mask = cold_dwell(recording)
    try:
        _, adev, _ = oadev(recording.gyro_dps[mask], recording.fs_hz, [tau_s])
    except ValueError:  # too few samples for one tau_s
        raise GyronetError(f"{recording.path}: its cold dwell (the longest stretch within 1 degC of its coldest "
                           f"temperature) is {int(mask.sum())} samples, too short for the noise floor (the Allan "
                           f"deviation at {tau_s:g} s needs more than {2 * tau_s:g} s of it)") from None
    return np.asarray(adev[0], dtype=np.float64)


def touched_blocks(recording: Recording, block_s: float = BLOCK_S) -> np.ndarray:
    """Per ``block_s`` block: was the device handled (any gyro or accelerometer axis unusually spread)?"""
    block = time_blocks(recording.time_s, block_s)
    n = int(block.max()) + 1
    acc = [recording.columns[f"acc_{a}_g"] for a in AXES if f"acc_{a}_g" in recording.columns]
    cols = np.column_stack([recording.gyro_dps, *acc])
    counts = np.maximum(np.bincount(block, minlength=n), 1)[:, None]
    mean = np.stack([np.bincount(block, c, n) for c in cols.T], 1) / counts
    square = np.stack([np.bincount(block, c * c, n) for c in cols.T], 1) / counts
    spread = np.sqrt(np.maximum(square - mean**2, 0.0))
    return np.any(spread > TOUCH_FACTOR * np.median(spread, axis=0), axis=1)


def score(recording: Recording, rate_dps: np.ndarray, score_from_s: float, floor: np.ndarray,
          touched: np.ndarray, box_c: tuple[float, float] | None = None) -> np.ndarray:
    """RMS of the 60 s block means of ``rate_dps`` after ``score_from_s``, untouched blocks only, / floor.

    With ``box_c`` only the samples inside those temperatures count, with their own mean removed:
    what transfers inside a trained box, whatever the run's constant (a perfect offset).
    """
    t = recording.time_s
    keep = (t >= t[0] + score_from_s) & ~touched[time_blocks(t, BLOCK_S)]
    if box_c is not None:
        keep &= (recording.temp_c >= box_c[0]) & (recording.temp_c <= box_c[1])
        rate_dps = rate_dps - rate_dps[keep].mean(0)
    means = block_means(rate_dps[keep], t[keep], BLOCK_S)
    return np.sqrt(np.mean(means**2, axis=0)) / floor


def _train(make_model: Callable[[int], torch.nn.Module], paths: Sequence[str], run_offsets: bool,
           train_cfg: Mapping[str, Any], seed: int, data_options: Mapping[str, Any] | None = None) -> Compensator:
    """Train on ``paths`` as ``train.py`` would; ``data_options`` are a model's own data settings.

    ``in_sample`` (PX4's script, which holds nothing out): one training run is fitted whole and
    validated on itself.
    """
    from gyronet.training.axis_lag import with_axis_lags
    from gyronet.training.pipeline import _meta
    from gyronet.training.train import fit

    options = {"features": PAPER_FEATURES, **dict(data_options or {})}
    in_sample = options.pop("in_sample", False) and len(paths) == 1
    options["features"] = [dict(s) for s in options["features"]]
    data = training_data(paths=list(paths), run_offsets=run_offsets, **options,
                         **({"val_path": str(paths[0])} if in_sample else {}))
    model = make_model(data.n_features)
    # one run: each axis's thermal lag as train.py chooses it (make_model then takes axis_columns)
    data, model = with_axis_lags(data, lambda n, columns: make_model(n, axis_columns=columns), model)
    if getattr(data, "n_runs", 1) > 1:
        fit_by_run(model, data, seed=seed, **train_cfg)
    else:
        fit(model, data, seed=seed, **train_cfg)
    return Compensator(model.eval(), _meta(model, data))


def _accepted(run: Any) -> Recording:
    """The run's recording without the rows the guard left out (a glitch is no cold dwell)."""
    if run.accepted is None:
        return run.recording
    return Recording({k: v[run.accepted] for k, v in run.recording.columns.items()}, run.recording.meta,
                     run.recording.path)


def held_out_table(paths: Sequence[str], models: Mapping[str, Callable[[int], torch.nn.Module] | None],
                   startup_s: float = 600.0, score_from_s: float = 600.0, run_offsets: bool = True,
                   train_cfg: Mapping[str, Any] | None = None, seed: int = 0,
                   data_options: Mapping[str, Mapping[str, Any]] | None = None) -> dict[str, Any]:
    """Hold each run out in turn; score every model (None: raw) with and without the start-up offset.

    ``data_options`` maps a model's name to its own data settings (features, ``block_s``,
    ``run_offsets``, ``in_sample``: see ``_train``), as a ``_global_`` model yaml sets them.

    Returns
    -------
    dict
        ``floor_dps`` and ``touched_blocks`` per run, and ``rows``: one per model and variant, with
        ``ratio`` per held-out run (x, y, z) and the share of its samples outside the trained range.
        The variant "own constant, in box" scores only the held-out samples inside the training
        runs' temperatures, with the run's own mean removed (``score`` with ``box_c``).
    """
    train_cfg = {"progress": False, **dict(train_cfg or {})}
    score_from_s = max(score_from_s, startup_s)
    # train.py's checks on the runs, before any training: a run named twice or copied (a fold scored in sample),
    # mixed rates, a run too short to score after its window, a glitch row left out
    runs = load_runs([str(p) for p in paths], PAPER_FEATURES)
    check_long_enough(runs, score_from_s, BLOCK_S)
    names = [r.name for r in runs]  # unique: two runs named run.csv in two folders are run and run_1
    recordings = {r.name: r.recording for r in runs}
    floors = {r.name: floor_dps(_accepted(r)) for r in runs}
    touched = {n: touched_blocks(r) for n, r in recordings.items()}
    rows: dict[str, dict[str, Any]] = {}
    for k, held in enumerate(names):
        recording = recordings[held]
        others = [p for j, p in enumerate(paths) if j != k]
        box_c = (min(r.temp_c.min() for r in runs if r.name != held), max(r.temp_c.max() for r in runs if r.name != held))
        for model_name, make_model in models.items():
            options = dict((data_options or {}).get(model_name) or {})
            offsets_allowed = options.pop("run_offsets", True) and make_model is not None
            variants = [False] + ([True] if run_offsets and offsets_allowed and len(others) >= 2 else [])
            for with_offsets in variants:
                label = model_name + (" + run offsets" if with_offsets else "")
                if make_model is None:
                    compensator, oor = None, np.zeros(len(recording), bool)
                else:
                    log.info("%s: training on %s", label, ", ".join(n for n in names if n != held))
                    compensator = _train(make_model, others, with_offsets, train_cfg, seed, options)
                rates = {}
                for still_s in (0.0, startup_s):
                    if compensator is None:
                        rate = recording.gyro_dps
                        if still_s:
                            t = recording.time_s
                            rate = rate - rate[t < t[0] + still_s].mean(0)
                    else:
                        compensator.use_startup(still_s=still_s)
                        compensator.reset()
                        out = compensator.process(recording.columns)
                        rate, oor = out.rate_dps, out.out_of_range
                    rates[f"startup {still_s:g} s" if still_s else "none"] = rate
                rates["own constant, in box"] = rates["none"]
                for offset, rate in rates.items():
                    row = rows.setdefault(f"{label} | {offset}", {"model": label, "offset": offset, "ratio": {},
                                                                  "out_of_range_fraction": {}})
                    row["ratio"][held] = score(recording, rate, score_from_s, floors[held], touched[held],
                                               box_c if offset.endswith("in box") else None).tolist()
                    row["out_of_range_fraction"][held] = float(np.mean(oor))
                    log.info("held out %s, %s, %s: %s", held, label, row["offset"],
                             np.round(row["ratio"][held], 2).tolist())
    return {"runs": dict(zip(names, map(str, paths))), "floor_dps": {n: f.tolist() for n, f in floors.items()},
            "touched_blocks": {n: int(t.sum()) for n, t in touched.items()}, "startup_s": startup_s,
            "score_from_s": score_from_s, "rows": rows}


def to_markdown(table: Mapping[str, Any], reference: str = "poly3") -> str:
    """One row per model and offset variant; per held-out run: x, y, z, their mean, and that mean / the cubic's."""
    runs = list(table["runs"])
    head = "| model | offset | " + " | ".join(f"held out {r}: x | y | z | mean | /cubic" for r in runs) + " |"
    lines = [head, "|" + "---|" * (head.count("|") - 1)]
    for row in table["rows"].values():
        ref = table["rows"].get(f"{reference} | {row['offset']}")
        cells = []
        for run in runs:
            ratio = np.asarray(row["ratio"][run])
            rel = np.mean(ratio) / np.mean(ref["ratio"][run]) if ref else float("nan")
            cells += [f"{v:.2f}" for v in ratio] + [f"{np.mean(ratio):.2f}", f"{rel:.2f}"]
        lines.append(f"| {row['model']} | {row['offset']} | " + " | ".join(cells) + " |")
    floors = "; ".join(f"{r}: " + " / ".join(f"{v:.4f}" for v in table["floor_dps"][r]) for r in runs)
    ref_row = table["rows"].get(f"{reference} | none")
    oor = "; ".join(f"{r}: {ref_row['out_of_range_fraction'][r]:.0%}" for r in runs) if ref_row else ""
    lines += ["", f"Residual / floor per axis (60 s block RMS from {table['score_from_s']:g} s on), each run held out "
              f"in turn and the models trained on the others; /cubic: the mean over axes / the PX4 cubic's "
              f"(same offset). Floor (deg/s, "
              f"x / y / z, Allan deviation at 60 s in the cold dwell): {floors}. Touched 60 s blocks skipped: "
              f"{table['touched_blocks']}. Held-out samples outside the trained temperatures: {oor or 'n/a'}."]
    return "\n".join(lines) + "\n"


__all__ = ["cold_dwell", "floor_dps", "held_out_table", "score", "to_markdown", "touched_blocks"]
