"""A bundle's curve at steady temperature, for the flight-stack exports: the model on a grid of
temperatures with dT/dt = 0 and every lag settled, its clamp edges, and what no cubic can express."""
from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from gyronet.errors import BundleError

log = logging.getLogger(__name__)

_STEADY = {"temp", "rate", "product", "lag", "power"}  # kinds with a value at steady temperature
# beyond its edge a clamped curve is flat to rounding, 1e-16 (a lag slot's copy moves to the edge in its own
# units); this is far above that and moves the edge found by under 1e-9 degC on a slope of 1e-3 deg/s per degC
FLAT_DPS = 1e-13


def _flat(a: np.ndarray, b: np.ndarray) -> bool:
    return bool(np.all(np.abs(a - b) <= FLAT_DPS))


def steady_features(meta: dict[str, Any], temp_c: np.ndarray) -> np.ndarray:
    """The bundle's features at a steady temperature ``temp_c`` (n,): dT/dt = 0, every lag settled."""
    rows = np.zeros((len(temp_c), len(meta["features"])))
    for i, spec in enumerate(meta["features"]):
        kind, source = spec["kind"], spec.get("source", "temp_c")
        if kind not in _STEADY or source != "temp_c":
            continue  # checked by the caller: the model must not read it
        if kind in ("temp", "lag"):
            rows[:, i] = temp_c
        elif kind == "power":
            rows[:, i] = (temp_c - float(spec.get("centre", 0.0))) ** float(spec["exponent"])
    return rows


def _inexpressible(model: Callable, meta: dict[str, Any], temp_c: np.ndarray) -> list[str]:
    """Names of the features the model reads that no temperature polynomial can stand for."""
    base = steady_features(meta, temp_c)
    found = []
    for i, spec in enumerate(meta["features"]):
        if spec["kind"] in _STEADY and spec.get("source", "temp_c") == "temp_c":
            continue
        bumped = base.copy()
        bumped[:, i] += 1.0
        if not np.array_equal(model(base), model(bumped)):
            found.append(meta["feature_names"][i])
    return found


def _clamp_edge(curve: Callable[[float], np.ndarray], flat_c: float, inside_c: float) -> float:
    """Bisect for the temperature where the curve starts to change, between a flat point and an inside one."""
    flat_value = curve(flat_c)
    for _ in range(80):
        middle = 0.5 * (flat_c + inside_c)
        if _flat(curve(middle), flat_value):
            flat_c = middle
        else:
            inside_c = middle
    return flat_c


def clamp_range(curve: Callable[[float], np.ndarray], low_c: float, high_c: float) -> tuple[float, float]:
    """Where the curve is clamped: its flat ends beyond [low_c, high_c] traced inwards; else low_c, high_c."""
    span = high_c - low_c
    edges = []
    for far, near, inside in ((low_c - span, low_c - span + 1.0, high_c), (high_c + span, high_c + span - 1.0, low_c)):
        if _flat(curve(far), curve(near)) and not _flat(curve(far), curve(inside)):
            edges.append(_clamp_edge(curve, far, inside))
        else:
            edges.append(low_c if far < low_c else high_c)
    return edges[0], edges[1]


def bundle_curve(bundle_dir: str | Path, grid_points: int = 2001) -> tuple[np.ndarray, np.ndarray, Callable, str]:
    """A bundle's steady-state curve: the grid over its clamp range (or trained range), the curve (n, 3) on it,
    the curve as a function of temperatures (n,) and the model's class; what no cubic can express is refused."""
    from gyronet.bundle.io import read_bundle
    from gyronet.bundle.schema import META_FILE, check_model, validate_meta

    bundle = read_bundle(bundle_dir)
    # every check Compensator.load makes: an edited meta.json is refused in one line, not used or a traceback
    validate_meta(bundle.meta, f"{bundle_dir}/{META_FILE}")
    check_model(bundle.model, bundle.facts, bundle.meta, str(bundle_dir))
    if bundle.kalman is not None:
        raise BundleError(f"{bundle_dir}: has a Kalman stage, which a temperature polynomial cannot express; "
                          "export format=c, or train without kalman=")
    meta = bundle.meta

    def model(features: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return bundle.model(torch.as_tensor(features, dtype=torch.float64)).numpy()

    low_c, high_c = (float(v) for v in meta["temp_range_c"])
    probe = np.linspace(low_c, high_c, 7)
    extra = _inexpressible(model, meta, probe)
    if extra:
        raise BundleError(f"{bundle_dir}: the model reads {', '.join(extra)}, which a temperature polynomial cannot "
                          "express (an auxiliary input or a time term); export format=c instead")

    def curve(temp_c: np.ndarray) -> np.ndarray:
        return model(steady_features(meta, np.asarray(temp_c, dtype=np.float64).reshape(-1)))

    temp_min, temp_max = clamp_range(curve, low_c, high_c)
    grid = np.linspace(temp_min, temp_max, grid_points)
    target = curve(grid)
    if not np.all(np.isfinite(target)):
        raise BundleError(f"{bundle_dir}: the model gives non-finite drift inside its trained range")
    return grid, target, curve, str(meta.get("model", {}).get("class", "?"))


__all__ = ["bundle_curve", "clamp_range", "steady_features"]
