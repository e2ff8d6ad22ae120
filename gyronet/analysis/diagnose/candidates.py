"""Candidate effects: generic feature specs built from whatever a recording holds.

Nothing here knows the simulator's effects. The candidates come from four generic sources:

============ ============================================================= ====================
kind         feature spec (``gyronet.model.features``)                           from
============ ============================================================= ====================
lag          ``{"kind": "lag", "source": "temp_c", "tau_s": tau}``          the temperature
             (another thermal path), ``tau`` over a log grid
hysteresis   ``{"kind": "hysteresis", "source": "temp_c", "width": w}``     the temperature
             (heating versus cooling: T minus its play operator)
polynomial   ``{"kind": "power", "source": "temp_c", "exponent": k,        the temperature
             "centre": c}``: powers the model's cubic and Gaussians miss
column       ``{"kind": "column", "source": name, "tau_s": tau}`` for       every other column
             every numeric column (``tau`` 0: the column as it is), and
             ``{"kind": "power", "source": name, "exponent": 2, ...}``
             about its median (an effect that is even in the column)
time         ``{"kind": "time", "tau_s": tau}`` (warm-up) and               the clock
             ``{"kind": "time"}`` (hours: ageing)
============ ============================================================= ====================

**Which columns.** Every column of the recording except ``time_s``, ``temp_c`` and the gyro
rates (anything named ``gyro_*``: a column derived from the rate would explain the drift by
the drift itself). The accelerometer is a legitimate source (g-sensitivity, tilt), as is any
column of any name: a new channel in a new recording needs no new code. Constant columns carry
nothing and are left out.

**Why powers for shape.** The default model already has Gaussians and a cubic in T; a higher
power (4..6) about the middle of the range is one extra linear input, so the test and the
deployed model treat it like every other candidate. More Gaussians would be a change of model
size, which the GA sweep already owns. Other columns enter the network linearly only, so a
column whose effect is even about its usual value (a humidity or a supply that hurts in both
directions) has no linear trace at all: its centred square is offered too.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import numpy as np

from gyronet.recordings.data import Recording
from gyronet.model.features import feature_name

log = logging.getLogger(__name__)

TEMPERATURE = "temp_c"
_EXCLUDED = ("time_s", TEMPERATURE)


@dataclass
class CandidateGrid:
    """The parameter grids of the candidates (``conf/diagnose.yaml``: ``diagnose.candidates``).

    Attributes
    ----------
    lag_tau_s
        Time constants of temperature through another thermal path, s (log grid).
    hysteresis_width_c
        Half-widths of the play operator on temperature, degC.
    power_exponents
        Powers of (T - middle of the range).
    column_tau_s
        Lags of every other column, s (0: the column as it is).
    column_powers
        Powers of every other column about its median (2: an even effect).
    time_tau_s
        Warm-up time constants, s (log grid).
    ageing
        Offer hours since the start (a linear drift in time).
    max_tau_fraction
        Drop time constants longer than this fraction of the record: the record cannot tell them
        from a ramp.
    """

    lag_tau_s: Sequence[float] = (60, 150, 300, 600, 1200, 2400, 4800, 9600)
    hysteresis_width_c: Sequence[float] = (0.25, 0.5, 1.0, 2.0, 4.0, 8.0)
    power_exponents: Sequence[int] = (4, 5, 6)
    column_tau_s: Sequence[float] = (0, 60, 300, 1200, 3600)
    column_powers: Sequence[int] = (2,)
    time_tau_s: Sequence[float] = (60, 180, 600, 1800, 5400, 16200)
    ageing: bool = True
    max_tau_fraction: float = 0.5
    extra: list = field(default_factory=list)  # more specs to try, written out in full


def source_columns(recording: Recording) -> list[str]:
    """Recording columns a ``column`` candidate may read: all but time, temperature and gyro."""
    names = []
    for name in recording.columns:
        if name in _EXCLUDED or name.startswith("gyro_"):
            continue
        values = recording.columns[name]
        if np.ptp(values) > 0:
            names.append(name)
        else:
            log.info("column %s is constant: not a candidate", name)
    return names


def candidate_specs(recording: Recording, grid: CandidateGrid, exclude: Sequence[Mapping[str, Any]] = (),
                    columns: Sequence[str] | None = None) -> list[dict[str, Any]]:
    """Every candidate feature spec for ``recording``, minus those already in ``exclude``.

    Parameters
    ----------
    recording
        The training recording: its length bounds the time constants, its temperature range
        centres the powers, its columns are the ``column`` sources.
    grid
        The parameter grids.
    exclude
        Specs the model already has.
    columns
        The column sources (default ``source_columns(recording)``); with a separate validation
        recording, the columns both recordings have.
    """
    span_s = float(recording.time_s[-1] - recording.time_s[0])
    longest = grid.max_tau_fraction * span_s
    taus = [float(t) for t in grid.lag_tau_s if 0 < t <= longest]
    temp = recording.temp_c
    centre = float(np.round(0.5 * (temp.min() + temp.max()), 1))
    specs: list[dict[str, Any]] = [{"kind": "lag", "source": TEMPERATURE, "tau_s": t} for t in taus]
    specs += [{"kind": "hysteresis", "source": TEMPERATURE, "width": float(w)} for w in grid.hysteresis_width_c
              if 0 < w < 0.5 * np.ptp(temp)]
    specs += [{"kind": "power", "source": TEMPERATURE, "exponent": int(k), "centre": centre}
              for k in grid.power_exponents]
    for name in source_columns(recording) if columns is None else columns:
        specs += [{"kind": "column", "source": name, "tau_s": float(t)} for t in grid.column_tau_s
                  if t <= longest]
        median = float(np.median(recording.columns[name]))
        specs += [{"kind": "power", "source": name, "exponent": int(k), "centre": float(f"{median:.4g}")}
                  for k in grid.column_powers]
    specs += [{"kind": "time", "tau_s": float(t)} for t in grid.time_tau_s if 0 < t <= longest]
    if grid.ageing:
        specs.append({"kind": "time"})
    specs += [dict(s) for s in grid.extra]
    taken = {feature_name(s) for s in exclude}
    unique: dict[str, dict[str, Any]] = {}
    for spec in specs:
        name = feature_name(spec)
        if name not in taken and name not in unique:
            unique[name] = spec
    return list(unique.values())


def effect_kind(spec: Mapping[str, Any]) -> str:
    """The diagnosis kind (CONTRACT.md section 4) of a feature spec."""
    kind, other_column = spec["kind"], spec.get("source", TEMPERATURE) != TEMPERATURE
    if kind in ("power", "lag") and other_column:
        return "column"
    return "polynomial" if kind == "power" else kind


def effect_source(spec: Mapping[str, Any]) -> str:
    """The recording column an effect is computed from (``time_s`` for the clock)."""
    return "time_s" if spec["kind"] == "time" else str(spec.get("source", TEMPERATURE))


def effect_params(spec: Mapping[str, Any]) -> dict[str, Any]:
    """The spec's parameters, without kind, source and name."""
    return {k: v for k, v in spec.items() if k not in ("kind", "source", "name")}


def family(spec: Mapping[str, Any]) -> tuple[str, str, bool]:
    """Candidates that differ only in a continuous parameter: (kind, source, has a time constant).

    A column as it is (no parameter, what the sensor measured) and the same column through a lag
    are two families, as hours since the start and a warm-up are: else the column as it is would
    only ever be compared through its family's best lag, and lose to it by a hair.
    """
    timed = bool(spec.get("tau_s")) or spec["kind"] not in ("time", "column")
    return spec["kind"], effect_source(spec), timed


def filter_tau(spec: Mapping[str, Any]) -> float | None:
    """The time constant of a candidate's lag filter, or None when it has none.

    A lag filter starts settled on the first sample, which is noisy, and relaxes from there with
    its own time constant: a noisy constant column (an accelerometer at rest) lagged by tau looks
    like a warm-up exp(-t / tau). The screen therefore scores lagged candidates as if the filter
    had started on the mean of the first block (``ScreenRows.features``).
    """
    if spec["kind"] == "lag" or (spec["kind"] == "column" and float(spec.get("tau_s", 0.0)) > 0):
        return float(spec["tau_s"])
    return None


def refinements(spec: Mapping[str, Any], steps: Sequence[float] = (-0.5, -0.25, 0.25, 0.5),
                longest_s: float = np.inf) -> list[dict[str, Any]]:
    """Neighbours of a grid point on a finer log grid (tau times 2**step, width times 2**step)."""
    key = "tau_s" if spec.get("tau_s") else "width" if "width" in spec else None
    if key is None:
        return []
    out, seen = [], {float(spec[key])}
    for step in steps:
        value = float(np.round(float(spec[key]) * 2.0**step, 3 if key == "width" else 0))
        # a fine step can round back to the spec itself or to its other neighbour: skip repeats
        if value > 0 and value not in seen and (key == "width" or value <= longest_s):
            seen.add(value)
            out.append({**spec, key: value})
    return out


def describe(spec: Mapping[str, Any]) -> str:
    """A few words for a person: 'temp_c through a 1800 s lag'."""
    kind, source = spec["kind"], effect_source(spec)
    if kind == "lag" or (kind == "column" and spec.get("tau_s")):
        return f"{source} through a {spec['tau_s']:g} s lag"
    if kind == "column":
        return f"the column {source}"
    if kind == "hysteresis":
        return f"heating versus cooling ({source} minus its play of half-width {spec['width']:g})"
    if kind == "power":
        return f"({source} - {spec.get('centre', 0.0):g})^{spec['exponent']:g}"
    if kind == "time":
        return f"a warm-up exp(-t / {spec['tau_s']:g} s)" if spec.get("tau_s") else "hours since the start (ageing)"
    return feature_name(spec)
