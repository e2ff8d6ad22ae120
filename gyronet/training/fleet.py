"""Fleet calibration: one chamber run per unit, one bundle per unit, one table of every unit's figures.

A production line calibrates hundreds of units. ``scripts/fleet.py`` expands a file pattern into
units and runs ``scripts/train.py`` once per unit through whatever Hydra launcher is configured
(joblib, submitit_local, submitit_slurm); each job's folder is named after its unit. This module
has the parts that need no Hydra: naming the units, the overrides that sweep them, and the table.

A unit's name is its file's path below the pattern's fixed folder, without the ``.csv`` (or
``.csv.gz``) suffix: ``units/line2/sn0042.csv`` under ``units/`` is ``line2/sn0042``. The
simulator's ground-truth files beside its recordings (``*.truth.csv``) are not units.
"""
from __future__ import annotations

import glob
import json
import logging
import math
import os
import re
import shutil
from pathlib import Path
from typing import Any, Mapping, Sequence

from gyronet.atomic import write_json, write_text
from gyronet.errors import GyronetError
from gyronet.recordings.data import AXES, TRUTH_SUFFIX

log = logging.getLogger(__name__)

UNITS_FILE = "fleet_units.json"  # written in the sweep folder before the jobs start
SUFFIXES = (".csv.gz", ".csv")
UNIT_KEY = "unit"  # the config key each job gets (+unit=...), also its folder (hydra.sweep.subdir)
PREVIOUS = "previous"  # in a unit's folder: its earlier run's outputs, set aside when it runs again
_OUTPUTS = ("report.json", "compensator", "tb")  # what a unit's job writes into its folder, besides its logs
_UNSAFE = ("$", "'", "\\", "\n")  # would break the quoted Hydra override or start an interpolation


def find_units(pattern: str) -> tuple[dict[str, str], str, str]:
    """The units a file pattern names.

    Parameters
    ----------
    pattern
        A glob pattern (``**`` allowed), e.g. ``units/*.csv``.

    Returns
    -------
    units, root, suffix
        Unit name -> recording path (sorted by name); the folder the names are relative to; the
        suffix every file shares.

    Raises
    ------
    GyronetError
        No file matches, the files are not all ``.csv`` or all ``.csv.gz``, or a name cannot be an override.
    """
    paths = sorted(p for p in glob.glob(pattern, recursive=True) if Path(p).is_file())
    truths = [p for p in paths if p.endswith((TRUTH_SUFFIX, TRUTH_SUFFIX + ".gz"))]
    if truths:
        log.info("fleet: %d simulator ground-truth file(s) (*%s) are not units", len(truths), TRUTH_SUFFIX)
        paths = [p for p in paths if p not in truths]
    if not paths:
        raise GyronetError(f"no file matches {pattern!r} (relative to {os.getcwd()})")
    suffix = next((s for s in SUFFIXES if all(p.endswith(s) for p in paths)), None)
    if suffix is None:
        kinds = sorted({next((s for s in SUFFIXES if p.endswith(s)), Path(p).suffix or Path(p).name) for p in paths})
        raise GyronetError(f"{pattern!r} matches files that are not recordings of one kind ({', '.join(kinds)}); "
                           "a fleet trains on CSV recordings (all .csv or all .csv.gz): convert others first "
                           "with scripts/convert.py, or narrow the pattern")
    root = pattern_root(pattern)
    units = {Path(os.path.relpath(p, root)).as_posix()[: -len(suffix)]: p for p in paths}
    bad = [p for p in [root, *units] if any(c in p for c in _UNSAFE)]
    if bad:
        raise GyronetError(f"unit path {bad[0]!r} has one of {' '.join(_UNSAFE[:3])}, which Hydra overrides "
                           "cannot carry; rename the file")
    return units, root, suffix


def pattern_root(pattern: str) -> str:
    """The pattern's fixed folder (before its first glob character): the same for a whole fleet and a re-run of
    one of its units (``units/**/sn0042.csv``), where the matches' common folder would rename the unit."""
    fixed = []
    for part in Path(pattern).parts[:-1]:
        if re.search(r"[*?[]", part):
            break
        fixed.append(part)
    return os.path.join(*fixed) if fixed else "."


def sweep_overrides(units: Mapping[str, str], root: str, suffix: str) -> list[str]:
    """The Hydra overrides that run one job per unit, in a folder named after it."""
    names = ",".join(f"'{name}'" for name in units)  # quoted: a unit named 007 stays a string
    path = Path(root).as_posix()
    return [f"+{UNIT_KEY}={names}", f"data.path='{path}/${{{UNIT_KEY}}}{suffix}'",
            f"hydra.sweep.subdir=${{{UNIT_KEY}}}"]


def write_units(sweep_dir: str | os.PathLike, units: Mapping[str, str]) -> Path:
    """Record the fleet's units in the sweep folder, so the table also lists units whose job never ran; added to
    the units already listed there (a re-run of some units keeps the others in the table)."""
    path = Path(sweep_dir) / UNITS_FILE
    listed = json.loads(path.read_text())["units"] if path.is_file() else {}
    same = lambda p, q: os.path.realpath(p) == os.path.realpath(q)  # noqa: E731 - ./units/a.csv is units/a.csv
    renamed = [(old, name) for old, p in listed.items() for name, q in units.items() if same(p, q) and old != name]
    if renamed:
        old, name = renamed[0]
        raise GyronetError(f"{units[name]} is unit {old!r} in {path}, here {name!r}: give the pattern the fleet's "
                           f"fixed folder, e.g. glob(<folder>/**/{Path(units[name]).name}), or use another hydra.sweep.dir")
    path.parent.mkdir(parents=True, exist_ok=True)
    write_json(path, {"units": {**listed, **units}})
    return path


def set_aside_outputs(job_dir: str | os.PathLike) -> None:
    """As a unit's job starts again: a complete earlier run (report and bundle) moves into ``<job dir>/previous/``,
    replacing the one there; a failed run's leftovers (its ``tb/``) are removed, so ``previous/`` keeps the last
    good run through any number of failed re-runs, and the table never reads an earlier run as this one's."""
    job_dir = Path(job_dir)
    found = [job_dir / name for name in _OUTPUTS if (job_dir / name).exists()]
    complete = (job_dir / "report.json").is_file() and (job_dir / "compensator").is_dir()
    if complete:
        shutil.rmtree(job_dir / PREVIOUS, ignore_errors=True)
        (job_dir / PREVIOUS).mkdir()
    for output in found:
        if complete:
            output.rename(job_dir / PREVIOUS / output.name)
        elif output.is_dir():
            shutil.rmtree(output)
        else:
            output.unlink()


def check_spec_range(spec: Any, name: str = "spec_range_c") -> list[float] | None:
    """``[LOW, HIGH]`` in degC as floats (None stays None), checked before anything is trained or read."""
    if spec is None:
        return None
    numbers = isinstance(spec, (list, tuple)) and len(spec) == 2 and all(
        isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in spec)
    if not (numbers and spec[1] > spec[0]):
        raise GyronetError(f"{name} must be [LOW,HIGH] in degC with HIGH > LOW, got {spec!r}")
    return [float(v) for v in spec]


def fleet_table(sweep_dir: str | os.PathLike, spec_range_c: Sequence[float] | None = None) -> dict[str, Any]:
    """Every unit's figures from a fleet sweep folder.

    Parameters
    ----------
    sweep_dir
        The sweep folder (``hydra.sweep.dir``) with ``fleet_units.json`` and one folder per unit.
    spec_range_c
        The temperature range every unit must cover, degC (low, high); None: the union of the
        units' trained ranges.

    Returns
    -------
    dict
        ``reference_range_c`` and ``units``: per unit ``status`` (``ok`` or ``missing``: no
        ``report.json``, the job failed or has not finished), ``val_rmse_dps`` per axis (held-out
        time blocks, 60 s residual RMSE), ``temp_range_c`` (trained), ``out_of_range_share`` (the
        share of the reference range outside it, where the bundle's outputs are flagged),
        ``bundle``, ``recording``; and, with held-out recordings (``eval.paths``), the share of
        their samples out of range (``eval_out_of_range_share``).
    """
    spec_range_c = check_spec_range(spec_range_c)
    sweep_dir = Path(sweep_dir)
    listing = sweep_dir / UNITS_FILE
    if not listing.is_file():
        raise GyronetError(f"{sweep_dir}: no {UNITS_FILE}; is this a folder written by scripts/fleet.py?")
    units = json.loads(listing.read_text())["units"]
    rows = {name: _unit_row(sweep_dir / name, path) for name, path in units.items()}
    ranges = [r["temp_range_c"] for r in rows.values() if r["status"] == "ok"]
    if spec_range_c is not None:
        low, high = spec_range_c
    elif ranges:
        low, high = min(r[0] for r in ranges), max(r[1] for r in ranges)
    else:  # no unit trained: nothing to compare with
        low = high = None
    for row in rows.values():
        if row["status"] == "ok" and low is not None:
            row["out_of_range_share"] = _uncovered_share(row["temp_range_c"], low, high)
    return {"sweep_dir": str(sweep_dir), "reference_range_c": [low, high],
            "reference": "spec_range_c" if spec_range_c is not None else "union of the units' trained ranges",
            "n_units": len(rows), "n_ok": len(ranges), "units": rows}


def _unit_row(job_dir: Path, recording: str) -> dict[str, Any]:
    report_path, meta_path = job_dir / "report.json", job_dir / "compensator" / "meta.json"
    row: dict[str, Any] = {"recording": recording, "job_dir": str(job_dir)}
    if not (report_path.is_file() and meta_path.is_file()):
        reason = "no job folder" if not job_dir.is_dir() else \
            "no report.json (failed or not finished: its one-line error is on fleet.py's stderr, its log in train.log)"
        return {**row, "status": "missing", "reason": reason}
    try:
        report = json.loads(report_path.read_text())
        meta = json.loads(meta_path.read_text())
        metrics, evals = report["metrics"], report.get("eval") or {}
        row.update(status="ok", val_rmse_dps={a: float(metrics[f"val/rmse_{a}_dps"]) for a in AXES},
                   temp_range_c=[float(v) for v in meta["temp_range_c"]], bundle=str(job_dir / "compensator"))
        if evals:
            n_out = sum(r["n_out_of_range"] for r in evals.values())
            row["eval_out_of_range_share"] = n_out / max(sum(r["n_samples"] for r in evals.values()), 1)
    except (ValueError, KeyError, TypeError) as err:  # a damaged or foreign file: listed, not fatal
        return {**row, "status": "missing", "reason": f"unreadable report.json or meta.json ({type(err).__name__}: {err})"}
    return row


def _uncovered_share(trained_c: Sequence[float], low: float, high: float) -> float:
    """The share of [low, high] outside the trained range."""
    if not high > low:
        return 0.0
    covered = max(0.0, min(high, trained_c[1]) - max(low, trained_c[0]))
    return 1.0 - covered / (high - low)


def to_markdown(table: Mapping[str, Any]) -> str:
    """One line per unit: validation error per axis, trained range, out-of-range share, bundle."""
    low, high = table["reference_range_c"]
    head = f"Fleet {table['sweep_dir']}: {table['n_ok']} of {table['n_units']} units trained"
    if low is not None:
        head += (f"; out of range: share of [{low:.2f}, {high:.2f}] degC ({table['reference']}) outside the "
                 "unit's trained range")
    held = any("eval_out_of_range_share" in row for row in table["units"].values())  # eval.paths given
    heads = ["unit", "status", "val RMSE x", "y", "z", "trained range", "out of range",
             *(["held out, out of range"] if held else []), "bundle"]
    units = ["", "", "deg/s", "deg/s", "deg/s", "degC", "share", *(["share"] if held else []), ""]
    lines = [head + ".", "", _cells(heads), "|" + "---|" * len(heads), _cells(units)]
    for name, row in table["units"].items():
        if row["status"] != "ok":
            lines.append(_cells([name, f"{row['status']}: {row['reason']}", *[""] * (len(heads) - 2)]))
            continue
        t_low, t_high = row["temp_range_c"]
        share = row.get("eval_out_of_range_share")
        held_cell = [("-" if share is None else f"{share:.3f}")] if held else []
        rmse = [f"{row['val_rmse_dps'][a]:.4g}" for a in AXES]
        lines.append(_cells([name, "ok", *rmse, f"{t_low:.2f} to {t_high:.2f}", f"{row['out_of_range_share']:.3f}",
                             *held_cell, row["bundle"]]))
    return "\n".join(lines) + "\n"


def _cells(cells: Sequence[str]) -> str:
    return "| " + " | ".join(cells) + " |"


def write_table(table: Mapping[str, Any], output: str | os.PathLike) -> Path:
    """The table as Markdown at ``output`` and every figure as JSON beside it (``.json``), each whole or not at all."""
    output = Path(output)
    output.parent.mkdir(parents=True, exist_ok=True)
    write_text(output, to_markdown(table))
    write_json(output.with_suffix(".json"), table)
    return output


__all__ = ["UNITS_FILE", "check_spec_range", "find_units", "fleet_table", "pattern_root", "set_aside_outputs",
           "sweep_overrides", "to_markdown", "write_table", "write_units"]
