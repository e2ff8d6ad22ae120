"""``report.md`` of a campaign of several runs, apart from ``runs.diagnose_runs`` so that runs.py stays short."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Mapping, Sequence

from gyronet.atomic import write_text
from gyronet.recordings.data import AXES
from gyronet.analysis.diagnose.advice import advice_lines
from gyronet.analysis.diagnose.report import alternatives_lines, params_text


def write_runs_report(out_dir: Path, diagnosis: Mapping[str, Any], details: Mapping[str, Any],
                      orientations: Sequence[str | None], advice: Sequence[Any], figures: Sequence[str] = ()) -> None:
    """Write ``out_dir/report.md`` of a campaign: the result, each effect, how it was tested, its ``figures`` (file
    names in ``out_dir``), what to record next."""
    runs = details["runs"]
    lines = [f"# Diagnosis of a campaign of {len(runs)} runs", "",
             "Runs: " + ", ".join(f"`{r['name']}` ({r['orientation'] or 'no accelerometer'})" for r in runs) + ".", "",
             "## Result", "", "Held-out 60 s residual, deg/s (leave-one-run-out, mean over the held-out runs):", "",
             "| model | x | y | z |", "| --- | --- | --- | --- |"]
    for label in ("baseline", "final"):
        lines.append(f"| {label} | " + " | ".join(f"{diagnosis[label]['val_rmse_dps'][a]:.4g}" for a in AXES) + " |")
    lines.append("")
    # the smallest p a test of n deals can give is 1 / (n + 1): with too few, neither test can pass anything
    first = details["rounds"][0] if details["rounds"] else {}
    deals = max(first.get("n_shifts", 0), first.get("run_n_shifts", 0))
    alpha = details["options"]["alpha"]
    if not diagnosis["effects"] and deals and 1 / (deals + 1) > alpha:
        lines += [f"**No effect can be shown.** With {deals} deals of the runs' pieces the smallest p the tests "
                  f"can give is {1 / (deals + 1):.3g}, above alpha = {alpha:g}: the runs are too short for them "
                  "to pass anything. The candidates' scores are listed below for what they suggest; the final "
                  "bundle is the baseline.", ""]
    elif not diagnosis["effects"]:
        lines += ["**No effect found**: nothing constant within a run changes between the runs by more than the "
                  "runs change within themselves, and nothing within the runs passes the test. The final bundle "
                  "is the baseline.", ""]
    for k, effect in enumerate(diagnosis["effects"], start=1):
        lines += [f"### {k}. `{effect['kind']}` of `{effect['source']}`{params_text(effect['params'])}, axes "
                  f"{', '.join(effect['axes'])}", "", effect["evidence"], ""]
        lines += alternatives_lines(effect)
        if effect["kind"] == "run_offset" and effect["alternatives"]:
            lines += [f"With {len(runs)} runs in the orientations {', '.join(str(o) for o in orientations)}, a "
                      "per-run offset (turn-on bias) and the orientation columns above are the same contrast "
                      "between the runs: this campaign cannot separate them (see what to record next).", ""]
    lines += ["## How it was tested", ""]
    for r, round_ in enumerate(details["rounds"], start=1):
        if "run_level" in round_:
            lines += [f"Round {r}, run-level: the {1 - details['options']['alpha']:.0%} quantile of the best "
                      f"score under {round_['run_n_shifts']} deals of the runs' pieces (each with a within-run shift) is "
                      f"{round_['run_null_quantile']:.3g}.", "", "| candidate | score | p |", "| --- | --- | --- |"]
            lines += [f"| `{c['name']}` | {c['score']:.3g} | {c['p_value']:.3g} |" for c in round_["run_level"][:6]]
            lines.append("")
        if "candidates" in round_:
            lines += [f"Round {r}, within the runs: the {1 - details['options']['alpha']:.0%} quantile of the "
                      f"best shifted score is {round_['null_max_quantile']:.3g}.", "",
                      "| candidate | score | p |", "| --- | --- | --- |"]
            lines += [f"| `{c['name']}` | {c['score']:.3g} | {c['p_value']:.3g} |" for c in round_["candidates"][:6]]
            lines.append("")
        lines += [f"- tried `{t['spec']}`: score {t['score']:.3g}, confirmation {t['confirm']:.3g}"
                  + ("" if t.get("harmless", True) else ", but the held-out runs' residual as it is got worse")
                  + "." for t in round_["tried"]]
        if round_["tried"]:
            lines.append("")
    if figures:
        lines += ["## Figures", "", "Baseline and final residual, 60 s means, of the networks trained on every run "
                  "(fit, not held-out error: the tables above hold that).", ""]
        lines += [f"![{name}]({name})" for name in figures] + [""]
    lines += advice_lines(advice)
    write_text(out_dir / "report.md", "\n".join(lines))
