"""What each feature kind computes from accepted rows: a segment of one period (arrays) or one sample (floats).

The extractor (:mod:`gyronet.model.features`) owns the state (filters, play operators) and passes it in.
"""
from __future__ import annotations

from typing import Any, Callable, Mapping, Sequence

import numpy as np

from gyronet.model.feature_specs import feature_name, product_rate_index


def segment_values(specs: Sequence[Mapping[str, Any]], names: Sequence[str], filters: Mapping[int, Any], run_play: Callable,
                   chunk: Mapping[str, np.ndarray], event: str | None, gap_s: float | None) -> np.ndarray:
    """The features of a segment of accepted rows of one period, between gaps (arrays)."""
    restart_gap_s = None if event == "power_on" else gap_s
    done: dict[str, np.ndarray] = {}
    for i, spec in enumerate(specs):
        done[names[i]] = _one(i, specs, names, filters, run_play, chunk, done, event, restart_gap_s)
    return np.column_stack([done[n] for n in names])


def _one(i: int, specs: Sequence[Mapping[str, Any]], names: Sequence[str], filters: Mapping[int, Any],
         run_play: Callable, chunk: Mapping[str, np.ndarray], done: Mapping[str, np.ndarray], event: str | None,
         gap_s: float | None) -> np.ndarray:
    spec = specs[i]
    kind, source = spec["kind"], spec.get("source", "temp_c")
    x = chunk.get(source)
    if kind in ("temp", "column") and i not in filters:
        return chunk["temp_c"] if kind == "temp" else x
    if kind in ("lag", "column", "rate"):
        if event is not None:
            filters[i].restart(float(x[0]), gap_s)
        return filters[i].run(x)
    if kind == "product":
        if float(spec.get("lag_s", 0.0)) > 0:
            return _lagged_product(spec, done)
        return chunk["temp_c"] * done[names[product_rate_index(specs, i)]]
    if kind == "power":
        return (x - float(spec.get("centre", 0.0))) ** float(spec["exponent"])
    if kind == "hysteresis":
        return x - run_play(i, x, float(spec["width"]), event == "power_on")
    if kind == "time":
        return np.zeros(len(chunk["temp_c"]))  # filled in by process, at every row's own time
    raise ValueError(f"unknown feature kind {kind!r}")


def lagged_inputs(spec: Mapping[str, Any]) -> tuple[str, str]:
    """The names of the lagged temperature and rate a product with ``lag_s`` multiplies."""
    lag_s = float(spec["lag_s"])
    return feature_name({"kind": "lag", "tau_s": lag_s}), feature_name({"kind": "rate", "lag_s": lag_s})


def _lagged_product(spec: Mapping[str, Any], done: Mapping[str, Any]) -> Any:
    """A product with ``lag_s``: the lagged temperature times the lagged rate, both computed before it."""
    temp_name, rate_name = lagged_inputs(spec)
    if temp_name not in done or rate_name not in done:
        raise ValueError(f"a lagged 'product' feature needs {temp_name} and {rate_name} before it")
    return done[temp_name] * done[rate_name]


def row_values(specs: Sequence[Mapping[str, Any]], names: Sequence[str], filters: Mapping[int, Any],
               run_play: Callable, values: Mapping[str, float], event: str | None,
               gap_s: float | None) -> list[float]:
    """The features of one accepted sample (``segment_values`` for a segment of one, in floats)."""
    row: list[float] = []
    for i, spec in enumerate(specs):
        kind, x = spec["kind"], values.get(spec.get("source", "temp_c"), 0.0)
        if kind == "temp":
            value = values["temp_c"]
        elif i in filters:
            if event is not None:
                filters[i].restart(x, gap_s)
            value = filters[i].step(x)
        elif kind == "column":
            value = x
        elif kind == "product" and float(spec.get("lag_s", 0.0)) > 0:
            value = _lagged_product(spec, dict(zip(names, row)))
        elif kind == "product":
            value = values["temp_c"] * row[product_rate_index(specs, i)]
        elif kind == "power":
            value = float(((np.array([x]) - float(spec.get("centre", 0.0))) ** float(spec["exponent"]))[0])
        elif kind == "hysteresis":
            value = x - run_play(i, [x], float(spec["width"]), event == "power_on")[0]
        elif kind == "time":
            value = 0.0  # filled in at the sample's own time
        else:
            raise ValueError(f"unknown feature kind {kind!r}")
        row.append(value)
    return row
