"""Feature specs: the small dicts ``meta.json`` stores, their column names, and what each kind reads.

A feature is a small dict (a "spec") that ``meta.json`` stores, so a bundle rebuilds exactly
the extractor it was trained with:

========== ================================================================= ====================
kind       what                                                              default name
========== ================================================================= ====================
temp       the measured temperature                                          ``temp_c``
rate       dT/dt from a critically damped alpha-beta tracker, ``tau_s``      ``temp_rate_c_per_s``
           (with ``lag_s``: then through a first-order lag of ``lag_s``)     (``..._lag<lag>s``)
product    T * dT/dt: the paper's "T times the change of T" per second       ``temp_x_rate_c2_per_s``
           (with ``lag_s``: the lagged temperature times the lagged rate)    (``..._lag<lag>s``)
lag        ``source`` through a first-order lag of ``tau_s``                 ``<source>_lag<tau>s``
column     a recording column as it is (or lagged, with ``tau_s`` > 0)       ``<source>``
hysteresis play (backlash) operator of half-width ``width``: source - play   ``<source>_play<w>``
power      ``source`` ** ``exponent`` about ``centre``                       ``<source>_pow<k>``
time       time since the start: exp(-t/``tau_s``) or, without tau, hours    ``warmup<tau>s``/``age_h``
========== ================================================================= ====================

The product uses dT/dt per second: with a per-sample change dT the paper's T*dT is this
feature times the sample interval, a constant factor the model absorbs. Its dT/dt is the
temperature's own unlagged ``rate`` listed before it, whatever other rates come first.
"""
from __future__ import annotations

from typing import Any, Mapping, Sequence

import numpy as np

PAPER_FEATURES: list[dict[str, Any]] = [
    {"kind": "temp"},
    {"kind": "rate", "tau_s": 5.0},
    {"kind": "product"},
]

PRIOR_TEMP_C = 25.0  # the temperature assumed for rejected rows before any sample was accepted


def feature_name(spec: Mapping[str, Any]) -> str:
    """The column name of a feature spec (``name`` if given, else from its kind and parameters)."""
    if "name" in spec:
        return str(spec["name"])
    kind, source = spec["kind"], spec.get("source", "temp_c")
    if kind == "temp":
        return "temp_c"
    lag = f"_lag{float(spec['lag_s']):g}s" if float(spec.get("lag_s", 0.0)) > 0 else ""
    if kind == "rate":
        return ("temp_rate_c_per_s" if source == "temp_c" else f"{source}_rate_per_s") + lag
    if kind == "product":
        return "temp_x_rate_c2_per_s" + lag
    if kind == "lag":
        return f"{source}_lag{spec['tau_s']:g}s"
    if kind == "column":
        tau_s = float(spec.get("tau_s", 0.0))
        return source if tau_s == 0 else f"{source}_lag{tau_s:g}s"
    if kind == "hysteresis":
        return f"{source}_play{spec['width']:g}"
    if kind == "power":
        return f"{source}_pow{spec['exponent']:g}"
    if kind == "time":
        return f"warmup{spec['tau_s']:g}s" if spec.get("tau_s") else "age_h"
    raise ValueError(f"unknown feature kind {kind!r}")


def product_rate_index(specs: Sequence[Mapping[str, Any]], index: int) -> int:
    """The spec an unlagged product (T * dT/dt) multiplies T by: the temperature's own unlagged rate before it."""
    for j, spec in enumerate(specs[:index]):
        if (spec["kind"] == "rate" and spec.get("source", "temp_c") == "temp_c"
                and not float(spec.get("lag_s", 0.0)) > 0):
            return j
    raise ValueError("a 'product' feature (T * dT/dt) needs the temperature's 'rate' feature (no source, no lag_s) "
                     "before it")


def required_columns(specs: Sequence[Mapping[str, Any]]) -> list[str]:
    """Recording columns that a list of specs reads (always ``time_s`` and ``temp_c``)."""
    needed = ["time_s", "temp_c"]
    for spec in specs:
        source = spec.get("source", "temp_c")
        if spec["kind"] in ("lag", "column", "hysteresis", "power", "rate") and source not in needed:
            needed.append(source)
    return needed


def power_on_rows(specs: Sequence[Mapping[str, Any]], source: Mapping[str, np.ndarray]) -> np.ndarray:
    """Features of rejected rows before any accepted one: a fresh filter's output at a prior (room
    temperature; other columns as read, 0 where not finite)."""
    values = {k: np.nan_to_num(v, nan=0.0, posinf=0.0, neginf=0.0) for k, v in source.items()}
    values["temp_c"] = np.full(len(values["temp_c"]), PRIOR_TEMP_C)
    rows = np.zeros((len(values["temp_c"]), len(specs)))
    for i, spec in enumerate(specs):
        kind, x = spec["kind"], values.get(spec.get("source", "temp_c"))
        if kind in ("temp", "column", "lag"):
            rows[:, i] = values["temp_c"] if kind == "temp" else x
        elif kind == "power":
            rows[:, i] = (x - float(spec.get("centre", 0.0))) ** float(spec["exponent"])
    return rows  # rate, product and hysteresis start at 0


def play_operator(start: float, x, width: float):
    """Play (backlash) operator: the output follows x only when x leaves the band [p - w, p + w].

    Returns the outputs (an array for an array ``x``, a list for a list) and the last output (the state).
    """
    play = start
    out = []
    for value in (x.tolist() if isinstance(x, np.ndarray) else x):
        play = min(max(play, value - width), value + width)
        out.append(play)
    return (np.array(out) if isinstance(x, np.ndarray) else out), play
