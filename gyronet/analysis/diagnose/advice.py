"""What the recording cannot show, and the cheapest recording that would show it.

Every item is computed from the data (the temperature history, the sample rate, the columns,
the runs' orientations, the equivalent explanations found) and carries a rough cost, so the
report can end with the cheapest experiment first. Nothing here is a fixed text about the
simulator: a record that shows everything still gets the one check no record can give itself,
another run held out entirely.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import numpy as np

# rough cost of each experiment, hours of recording or of set-up (only the order matters)
COST_H = {"log": 0.0, "rate": 0.0, "still": 0.2, "repeat": 12.0, "orientation": 12.0, "run": 12.0,
          "reverse": 12.0, "wider": 24.0}


@dataclass
class Advice:
    """One thing the recording cannot show and the experiment that would show it."""

    cost: str  # a key of COST_H
    cannot_show: str
    record: str
    decides: bool = False  # it would decide between explanations this diagnosis found equivalent

    def to_dict(self) -> dict[str, Any]:
        return {"cost_h": COST_H[self.cost], "cannot_show": self.cannot_show, "record": self.record,
                "decides": self.decides}


def _direction(time_s: np.ndarray, temp_c: np.ndarray, block_s: float = 300.0, min_step_c: float = 0.05) -> float:
    """Fraction of the moving ``block_s`` steps of the block-mean temperature that rise (0.5: it never moves)."""
    from gyronet.recordings.data import block_means

    steps = np.diff(block_means(temp_c, time_s, block_s))
    moving = np.abs(steps) > min_step_c
    return float(np.mean(steps[moving] > 0)) if moving.any() else 0.5


def rate_tau_of(features: Sequence[dict]) -> float:
    """The dT/dt tracker's time constant, s, of a stage's features (5 s where none says)."""
    return next((float(f.get("tau_s", 5.0)) for f in features if f["kind"] == "rate"), 5.0)


def record_advice(time_s: np.ndarray, temp_c: np.ndarray, fs_hz: float, columns: Sequence[str],
                  rate_tau_s: float = 5.0, still_s: float = 600.0, min_span_c: float = 30.0,
                  range_c: tuple[float, float] | None = None) -> list[Advice]:
    """Advice from one record's samples: its temperature history, rate and columns.

    Parameters
    ----------
    time_s, temp_c
        The record at the full rate (s, degC).
    fs_hz
        Its sample rate.
    columns
        Its auxiliary columns (candidates of kind ``column``).
    rate_tau_s
        The dT/dt tracker's time constant, s: fewer than 10 samples in it make dT/dt noisy.
    still_s
        The start-up window a deployed compensator averages (``startup.still_s``).
    min_span_c
        A temperature span below this is called narrow.
    range_c
        The range trained on, when it is not this record's (a campaign: the union of its runs).
    """
    out = []
    low_c, high_c = (float(temp_c.min()), float(temp_c.max())) if range_c is None else range_c
    if high_c - low_c < min_span_c:
        out.append(Advice("wider", f"the drift outside {low_c:.1f} to {high_c:.1f} degC ({high_c - low_c:.1f} "
                                   "degC): a model holds its edge value beyond the trained range",
                          f"a run over a wider range (at least {min_span_c:g} degC, the temperatures of use)"))
    span_c = float(np.ptp(temp_c))
    rising = _direction(time_s, temp_c)
    if rising < 0.05 or rising > 0.95:
        seen, missing = ("rises", "cooling") if rising > 0.5 else ("falls", "heating")
        out.append(Advice("reverse", f"heating versus cooling (hysteresis): the temperature only {seen}",
                          f"{missing} as well, over the same range"))
    if len(time_s) > 2 and span_c > 0:
        corr = float(np.corrcoef(time_s, temp_c)[0, 1])
        if abs(corr) > 0.9:
            out.append(Advice("run", f"a drift in time (warm-up, ageing) apart from a drift in temperature: "
                                     f"they are correlated at {corr:.2f}",
                              "another thermal history of the same unit (down and up, or dwells in another "
                              "order)"))
    start = time_s < time_s[0] + still_s
    moved_c = float(np.ptp(temp_c[start])) if start.any() else 0.0
    if moved_c > 0.5:
        out.append(Advice("still", f"the turn-on offset at a steady temperature: the temperature moves "
                                   f"{moved_c:.1f} degC in the first {still_s:g} s",
                          f"a still period of {still_s:g} s at a steady temperature at the start "
                          "(what startup.still_s averages)"))
    if fs_hz * rate_tau_s < 10:
        out.append(Advice("rate", f"fast temperature changes: {fs_hz:g} Hz leaves {fs_hz * rate_tau_s:.0f} samples "
                                  f"in the dT/dt tracker's {rate_tau_s:g} s",
                          f"a rate of at least {10 / rate_tau_s:g} Hz"))
    if not any(c.startswith("acc_") for c in columns):
        out.append(Advice("log", "g-sensitivity and orientation: there is no accelerometer column",
                          "log the accelerometer (acc_x_g, acc_y_g, acc_z_g)"))
    if not any(not c.startswith("acc_") for c in columns):  # no column but the accelerometer's to test
        out.append(Advice("log", "a second thermal path (board or case temperature) apart from a lag of temp_c",
                          "log a board thermistor (board_temp_c) or the supply (vdd_v)"))
    return out


def alternatives_advice(effects: Sequence[Mapping[str, Any]]) -> list[Advice]:
    """For each effect with equivalent explanations: the recording on which they would differ."""
    out = []
    for effect in effects:
        alternatives = effect.get("alternatives") or []
        if not alternatives:
            continue
        sources = {effect["source"], *(a["source"] for a in alternatives)}
        kinds = {effect["kind"], *(a["kind"] for a in alternatives)}
        names = ", ".join(_named(a) for a in alternatives)
        what = f"whether the {_named(effect)} or its equivalents ({names}) is the cause"
        if "time" in kinds:
            record = "another thermal history, so that time and temperature part"
        elif len(sources) == 1:  # one column's shapes: as it is, lagged, with hysteresis
            longest_s = max(float((x.get("params") or {}).get("tau_s") or 0.0) for x in (effect, *alternatives))
            record = (f"a run where {effect['source']} steps and then holds for longer than {longest_s:g} s, "
                      "so that its lags part" if longest_s > 0 else
                      f"a run where {effect['source']} turns up and down more often, so that its shapes part")
        elif len(sources - {"temp_c"}) and "temp_c" in sources:
            record = (f"a run where {', '.join(sorted(sources - {'temp_c'}))} and the temperature part (a change "
                      "of supply, load or humidity at constant chamber temperature)")
        else:
            record = f"a run where {', '.join(sorted(sources))} do not move together"
        out.append(Advice("run", what, record, decides=True))
    return out


def _named(effect: Mapping[str, Any]) -> str:
    """``column of vdd_v (tau_s 16 s)``: an effect or alternative as the advice names it."""
    tau_s = float((effect.get("params") or {}).get("tau_s") or 0.0)
    return f"{effect['kind']} of {effect['source']}" + (f" (tau_s {tau_s:g} s)" if tau_s else "")


def orientation_label(acc_g: np.ndarray) -> str:
    """The axis along gravity of a run's mean specific force (g): 'z_down', 'y_up', ... or 'tilted'."""
    axis = int(np.argmax(np.abs(acc_g)))
    if abs(acc_g[axis]) < 0.8 * np.linalg.norm(acc_g):
        return "tilted"
    return f"{'xyz'[axis]}_{'up' if acc_g[axis] > 0 else 'down'}"


def runs_advice(orientations: Sequence[str | None]) -> list[Advice]:
    """Advice from a campaign's design: which orientations were recorded, how often.

    ``orientations`` has one label per run (None: no accelerometer). A per-run offset and an
    orientation term are both constant within a run; they can be told apart only when an
    orientation repeats (its runs differ by the turn-on bias alone) or when there are more runs
    than an orientation term and an offset together can fit.
    """
    n_runs = len(orientations)
    if n_runs < 2:
        return [Advice("run", "the run-to-run offset (turn-on bias) and whether the model transfers to another "
                              "power-up", "a second run of the same unit (another power-up)")]
    if any(o is None for o in orientations):
        return [Advice("log", "orientation (g-sensitivity) apart from the run-to-run offset: a run has no "
                              "accelerometer", "log the accelerometer in every run")]
    distinct = sorted(set(orientations))
    counts = {o: orientations.count(o) for o in distinct}
    out = []
    if len(distinct) == 1:
        out.append(Advice("orientation", f"g-sensitivity: all {n_runs} runs are {distinct[0]}",
                          f"a run in another orientation (e.g. {_other(distinct)})"))
    elif max(counts.values()) == 1:
        # every orientation once: a per-run offset explains any orientation term exactly
        out.append(Advice("repeat", f"orientation ({', '.join(distinct)}) apart from the run-to-run offset: each "
                                    "orientation was recorded once, so every difference between runs can be "
                                    "either", f"the same orientation twice (e.g. {distinct[0]} again)", True))
        if len(distinct) < 3:
            out.append(Advice("orientation", "which axis the g-sensitivity acts on: two orientations give one "
                                             "difference", f"a third orientation (e.g. {_other(distinct)})", True))
    return out


def _other(seen: Sequence[str]) -> str:
    for label in ("z_down", "y_down", "x_down", "z_up", "y_up", "x_up"):
        if label not in seen and label.split("_")[0] not in {s.split("_")[0] for s in seen}:
            return label
    return next(label for label in ("z_up", "y_up", "x_up", "z_down", "y_down", "x_down") if label not in seen)


def advice_lines(items: Sequence[Advice]) -> list[str]:
    """Markdown for the end of a report: what would decide this diagnosis's ties first, then the
    rest cheapest first; always at least one item."""
    items = sorted(items, key=lambda a: (not a.decides, COST_H[a.cost])) or [
        Advice("run", "whether the model transfers to a run it was not trained on",
               "another run of the same unit, kept out of training and checked with compensate.py")]
    order = ("What would decide between equivalent explanations first, then cheapest first." if items[0].decides
             else "Cheapest first.")
    lines = ["## What to record next", "",
             f"{order} **Next: {items[0].record}** (it would show {items[0].cannot_show.split(':')[0]}).", ""]
    lines += [f"- Cannot show {a.cannot_show}. Record: {a.record}." for a in items]
    return lines + [""]
