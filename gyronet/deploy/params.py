"""A bundle as flight-stack parameters: PX4's ``TC_G{n}_*`` and ArduPilot's ``INS_TCAL{n}_*`` in a .params file.

Both stacks correct a gyro with one cubic in temperature per axis, the temperature clamped to
[TMIN, TMAX]; they differ in reference and scale:

- PX4 (``TemperatureCompensation.cpp`` ``calc_thermal_offsets_3D``, ``Gyroscope.hpp`` ``Correct()``):
  rate -= X0 + X1 dT + X2 dT^2 + X3 dT^3 with dT = clamp(T) - TREF, rad/s, enabled by
  ``TC_G_ENABLE`` = 1 and applied to the gyro whose device id is ``TC_G{n}_ID``.
- ArduPilot (``AP_InertialSensor_tempcal.cpp`` ``correct_sensor``): rate -= p(clamp(T) - 35) -
  p(clamp(T_cal) - 35), p(u) = (GYR1 u + GYR2 u^2 + GYR3 u^3) * 1e-6, rad/s; the reference is fixed
  at 35 degC, and the constant is the gyro offset ArduPilot calibrates at boot (at T_cal).

The cubic is read off the bundle's own curve: its model evaluated on a fine grid of temperatures
at steady state (dT/dt = 0) and fitted by least squares. For a cubic bundle (poly3, px4,
px4_onboard) that is the model itself (error at rounding level); for gyronet's own model it is the
best cubic over the trained range, and the error is stated. The clamp edges are where the curve
stops changing, found by bisection, so a bundle clamped inside its data keeps its own TMIN, TMAX.
The file is QGroundControl's: ``#`` comment lines, then ``vehicle-id component-id name value
type`` separated by tabs, the type a MAVLink ``MAV_PARAM_TYPE`` (6 INT32, 2 INT8, 9 REAL32).
"""
from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

import numpy as np
import torch

from gyronet.errors import BundleError, GyronetError

log = logging.getLogger(__name__)

INT8, INT32, REAL32 = 2, 6, 9  # MAV_PARAM_TYPE
RAD_PER_DEG = np.pi / 180.0
ARDUPILOT_TREF_C = 35.0  # AP_InertialSensor_tempcal.cpp TEMP_REFERENCE
ARDUPILOT_SCALE = 1.0e6  # ... SCALE_FACTOR
AXES = ("x", "y", "z")
_STEADY = {"temp", "rate", "product", "lag", "power"}  # kinds with a value at steady temperature


@dataclass
class Cubic:
    """drift = sum_k coef[k] (clamp(T, temp_min_c, temp_max_c) - temp_ref_c)^k per axis, deg/s; coef (4, 3)."""

    temp_min_c: float
    temp_max_c: float
    temp_ref_c: float
    coef_dps: np.ndarray

    def __call__(self, temp_c: np.ndarray) -> np.ndarray:
        """Drift per axis (n, 3), deg/s."""
        delta = np.clip(np.asarray(temp_c, dtype=np.float64), self.temp_min_c, self.temp_max_c) - self.temp_ref_c
        return np.vander(delta, 4, increasing=True) @ self.coef_dps

    def about(self, temp_ref_c: float) -> "Cubic":
        """The same curve written about another reference (exact re-expansion of the polynomial)."""
        shift = temp_ref_c - self.temp_ref_c  # (T - old) = (T - new) + shift
        binomial = np.array([[1, 0, 0, 0], [1, 1, 0, 0], [1, 2, 1, 0], [1, 3, 3, 1]], dtype=np.float64)
        powers = np.array([[shift ** (k - j) if k >= j else 0.0 for j in range(4)] for k in range(4)])
        return Cubic(self.temp_min_c, self.temp_max_c, temp_ref_c, (binomial * powers).T @ self.coef_dps)


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
        if np.array_equal(curve(middle), flat_value):
            flat_c = middle
        else:
            inside_c = middle
    return flat_c


def clamp_range(curve: Callable[[float], np.ndarray], low_c: float, high_c: float) -> tuple[float, float]:
    """Where the curve is clamped: its flat ends beyond [low_c, high_c] traced inwards; else low_c, high_c."""
    span = high_c - low_c
    edges = []
    for far, near, inside in ((low_c - span, low_c - span + 1.0, high_c), (high_c + span, high_c + span - 1.0, low_c)):
        if np.array_equal(curve(far), curve(near)) and not np.array_equal(curve(far), curve(inside)):
            edges.append(_clamp_edge(curve, far, inside))
        else:
            edges.append(low_c if far < low_c else high_c)
    return edges[0], edges[1]


@dataclass
class CubicFit:
    """The cubic written out, and how far it is from the bundle's curve on the grid (deg/s per axis)."""

    cubic: Cubic
    max_error_dps: np.ndarray
    rms_error_dps: np.ndarray
    model_class: str
    grid_points: int

    def summary(self) -> dict[str, Any]:
        return {"model_class": self.model_class, "temp_min_c": self.cubic.temp_min_c,
                "temp_max_c": self.cubic.temp_max_c, "temp_ref_c": self.cubic.temp_ref_c,
                "coef_dps": self.cubic.coef_dps.tolist(),
                "max_error_dps": dict(zip(AXES, self.max_error_dps.tolist())),
                "rms_error_dps": dict(zip(AXES, self.rms_error_dps.tolist())),
                "grid": f"{self.grid_points} temperatures over [TMIN, TMAX] at dT/dt = 0"}


def bundle_cubic(bundle_dir: str | Path, grid_points: int = 2001) -> CubicFit:
    """The least-squares cubic of a bundle's steady-state curve over its clamp range (or trained range)."""
    from gyronet.export import read_bundle

    bundle = read_bundle(bundle_dir)
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

    def curve(temp_c: float) -> np.ndarray:
        return model(steady_features(meta, np.array([temp_c])))

    temp_min, temp_max = clamp_range(curve, low_c, high_c)
    grid = np.linspace(temp_min, temp_max, grid_points)
    target = model(steady_features(meta, grid))
    if not np.all(np.isfinite(target)):
        raise BundleError(f"{bundle_dir}: the model gives non-finite drift inside its trained range")
    temp_ref = 0.5 * (temp_min + temp_max)
    coef = np.linalg.lstsq(np.vander(grid - temp_ref, 4, increasing=True), target, rcond=None)[0]
    cubic = Cubic(temp_min, temp_max, temp_ref, coef)
    error = cubic(grid) - target
    return CubicFit(cubic, np.abs(error).max(0), np.sqrt(np.mean(error**2, 0)),
                    str(meta.get("model", {}).get("class", "?")), grid_points)


def _f32(value: float) -> float:
    return float(np.float32(value))


def px4_rows(cubic: Cubic, instance: int = 0, device_id: int = 0) -> list[tuple[str, float | int, int]]:
    """``TC_G_ENABLE`` and ``TC_G{instance}_*`` (name, value, MAV_PARAM_TYPE), coefficients in rad/s."""
    if not 0 <= instance <= 3:
        raise GyronetError(f"PX4 has gyro thermal parameters for instances 0-3 (TC_G0..TC_G3), not {instance}")
    prefix = f"TC_G{instance}"
    rows: list[tuple[str, float | int, int]] = [("TC_G_ENABLE", 1, INT32), (f"{prefix}_ID", int(device_id), INT32)]
    rows += [(f"{prefix}_TMIN", _f32(cubic.temp_min_c), REAL32), (f"{prefix}_TMAX", _f32(cubic.temp_max_c), REAL32),
             (f"{prefix}_TREF", _f32(cubic.temp_ref_c), REAL32)]
    for k in range(4):
        for axis in range(3):
            rows.append((f"{prefix}_X{k}_{axis}", _f32(cubic.coef_dps[k, axis] * RAD_PER_DEG), REAL32))
    return sorted(rows)


def ardupilot_rows(cubic: Cubic, instance: int = 0) -> list[tuple[str, float | int, int]]:
    """``INS_TCAL{instance + 1}_*``: ENABLE, TMIN, TMAX and GYR1..GYR3 about 35 degC, rad/s times 1e6."""
    if not 0 <= instance <= 2:
        raise GyronetError(f"ArduPilot has temperature calibrations for IMUs 0-2 (INS_TCAL1..3), not {instance}")
    prefix = f"INS_TCAL{instance + 1}"
    about = cubic.about(ARDUPILOT_TREF_C)
    rows: list[tuple[str, float | int, int]] = [(f"{prefix}_ENABLE", 1, INT8),
                                                (f"{prefix}_TMIN", _f32(cubic.temp_min_c), REAL32),
                                                (f"{prefix}_TMAX", _f32(cubic.temp_max_c), REAL32)]
    for k in range(1, 4):
        for axis, name in enumerate("XYZ"):
            rows.append((f"{prefix}_GYR{k}_{name}", _f32(about.coef_dps[k, axis] * RAD_PER_DEG * ARDUPILOT_SCALE),
                         REAL32))
    return sorted(rows)


def params_text(rows: list[tuple[str, float | int, int]], stack: str, vehicle_id: int = 1, component_id: int = 1,
                source: str = "") -> str:
    """QGroundControl's .params text; a float is written as the shortest text that reads back to its float32."""
    lines = [f"# Onboard parameters for Vehicle {vehicle_id}", "#", f"# Stack: {stack}",
             f"# Thermal compensation from gyronet{': ' + source if source else ''}", "#",
             "# Vehicle-Id Component-Id Name Value Type"]
    for name, value, kind in rows:
        text = str(int(value)) if kind != REAL32 else np.format_float_positional(np.float32(value), unique=True,
                                                                                  trim="-")
        lines.append("\t".join((str(vehicle_id), str(component_id), name, text, str(kind))))
    return "\n".join(lines) + "\n"


def read_params(path: str | Path) -> dict[str, float]:
    """Name -> value from a .params file (QGroundControl's five tab-separated columns); bad lines are errors."""
    try:
        text = Path(path).read_text()
    except (OSError, UnicodeDecodeError) as err:
        raise GyronetError(f"{path}: cannot be read as a .params file ({getattr(err, 'strerror', None) or err})") from None
    values = {}
    for number, line in enumerate(text.splitlines(), 1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        fields = line.split("\t")
        if len(fields) != 5:
            raise GyronetError(f"{path}: line {number}: {len(fields)} tab-separated fields, a .params line has 5")
        try:
            values[fields[2]] = float(fields[3])
        except ValueError:
            raise GyronetError(f"{path}: line {number}: {fields[2]} = {fields[3]!r} is not a number") from None
    return values


def px4_cubic(values: dict[str, float], instance: int = 0) -> Cubic:
    """The cubic PX4 applies from ``TC_G{instance}_*`` (deg/s), as ``calc_thermal_offsets_3D`` reads them."""
    p = f"TC_G{instance}"
    coef = np.array([[values[f"{p}_X{k}_{axis}"] for axis in range(3)] for k in range(4)]) / RAD_PER_DEG
    return Cubic(values[f"{p}_TMIN"], values[f"{p}_TMAX"], values[f"{p}_TREF"], coef)


def ardupilot_cubic(values: dict[str, float], instance: int = 0) -> Cubic:
    """The cubic about 35 degC ArduPilot applies from ``INS_TCAL{instance + 1}_*``, deg/s, without its constant."""
    p = f"INS_TCAL{instance + 1}"
    coef = np.zeros((4, 3))
    for k in range(1, 4):
        coef[k] = [values[f"{p}_GYR{k}_{axis}"] for axis in "XYZ"]
    return Cubic(values[f"{p}_TMIN"], values[f"{p}_TMAX"], ARDUPILOT_TREF_C, coef / ARDUPILOT_SCALE / RAD_PER_DEG)


def export_params(bundle_dir: str | Path, output: str | Path, stack: str = "px4", instance: int = 0,
                  device_id: int = 0, vehicle_id: int = 1, component_id: int = 1, grid_points: int = 2001) -> dict:
    """Write ``output`` (.params) and ``output`` with suffix .json (the cubic and its error); return the summary."""
    from gyronet.atomic import atomic_output

    if stack not in ("px4", "ardupilot"):
        raise GyronetError(f"parameters are written for px4 or ardupilot, not {stack!r}")
    if Path(output).suffix == ".json":
        raise GyronetError(f"output={output}: the cubic and its error go to <output>.json beside the .params file; "
                           "name the parameter file F.params")
    if grid_points < 8:
        raise GyronetError(f"grid_points must be at least 8 to fit and check a cubic, got {grid_points}")
    fit = bundle_cubic(bundle_dir, grid_points)
    if stack == "px4":
        rows, name = px4_rows(fit.cubic, instance, device_id), "PX4 Pro"
        if not device_id:
            log.warning("TC_G%d_ID is 0: PX4 applies TC_G%d_* only to the gyro whose device id it names; give "
                        "device_id=<CAL_GYRO%d_ID of the calibrated board>", instance, instance, instance)
    else:
        rows, name = ardupilot_rows(fit.cubic, instance), "ArduPilot"
    output = Path(output)
    output.parent.mkdir(parents=True, exist_ok=True)
    with atomic_output(output) as tmp:
        tmp.write_text(params_text(rows, name, vehicle_id, component_id, source=str(bundle_dir)))
    summary = {"format": stack, "bundle": str(bundle_dir), "params": str(output), "n_params": len(rows),
               **fit.summary()}
    with atomic_output(output.with_suffix(".json")) as tmp:
        tmp.write_text(json.dumps(summary, indent=2) + "\n")
    return summary


__all__ = ["Cubic", "CubicFit", "ardupilot_cubic", "ardupilot_rows", "bundle_cubic", "clamp_range", "export_params",
           "params_text", "px4_cubic", "px4_rows", "read_params", "steady_features"]
