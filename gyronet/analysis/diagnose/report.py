"""The human side of a diagnosis: ``report.md`` and its figures (residual before and after).

The figures show 60 s block means of the residual (gyro minus the static rate minus the model's
drift estimate, run causally at the full rate) of the baseline and the final network: against
time, against temperature, and against the feature of each effect found. They use the separate
validation recording when there is one, else the training record (both networks were trained on
most of it, so the figures show fit, and the numbers in the tables show held-out error).
"""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from gyronet.recordings.data import AXES
from gyronet.analysis.diagnose.candidates import describe
from gyronet.analysis.diagnose.report_figures import write_figures
from gyronet.analysis.diagnose.rows import ScreenRows

log = logging.getLogger(__name__)


def data_notes(time_s: np.ndarray, temp_c: np.ndarray, n_blocks: int, options: Mapping[str, Any],
               gap_s: float = 0.0, n_shifts: int | None = None) -> list[str]:
    """What this record can and cannot show, from its block times and temperatures."""
    notes = []
    hours = (time_s[-1] - time_s[0]) / 3600.0
    steps = np.diff(temp_c)
    moving = np.abs(steps) > 0.02 * max(np.ptp(temp_c), 1e-9) / max(len(steps), 1) ** 0.5
    rising = float(np.mean(steps[moving] > 0)) if moving.any() else 0.5
    if rising < 0.05 or rising > 0.95:
        notes.append(f"The temperature only {'rises' if rising > 0.5 else 'falls'}: there is no reversal, so "
                     "heating versus cooling (hysteresis) cannot be seen, and a hysteresis term would be a "
                     "constant offset here.")
    if len(time_s) > 2:
        corr = float(np.corrcoef(time_s, temp_c)[0, 1]) if np.ptp(temp_c) > 0 else 0.0
        if abs(corr) > 0.9:
            notes.append(f"Time and temperature are confounded (correlation {corr:.2f} over the blocks): a drift "
                         "in time (warm-up, ageing) and a drift in temperature explain the same data nearly "
                         "equally, so the model's split between them is a guess that another thermal history "
                         "would have to confirm.")
    n_shifts = options["n_shifts"] if n_shifts is None else n_shifts
    floor = 1 / (n_shifts + 1)
    notes.append(f"{n_blocks} blocks of {options['block_s']:g} s over {hours:.2f} h allow {n_shifts} distinct circular "
                 f"shifts, so the smallest p-value is {floor:.3g}; the test uses alpha = {options['alpha']:g}"
                 + (": no candidate can pass on this record, however large its gain." if floor > options["alpha"]
                    else "."))
    if n_blocks < 100:
        notes.append("So few blocks give the test little power: only large effects can pass, and the "
                     "cross-validation folds hold few blocks each.")
    if gap_s > 0:
        notes.append(f"The record has breaks (longest {gap_s:.0f} s): the causal filters restart after each, "
                     "so slow lags and warm-ups are only partly observable.")
    return notes


def rivals(candidates: Sequence[Mapping[str, Any]], within: float = 0.1) -> list[str]:
    """Names of the best candidates of other kinds or sources whose score is within ``within`` of the best."""
    from gyronet.analysis.diagnose.candidates import family

    if not candidates or candidates[0]["score"] <= 0:
        return []
    best, seen, out = candidates[0], {family(candidates[0]["spec"])}, []
    for c in candidates[1:]:
        fam = family(c["spec"])
        if fam not in seen and c["score"] >= (1 - within) * best["score"]:
            out.append(c["name"])
        seen.add(fam)
    return out


def evidence(spec: Mapping[str, Any], score: float, rmse_after: np.ndarray, index: int, result: Any,
             axes: Sequence[str], alpha: float, min_gain: float, confirmed: float, confirm_gain: float) -> str:
    """The one sentence of an effect that a person can check against the report's tables."""
    from gyronet.model.features import feature_name

    before = ", ".join(f"{a} {result.rmse_before[AXES.index(a)]:.3g}" for a in axes)
    after = ", ".join(f"{a} {rmse_after[AXES.index(a)]:.3g}" for a in axes)
    beaten = int((result.null_max >= result.score[index]).sum())
    grid_point = result.names[index]
    refined = "" if feature_name(spec) == grid_point else f" (refined from {grid_point})"
    # the shift test ran on the grid: a refined effect's p-value is its grid point's, said so
    tested = "it" if not refined else f"its grid point {grid_point} (score {result.score[index]:.3g})"
    held_out = ("a separate recording" if result.n_folds == 1
                else f"{result.n_folds}-fold cross-validation over time spans")
    return (f"Added to the network's frozen regressors (its output layer refitted), {describe(spec)}{refined} cut "
            f"the held-out 60 s residual ({held_out}, {result.n_rows} blocks) from {before} to {after} deg/s, "
            f"score {score:.3g} >= {min_gain:g}; against {tested}, the best of all {len(result.names)} candidates "
            f"did as well in {beaten} of {len(result.null_max)} circular time shifts (family-wise p = "
            f"{result.p_value[index]:.3g} <= {alpha:g}); the network retrained with it confirms it on its own "
            f"held-out residual (the table below: score {confirmed:.3g} >= {confirm_gain:g}).")


def approximation_sentence(spec: Mapping[str, Any], score: float, approximations: Sequence[Mapping[str, Any]]) -> str:
    """The sentence that names the measured columns a derived effect approximates ('' if none)."""
    if not approximations:
        return ""
    named = "; ".join(f"{describe(a['spec'])} (`{a['name']}`, score {a['score']:.3g}, correlation "
                      f"{a['corr']:.3g} once the model's own regressors are removed)" for a in approximations)
    first = approximations[0]["spec"]["source"]
    return (f" It approximates a measured column: {named}, against {score:.3g} for {describe(spec)}. "
            f"Look at what `{first}` measures before looking for a lag or a state inside the package.")


def _rmse_row(label: str, values: Mapping[str, float]) -> str:
    return f"| {label} | " + " | ".join(f"{values[a]:.4g}" for a in AXES) + " |"


def params_text(params: Mapping[str, Any]) -> str:
    """An effect's parameters for a reader (`` (tau_s 389)``), or nothing; a zero lag or free count says nothing."""
    shown = [f"{k} {v:g}" if isinstance(v, float) else f"{k} {v}" for k, v in params.items() if v not in (0, 0.0, None)]
    return f" ({', '.join(shown)})" if shown else ""


def alternatives_lines(effect: Mapping[str, Any]) -> list[str]:
    """The sentence that names an effect's equivalent explanations, if it has any."""
    alternatives = effect.get("alternatives") or []
    if not alternatives:
        return []
    names = "; ".join(f"`{a['kind']}` of `{a['source']}`{params_text(a['params'])} (score {a['score']:.3g})"
                      for a in alternatives)
    return [f"Equally good within the screen's own noise: {names}. This record cannot tell them apart; the "
            f"effect kept is the first of them that the retrained network confirmed, tried simplest first and, "
            f"of equal freedom, in this order: a recording column as it is or the clock's own shapes, then a "
            f"recording column through a lag, then what is derived from the temperature (a lag of it last).", ""]


def write_report(out_dir: Path, diagnosis: Mapping[str, Any], details: Mapping[str, Any], rows: ScreenRows,
                 stages: Sequence[Any], plots: bool = True) -> Path:
    """Write ``out_dir/report.md`` (and its PNG figures when ``plots``), ending with what to record next."""
    options = details["options"]
    record = len(rows.recordings) - 1  # the separate validation recording, when there is one
    training = rows.recordings[0]
    lines = [f"# Diagnosis of {training.path}", ""]
    span_h = (training.time_s[-1] - training.time_s[0]) / 3600.0
    lines += [f"{len(training)} samples at {training.fs_hz:g} Hz over {span_h:.2f} h, temperature "
              f"{training.temp_c.min():.1f} to {training.temp_c.max():.1f} degC.", "",
              "Declared inputs: " + ", ".join(f"`{n}`" for n in diagnosis["baseline"]["inputs"]) + ".", ""]
    lines += ["## Result", "", "Held-out 60 s residual of the networks, deg/s "
              f"({'the separate validation recording' if record else 'held-out time blocks, pooled over the cross-validation folds'}):", "",
              "| model | " + " | ".join(AXES) + " |", "| --- | --- | --- | --- |",
              _rmse_row("baseline", diagnosis["baseline"]["val_rmse_dps"]),
              _rmse_row("final", diagnosis["final"]["val_rmse_dps"]), ""]
    n_shifts = details["rounds"][0]["n_shifts"] if details["rounds"] else options["n_shifts"]
    if not diagnosis["effects"] and 1 / (n_shifts + 1) > options["alpha"]:
        log.warning("no effect can be shown: the record is too short for the test to pass anything at alpha = %g "
                    "(an empty effects list here is not 'nothing missing'; %s)", options["alpha"], out_dir / "report.md")
        lines += ["**No effect can be shown.** The record is too short for the test to pass anything at alpha = "
                  f"{options['alpha']:g} (see below); the candidates' scores are listed for what they suggest. "
                  "The final bundle is the baseline.", ""]
    elif not diagnosis["effects"]:
        lines += ["**No effect found.** No candidate lowered the held-out residual by more than chance and "
                  "the multiple comparisons allow and held on confirmation: as far as this record can tell, the "
                  "declared inputs explain the drift"
                  + (", but not the columns left untried (below)" if training.dropped or details.get("untried_columns")
                     else "")
                  + ". The final bundle is the baseline.", ""]
    close = rivals(details["rounds"][-1]["candidates"]) if details["rounds"] else []
    if close:
        lines += [f"In the last round, `{details['rounds'][-1]['candidates'][0]['name']}` and "
                  + ", ".join(f"`{n}`" for n in close) + " score within 10 % of each other: this record cannot "
                  "tell these explanations apart.", ""]
    for k, effect in enumerate(diagnosis["effects"], start=1):
        lines += [f"### {k}. `{effect['kind']}` of `{effect['source']}`{params_text(effect['params'])}, axes "
                  f"{', '.join(effect['axes'])}", "", effect["evidence"], "",
                  "| network's held-out 60 s residual | " + " | ".join(AXES) + " |", "| --- | --- | --- | --- |",
                  _rmse_row("before", effect["val_rmse_before_dps"]),
                  _rmse_row("after", effect["val_rmse_after_dps"]), ""]
        lines += alternatives_lines(effect)
    lines += ["Final inputs: " + ", ".join(f"`{n}`" for n in diagnosis["final"]["inputs"]) + ".", ""]
    lines += ["## How it was tested", "",
              f"Every candidate (temperature through other lags, heating versus cooling, powers of T, every "
              f"other column as it is and lagged, warm-up and ageing in time) was added alone to the current "
              f"network's frozen regressors and its output layer refitted; the score is the drop in the "
              f"held-out sum of squares of the 60 s residual ({options['n_folds']}-fold cross-validation over "
              f"interleaved {options['span_s']:g} s spans, or the separate recording), summed over the axes. "
              f"A candidate passes when no more than a fraction alpha = {options['alpha']:g} of "
              f"{n_shifts} circular time shifts of all candidates gives any candidate a score as "
              f"high (a family-wise test over every candidate), and its score is at least "
              f"{options['min_gain']:g}. Lagged candidates are scored as if their filter had started on the mean "
              f"of the first block, not on one noisy sample. A candidate that passes is then added and the network retrained; it is "
              f"kept only if the retrained network's own held-out residual drops by a score of at least "
              f"{options['confirm_gain']:g} (a real but negligible association, such as the baseline's own small "
              f"imperfections on a long record, passes the first test but not this one).", ""]
    for r, round_ in enumerate(details["rounds"], start=1):
        lines += [f"Round {r}: {round_['n_candidates']} candidates; the {1 - options['alpha']:.0%} quantile of the "
                  f"best shifted score is {round_['null_max_quantile']:.3g}.", "",
                  "| candidate | score | p | gain x | gain y | gain z |", "| --- | --- | --- | --- | --- | --- |"]
        lines += [f"| `{c['name']}` | {c['score']:.3g} | {c['p_value']:.3g} | "
                  + " | ".join(f"{c['gain'][a]:.3g}" for a in AXES) + " |" for c in round_["candidates"][:6]]
        lines.append("")
        for tried in round_.get("tried", []):
            verdict = "kept" if tried["confirm"] >= options["confirm_gain"] else "not confirmed"
            lines.append(f"- tried `{tried['spec']}`: screen score {tried['score']:.3g}, retrained held-out score "
                         f"{tried['confirm']:.3g}: {verdict}.")
        if round_.get("tried"):
            lines.append("")
    gaps = np.diff(training.time_s)
    gap_s = float(gaps.max()) if gaps.max() > 1.5 * np.median(gaps) else 0.0
    mask = rows.recording == 0
    temp_blocks = rows.features([{"kind": "temp"}])[mask, 0]
    lines += ["## What this record can and cannot show", ""]
    lines += [f"- {note}" for note in data_notes(rows.time_s[mask], temp_blocks, int(mask.sum()), options, gap_s,
                                                 n_shifts)]
    lines += [f"- `{name}` was logged but the loader dropped it ({why}): nothing of it was tried. Fill or cut those "
              "rows and diagnose again." for name, why in training.dropped.items()]
    lines += [f"- `{name}` is in the training record but missing or constant in `data.val_path`: nothing of it was "
              "tried. Give a validation record that logs it." for name in details.get("untried_columns", [])]
    if details.get("n_blocks_outside"):
        lines.append(f"- {details['n_blocks_outside']} blocks lie outside the temperature range the networks were "
                     "trained on (the held-out time blocks reach beyond it): the screen leaves them out, since "
                     "there the network is clamped and any candidate that extrapolates would win for the wrong "
                     "reason, and so do the networks' held-out numbers above.")
    lines.append("")
    from gyronet.analysis.diagnose.advice import (advice_lines, alternatives_advice, rate_tau_of, record_advice,
                                                  runs_advice)
    from gyronet.analysis.diagnose.candidates import source_columns

    advice = record_advice(training.time_s, training.temp_c, training.fs_hz, source_columns(training),
                           rate_tau_of(stages[0].data.features))
    advice += alternatives_advice(diagnosis["effects"]) + ([] if record else runs_advice([None]))
    if plots:
        figures = write_figures(out_dir, rows, stages, record)
        lines += ["## Figures", "", "Baseline and final residual, 60 s means"
                  f" ({'validation recording' if record else 'training record; grey: the held-out time blocks'}).",
                  ""]
        lines += [f"![{name}]({name})" for name in figures]
        lines.append("")
    lines += advice_lines(advice)
    path = out_dir / "report.md"
    path.write_text("\n".join(lines))
    return path
