"""The table on the simulator's effects (docs/results/effects.md): each diagnosis's bundles scored on another history.

One row per simulated effect: what the diagnosis found, its held-out residual (``diagnosis.json``)
baseline -> final, and both bundles checked against the ground truth of a second recording of the
same sensor with another thermal history (the drift estimate's error and the residual over the
noise floor, in 60 s blocks). ``scripts/effects_table.py`` makes the recordings and runs the
diagnoses; this module only reads what they wrote.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from gyronet.atomic import write_json, write_text
from gyronet.bundle.compensator import Compensator
from gyronet.recordings.data import AXES, load_recording, load_truth
from gyronet.training.dataset import block_rmse
from gyronet.training.train import residual_report

COLUMNS = ["effect in the data", "found, in order", "held-out, mdps: baseline -> final",
           "drift error elsewhere, mdps", "residual / noise floor elsewhere"]


def check_bundle(bundle: str | os.PathLike, path: str | os.PathLike, block_s: float = 60.0) -> dict[str, Any]:
    """Score a bundle where it matters: on a history it never saw, against the simulator's true drift.

    Returns the RMS over ``block_s`` blocks of the drift estimate minus the true drift per axis
    (``drift_error_dps``) and over all axes (``drift_error_all_dps``), ``residual_report``'s
    residual over the noise floor, and the share of samples inside the trained temperature range:
    only those are scored (outside, the compensator flags them).
    """
    recording, truth = load_recording(path), load_truth(path).columns
    out = Compensator.load(bundle).process(recording.columns)
    inside = ~out.out_of_range
    time_s = recording.time_s[inside]
    true_drift = np.column_stack([truth[f"drift_{a}_dps"] for a in AXES])
    error = block_rmse(time_s, (out.drift_dps - true_drift)[inside], block_s)
    report = residual_report(time_s, out.rate_dps[inside], {k: v[inside] for k, v in truth.items()}, block_s)
    return {"drift_error_dps": dict(zip(AXES, error.tolist())),
            "drift_error_all_dps": float(np.sqrt(np.mean(error**2))),
            "ratio_to_floor": report["ratio_to_floor"], "inside_share": float(inside.mean())}


def effect_row(effect: str, diagnosis: Mapping[str, Any], baseline: Mapping[str, Any],
               final: Mapping[str, Any]) -> dict[str, Any]:
    """Gather one effect's figures once, so the JSON's row and the Markdown's line cannot disagree.

    ``diagnosis`` is ``diagnosis.json``; ``baseline`` and ``final`` are ``check_bundle`` of its two bundles.
    """
    found = [{k: e[k] for k in ("kind", "source", "params", "axes", "alternatives")} for e in diagnosis["effects"]]
    held_out = {part: diagnosis[part]["val_rmse_dps"] for part in ("baseline", "final")}
    return {"effect": effect, "found": found, "held_out_dps": held_out,
            "check": {"baseline": dict(baseline), "final": dict(final)},
            "drift_error_ratio": final["drift_error_all_dps"] / baseline["drift_error_all_dps"]}


def _named(effect: Mapping[str, Any]) -> str:
    params = " ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in effect["params"].items())
    return f"{effect['kind']} `{effect['source']}` {params}".rstrip()


def found_text(found: Sequence[Mapping[str, Any]]) -> str:
    """Name what was found as docs/results/effects.md does, kind, source and parameter (``lag `temp_c` tau_s=1773``),
    each effect's equivalent explanations in brackets (``(or lag `temp_c` tau_s=2018)``)."""
    if not found:
        return "nothing"
    parts = []
    for effect in found:
        alternatives = effect.get("alternatives") or []
        others = f" (or {'; '.join(_named(a) for a in alternatives)})" if alternatives else ""
        parts.append(_named(effect) + others)
    return ", ".join(parts)


def _axes(values: Mapping[str, float], scale: float, digits: int) -> str:
    """Put x/y/z in one cell, as every column of the effects table does."""
    return "/".join(f"{values[a] * scale:.{digits}f}" for a in AXES)


def to_markdown(rows: Sequence[Mapping[str, Any]]) -> str:
    """Print the table as docs/results/effects.md shows it, so a re-run is pasted in as it is: one line per effect."""
    lines = ["| " + " | ".join(COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    for row in rows:
        held, base, final = row["held_out_dps"], row["check"]["baseline"], row["check"]["final"]
        cells = [row["effect"], found_text(row["found"]),
                 f"{_axes(held['baseline'], 1e3, 1)} -> {_axes(held['final'], 1e3, 1)}",
                 f"{_axes(base['drift_error_dps'], 1e3, 1)} -> {_axes(final['drift_error_dps'], 1e3, 1)} "
                 f"({row['drift_error_ratio']:.2f})",
                 f"{_axes(base['ratio_to_floor'], 1, 2)} -> {_axes(final['ratio_to_floor'], 1, 2)}"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def write_table(rows: Sequence[Mapping[str, Any]], output: str | os.PathLike, settings: Mapping[str, Any]) -> Path:
    """Keep every figure and the settings that made them (JSON) beside the Markdown, each file whole or not at all."""
    output = Path(output)
    output.parent.mkdir(parents=True, exist_ok=True)
    write_text(output, to_markdown(rows))
    everything = {"settings": dict(settings), "rows": list(rows)}
    write_json(output.with_suffix(".json"), everything)
    return output


__all__ = ["COLUMNS", "check_bundle", "effect_row", "found_text", "to_markdown", "write_table"]
