"""The survey's table: median, 90th percentile and worst of each sensor's worst axis, per method, and the goals."""
from __future__ import annotations

import csv
import io
import json
import logging
import os
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from gyronet.atomic import atomic_output, write_text
from gyronet.model.recalibration import HOUR_RMS_LIMIT
from gyronet.recordings.data import AXES
from gyronet.training.sigma_table import BELOW_RANGE, GOAL
from gyronet.errors import GyronetError
from gyronet.analysis.survey.scoring import VARIANTS
from gyronet.analysis.survey.sensor_run import describe_sensor

log = logging.getLogger(__name__)

VARIANT_TEXT = {"deployed": "as deployed (startup.still_s={startup_s:g})",
                "turn_on_removed": "turn-on bias from the truth", "as_is": "no start-up offset"}


def goal_keys(p90_max: float = 1.15, worst_max: float = 1.3, vs_reference_max: float = 1.0 / 3.0) -> dict[str, float]:
    """The goals a survey checks (the schema of ``conf/survey.yaml``'s ``goals``)."""
    return {"p90_max": p90_max, "worst_max": worst_max, "vs_reference_max": vs_reference_max}


def worst_axis(result: Mapping[str, Any], method: str, variant: str = "deployed") -> float:
    """A sensor's worst axis (largest residual / floor) for one method and scoring variant."""
    return float(max(result["methods"][method][variant]))


def summarize(results: Sequence[Mapping[str, Any]], ours: str, reference: str | None,
              goals: Mapping[str, float] | None = None) -> dict[str, Any]:
    """Every method's median, 90th percentile and worst over the sensors, the ratio to the reference, the goals.

    Parameters
    ----------
    results
        :func:`gyronet.analysis.survey.sensor_run.run_sensor` results, one per sensor.
    ours, reference
        The method the goals are about and the one it must beat (the PX4 cubic; None: no comparison).
    goals
        ``p90_max``, ``worst_max`` (residual / floor of the worst axis, ``deployed``) and
        ``vs_reference_max`` (ours / reference, worst axis, every sensor).

    Returns
    -------
    dict
        ``rows`` (method, variant, median, p90, worst, worst_sensor), ``vs_reference``, ``goals``,
        ``misses`` (sensor seed -> what it misses).
    """
    goals = goal_keys(**dict(goals or {}))
    failed = {int(r["sensor_seed"]): r["error"] for r in results if "error" in r}
    results = [r for r in results if "error" not in r]
    if not results:
        raise GyronetError(f"every sensor of the survey failed; the first: {next(iter(failed.values()))}")
    seeds = [int(r["sensor_seed"]) for r in results]
    methods = list(results[0]["methods"])
    rows = []
    for method in methods:
        for variant in VARIANTS:
            values = np.array([worst_axis(r, method, variant) for r in results])
            rows.append({"method": method, "variant": variant, "median": float(np.median(values)),
                         "p90": float(np.percentile(values, 90)), "worst": float(values.max()),
                         "worst_sensor": seeds[int(values.argmax())]})
    ours_worst = np.array([worst_axis(r, ours) for r in results])
    vs_reference, ratios = None, [None] * len(results)  # no reference (a survey of one method): no ratio, no goal
    if reference is not None:
        ratios = np.array([worst_axis(r, ours) / worst_axis(r, reference) for r in results])
        vs_reference = {"worst": float(ratios.max()), "median": float(np.median(ratios)),
                        "worst_sensor": seeds[int(ratios.argmax())]}
    misses: dict[int, list[str]] = {}
    for seed, value, ratio in zip(seeds, ours_worst, ratios):
        missed = [f"{value:.2f}x > {goals['p90_max']:g}x"] if value > goals["p90_max"] else []
        missed += [f"worst goal {goals['worst_max']:g}x"] if value > goals["worst_max"] else []
        if ratio is not None and ratio > goals["vs_reference_max"]:
            missed.append(f"/{reference} {ratio:.2f} > {goals['vs_reference_max']:.2f}")
        if missed:
            misses[seed] = missed
    ours_row = next(r for r in rows if r["method"] == ours and r["variant"] == "deployed")
    met = {"p90": ours_row["p90"] <= goals["p90_max"], "worst": ours_row["worst"] <= goals["worst_max"]}
    if vs_reference is not None:
        met["vs_reference"] = vs_reference["worst"] <= goals["vs_reference_max"]
    return {"n_sensors": len(results), "failed": failed, "seeds": seeds, "ours": ours, "reference": reference, "rows": rows,
            "vs_reference": vs_reference, "goals": goals, "met": met, "misses": misses,
            "error_bar": error_bar_summary(results, ours),
            "seconds_per_sensor": float(np.median([r["seconds"] for r in results]))}


def error_bar_arrays(results: Sequence[Mapping[str, Any]], method: str) -> tuple | None:
    """``method``'s error bar per sensor-axis: seeds, within 1 sigma (n, 3), the ranges a bar that holds gives
    (n, 3, 2; NaN for results made before they were scored) and the worst hour (n, 3); None without error bars."""
    scored = [r for r in results if "error" not in r and "error_bar" in r["methods"][method]]
    if not scored:
        return None
    bars = [r["methods"][method]["error_bar"] for r in scored]
    ranges = np.array([b.get("calibrated_range", [[np.nan, np.nan]] * 3) for b in bars], dtype=np.float64)
    return ([int(r["sensor_seed"]) for r in scored], np.array([b["within_1_sigma"] for b in bars]), ranges,
            np.array([b["worst_hour_rms_ratio"] for b in bars]))


def error_bar_summary(results: Sequence[Mapping[str, Any]], method: str) -> dict[str, Any] | None:
    """``method``'s error bar as deployed over the sensors: blocks within 1 sigma (pooled, and the spread over
    sensor-axes) and the sensors whose recalibration check asks on some axis; None without error bars."""
    arrays = error_bar_arrays(results, method)
    if arrays is None:
        return None
    seeds, within, ranges, hours = arrays
    known = np.isfinite(ranges[..., 0])  # results made before the range was scored have none
    return {"n_sensors": len(seeds), "within_1_sigma_pooled": float(within.mean()),
            "below_calibrated_range": [int((within < ranges[..., 0])[known].sum()), int(known.sum())],
            "within_1_sigma_p10": float(np.percentile(within, 10)), "within_1_sigma_p90": float(np.percentile(within, 90)),
            "in_goal_share": float(np.mean((within >= GOAL[0]) & (within <= GOAL[1]))),
            "worst_hour_rms_ratio_max": float(hours.max()),
            "recalibrate_sensors": [s for s, h in zip(seeds, hours) if h.max() > HOUR_RMS_LIMIT]}


def to_markdown(summary: Mapping[str, Any], settings: Mapping[str, Any]) -> str:
    """The survey's table (docs/results/survey.md), the ratio to the reference, the goals and the sensors that miss one."""
    ours, reference, goals, met = summary["ours"], summary["reference"], summary["goals"], summary["met"]
    lines = [f"Residual / noise floor of each sensor's worst axis, {summary['n_sensors']} sensors "
             f"(distribution {settings.get('distribution', '?')}), trained on {settings.get('train', '?')}, "
             f"scored on {settings.get('check', '?')} against the truth from t = {settings.get('startup_s', 0):g} s.",
             "", "| method | scored | median | 90th percentile | worst (sensor) |", "|---|---|---|---|---|"]
    for row in summary["rows"]:
        text = VARIANT_TEXT[row["variant"]].format(startup_s=settings.get("startup_s", 0))
        lines.append(f"| {row['method']} | {text} | {row['median']:.2f} | {row['p90']:.2f} | "
                     f"{row['worst']:.2f} ({row['worst_sensor']}) |")
    vs = summary["vs_reference"]
    ours_row = next(r for r in summary["rows"] if r["method"] == ours and r["variant"] == "deployed")

    def mark(ok: bool) -> str:
        return "met" if ok else "NOT met"

    goal_text = (f"Goals for {ours}, as deployed: 90th percentile <= {goals['p90_max']:g}x: {mark(met['p90'])} "
                 f"({ours_row['p90']:.2f}); worst <= {goals['worst_max']:g}x: {mark(met['worst'])} "
                 f"({ours_row['worst']:.2f})")
    if vs is not None:
        lines += ["", f"{ours} / {reference}, worst axis, as deployed: worst sensor {vs['worst']:.3f} "
                      f"(sensor {vs['worst_sensor']}), median {vs['median']:.3f}."]
        goal_text += (f"; every sensor at least {1 / goals['vs_reference_max']:.3g}x better than {reference}: "
                      f"{mark(met['vs_reference'])} (worst ratio {vs['worst']:.3f})")
    lines += ["", goal_text + ".", ""]
    bar = summary.get("error_bar")
    if bar:
        asks = bar["recalibrate_sensors"]
        lines += [f"{ours}'s error bar as deployed ({bar['n_sensors']} sensors): {100 * bar['within_1_sigma_pooled']:.0f} % of "
                  f"60 s blocks within 1 sigma of the drift error, pooled (goal {100 * GOAL[0]:.0f}-{100 * GOAL[1]:.0f} %; sensor-axes "
                  f"{100 * bar['within_1_sigma_p10']:.0f}-{100 * bar['within_1_sigma_p90']:.0f} % from the 10th to the 90th "
                  f"percentile, {100 * bar['in_goal_share']:.0f} % of them in the goal); allan.py's recalibration check "
                  f"asks on {len(asks)} sensor(s){' (' + ', '.join(map(str, asks)) + ')' if asks else ''}, worst hour "
                  f"{bar['worst_hour_rms_ratio_max']:.2f}x the bar.", ""]
        below, cells = bar["below_calibrated_range"]
        if cells:
            lines[-2] += f" Sensor-axes {BELOW_RANGE}: {below} of {cells}."
    misses = summary["misses"]
    lines.append("Sensors that miss a goal: " + ("none" if not misses else "; ".join(
        f"{seed} ({', '.join(what)})" for seed, what in sorted(misses.items(), key=lambda kv: int(kv[0])))) + ".")
    failed = summary.get("failed") or {}
    if failed:
        lines += ["", f"Failed, left out of every figure above ({len(failed)}): " + "; ".join(
            f"{seed} ({error})" for seed, error in sorted(failed.items(), key=lambda kv: int(kv[0]))) + "."]
    return "\n".join(lines) + "\n"


def sensors_csv(results: Sequence[Mapping[str, Any]]) -> str:
    """One row per sensor: each method's x, y, z and worst axis for every variant, and the sensor's figures."""
    results = [r for r in results if "error" not in r]
    methods = list(results[0]["methods"])
    header = ["sensor_seed", "sharpest_knee_c", "max_rate_gain_deg_per_c", "max_axis_lag_s"]
    header += [f"{m}:{v}:{a}" for m in methods for v in VARIANTS for a in (*AXES, "worst")]
    header += ["seconds"]
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(header)
    for r in sorted(results, key=lambda r: int(r["sensor_seed"])):
        figures = describe_sensor(r["sensor"])
        cells: list[Any] = [r["sensor_seed"], f"{figures['sharpest_knee_c']:.2f}",
                            f"{figures['max_rate_gain_deg_per_c']:.2f}", f"{figures['max_axis_lag_s']:.1f}"]
        for m in methods:
            for v in VARIANTS:
                values = r["methods"][m][v]
                cells += [f"{x:.4f}" for x in values] + [f"{max(values):.4f}"]
        cells.append(f"{r['seconds']:.1f}")
        writer.writerow(cells)
    return out.getvalue()


def write_outputs(results: Sequence[Mapping[str, Any]], summary: Mapping[str, Any], settings: Mapping[str, Any],
                  output: str | os.PathLike) -> Path:
    """``output`` (Markdown), and beside it ``.json`` (summary, settings, every sensor), ``_sensors.csv`` and ``.png``."""
    output = Path(output)
    output.parent.mkdir(parents=True, exist_ok=True)
    write_text(output, to_markdown(summary, settings))
    everything = {"summary": summary, "settings": settings,
                  "sensors": [{k: v for k, v in r.items() if k != "reused"} for r in results]}
    write_text(output.with_suffix(".json"), json.dumps(everything, indent=1, default=str) + "\n")
    write_text(output.with_name(output.stem + "_sensors.csv"), sensors_csv(results))
    from gyronet.figures.plots import plt, survey_figure

    arrays = error_bar_arrays(results, summary["ours"])
    figure = survey_figure(results, summary["ours"], summary["goals"], None if arrays is None else arrays[1:3], GOAL)
    with atomic_output(output.with_suffix(".png")) as tmp:
        figure.savefig(tmp, format="png", dpi=110)
    plt.close(figure)
    return output
