"""A bundle as flight-stack parameters: PX4's ``TC_G{n}_*`` and ArduPilot's ``INS_TCAL{n}_*`` in a .params file.

Both stacks correct a gyro with one cubic in temperature per axis, the temperature clamped to
[TMIN, TMAX]; they differ in reference and scale:

- PX4 (``TemperatureCompensation.cpp`` ``calc_thermal_offsets_3D``, ``Gyroscope.hpp`` ``Correct()``):
  rate -= X0 + X1 dT + X2 dT^2 + X3 dT^3 with dT = clamp(T) - TREF, rad/s, enabled by
  ``TC_G_ENABLE`` = 1 and applied to the gyro whose device id is ``TC_G{n}_ID``.
- ArduPilot (``AP_InertialSensor_tempcal.cpp`` ``correct_sensor``): rate -= p(clamp(T) - 35) -
  p(clamp(T_cal) - 35), p(u) = (GYR1 u + GYR2 u^2 + GYR3 u^3) * 1e-6, rad/s; the reference is fixed
  at 35 degC, and the constant is the gyro offset ArduPilot calibrates at boot (at T_cal).

The cubic is read off the bundle's own curve (``gyronet.deploy.bundle_curve``): its model
evaluated on a fine grid of temperatures at steady state (dT/dt = 0), and fitted for the stack
that runs it: by least squares for PX4, which applies the cubic itself; as the minimax cubic for
ArduPilot, whose users get e(T) - e(T_cal) (``gyronet.deploy.as_flown``). For a cubic bundle
(poly3, px4, px4_onboard) that is the model itself (error at rounding level); for gyronet's own
model it is an approximation, and the error each stack's users get is stated. The clamp edges are where the curve
stops changing, found by bisection, so a bundle clamped inside its data keeps its own TMIN, TMAX.
The file is QGroundControl's: ``#`` comment lines, then ``vehicle-id component-id name value
type`` separated by tabs, the type a MAVLink ``MAV_PARAM_TYPE`` (6 INT32, 2 INT8, 9 REAL32).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from gyronet.atomic import write_json
from gyronet.deploy.bundle_curve import bundle_curve, clamp_range, steady_features  # noqa: F401 (re-exported)
from gyronet.deploy.as_flown import (DEFAULT_TEMP_RATE_C_PER_S, difference_error, history_error, minimax_cubic,
                                     px4_stated_error)
from gyronet.errors import GyronetError

log = logging.getLogger(__name__)

INT8, INT32, REAL32 = 2, 6, 9  # MAV_PARAM_TYPE
EXPORT_MARK = "Thermal compensation from gyronet"  # in an export's header: the only .params it replaces
RAD_PER_DEG = np.pi / 180.0
ARDUPILOT_TREF_C = 35.0  # AP_InertialSensor_tempcal.cpp TEMP_REFERENCE
ARDUPILOT_SCALE = 1.0e6  # ... SCALE_FACTOR
AXES = ("x", "y", "z")


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


@dataclass
class CubicFit:
    """The cubic written out, and how far it is from the bundle's curve on the grid (deg/s per axis).

    ``form``: what the cubic was fitted for, ``"px4"`` (least squares of e(T) = cubic - curve, PX4
    applies the cubic as it is) or ``"difference"`` (ArduPilot's e(T) - e(T_cal): the minimax cubic).
    """

    cubic: Cubic
    max_error_dps: np.ndarray
    rms_error_dps: np.ndarray
    model_class: str
    grid_points: int
    form: str = "px4"
    grid_c: np.ndarray | None = field(default=None, repr=False)
    curve_dps: np.ndarray | None = field(default=None, repr=False)

    def summary(self) -> dict[str, Any]:
        grid = f"{self.grid_points} temperatures over [TMIN, TMAX] at dT/dt = 0"
        found = {"model_class": self.model_class, "temp_min_c": self.cubic.temp_min_c,
                 "temp_max_c": self.cubic.temp_max_c, "temp_ref_c": self.cubic.temp_ref_c,
                 "coef_dps": self.cubic.coef_dps.tolist(),
                 "max_error_dps": dict(zip(AXES, self.max_error_dps.tolist())),
                 "rms_error_dps": dict(zip(AXES, self.rms_error_dps.tolist())), "grid": grid, "fit_form": self.form}
        if self.grid_c is not None:
            bound, rms = difference_error(self.cubic(self.grid_c) - self.curve_dps)
            found["difference_max_error_dps"] = dict(zip(AXES, bound.tolist()))
            found["difference_rms_error_dps"] = dict(zip(AXES, rms.tolist()))
        return found


FORMS = ("px4", "difference")


def fit_cubic(grid_c: np.ndarray, curve_dps: np.ndarray, form: str = "px4", model_class: str = "?") -> CubicFit:
    """The cubic about mid-range fitted to the curve on the grid: least squares (``px4``) or minimax (``difference``)."""
    if form not in FORMS:
        raise GyronetError(f"the cubic is fitted in PX4's form or ArduPilot's difference form ({', '.join(FORMS)}), "
                           f"not {form!r}")
    temp_ref = 0.5 * (grid_c[0] + grid_c[-1])
    if form == "px4":
        coef = np.linalg.lstsq(np.vander(grid_c - temp_ref, 4, increasing=True), curve_dps, rcond=None)[0]
    else:  # ArduPilot's bound max e - min e is least for the minimax cubic (as_flown.minimax_cubic)
        coef = minimax_cubic(grid_c - temp_ref, curve_dps)
    cubic = Cubic(float(grid_c[0]), float(grid_c[-1]), temp_ref, coef)
    error = cubic(grid_c) - curve_dps
    return CubicFit(cubic, np.abs(error).max(0), np.sqrt(np.mean(error**2, 0)), model_class, len(grid_c), form,
                    grid_c, curve_dps)


def bundle_cubic(bundle_dir: str | Path, grid_points: int = 2001, form: str = "px4") -> CubicFit:
    """The cubic of a bundle's steady-state curve over its clamp range (or trained range), fitted for ``form``."""
    grid, target, _, model_class = bundle_curve(bundle_dir, grid_points)
    return fit_cubic(grid, target, form, model_class)


def _f32(value: float) -> float:
    return float(np.float32(value))


def px4_rows(cubic: Cubic, instance: int = 0, device_id: int = 0) -> list[tuple[str, float | int, int]]:
    """``TC_G_ENABLE`` and ``TC_G{instance}_*`` (name, value, MAV_PARAM_TYPE), coefficients in rad/s."""
    if not 0 <= instance <= 3:
        raise GyronetError(f"PX4 has gyro thermal parameters for instances 0-3 (TC_G0..TC_G3), not {instance}")
    prefix = f"TC_G{instance}"
    stored_id = int(device_id) - 2 ** 32 if device_id >= 2 ** 31 else int(device_id)  # a uint32 id in an int32
    rows: list[tuple[str, float | int, int]] = [("TC_G_ENABLE", 1, INT32), (f"{prefix}_ID", stored_id, INT32)]
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
             f"# {EXPORT_MARK}{': ' + source if source else ''}", "#",
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


def _check_output(bundle_dir: Path, output: Path) -> None:
    """Refuse an output that would replace what is not a parameter export: a bundle's file, a recording."""
    if output.suffix == ".json":
        raise GyronetError(f"output={output}: the cubic and its error go to <output>.json beside the .params file; "
                           "name the parameter file F.params")
    if output.resolve().parent == bundle_dir.resolve():
        raise GyronetError(f"output={output} is inside the bundle {bundle_dir}; write the parameters elsewhere")
    if output.exists() and (output.suffix != ".params" or EXPORT_MARK not in output.read_text(errors="replace")[:500]):
        raise GyronetError(f"output={output} exists and is not a parameter file gyronet exported (a vehicle's own "
                           ".params, a recording?), which export would replace; name a new .params file")
    sidecar = output.with_suffix(".json")
    if sidecar.exists() and '"stated_error_dps"' not in sidecar.read_text(errors="replace"):
        raise GyronetError(f"{sidecar} exists and is not an export's summary, which export would replace; "
                           "name the output otherwise")


def export_params(bundle_dir: str | Path, output: str | Path, stack: str = "px4", instance: int = 0,
                  device_id: int = 0, vehicle_id: int = 1, component_id: int = 1, grid_points: int = 2001,
                  temp_rate_c_per_s: float = DEFAULT_TEMP_RATE_C_PER_S, history: str | Path | None = None,
                  fit: str | None = None) -> dict:
    """Write ``output`` (.params) and ``output`` with suffix .json (the cubic and its error); return the summary.

    PX4 gets the least-squares cubic, ArduPilot the minimax one (its users see e(T) - e(T_cal));
    ``fit`` (``FORMS``) overrides that: ``px4`` for ArduPilot is the least RMS of e(T) - e(T_cal)
    over all pairs (2 var(e)), the minimax its least bound. The
    summary's ``stated_error_dps`` is the bound the stack's users get: PX4's as its firmware runs
    (1 Hz, 1 degC, at ``temp_rate_c_per_s``), ArduPilot's over T and T_cal. ``history``: a
    recording whose temperature history the errors are also measured on (``history_error``).
    """
    from gyronet.atomic import write_text

    if stack not in ("px4", "ardupilot"):
        raise GyronetError(f"parameters are written for px4 or ardupilot, not {stack!r}")
    _check_output(Path(bundle_dir), Path(output))
    for name, value, low, high in (("device_id", device_id, -2 ** 31, 2 ** 32 - 1), ("vehicle_id", vehicle_id, 1, 255),
                                   ("component_id", component_id, 0, 255)):
        if not low <= value <= high:  # a device id as PX4 stores it (int32) or as a ULog names it (uint32)
            raise GyronetError(f"{name} must be in [{low}, {high}], got {value}")
    if grid_points < 8:
        raise GyronetError(f"grid_points must be at least 8 to fit and check a cubic, got {grid_points}")
    if fit is not None and fit not in FORMS:
        raise GyronetError(f"fit must be one of {', '.join(FORMS)} (or null: the stack's own), got {fit!r}")
    grid, target, curve, model_class = bundle_curve(bundle_dir, grid_points)
    fit = fit_cubic(grid, target, fit or ("px4" if stack == "px4" else "difference"), model_class)
    summary = {"format": stack, "bundle": str(bundle_dir), "params": str(output), **fit.summary()}
    if stack == "px4":
        rows, name = px4_rows(fit.cubic, instance, device_id), "PX4 Pro"
        summary["px4_firmware"] = px4_stated_error(grid, fit.cubic(grid), target, temp_rate_c_per_s)
        summary["stated_error_dps"] = summary["px4_firmware"]["max_error_dps"]
        summary["stated_error"] = ("largest |offset PX4 applies - bundle's curve|, the offset held from each "
                                   f"publication (|T - T_published| <= {summary['px4_firmware']['temp_step_c']:g} degC)")
    else:
        rows, name = ardupilot_rows(fit.cubic, instance), "ArduPilot"
        other = fit_cubic(grid, target, "px4" if fit.form == "difference" else "difference").summary()
        # what the other fit would give ArduPilot's users, for comparison
        summary["other_fit"] = {k: other[k] for k in ("fit_form", "difference_max_error_dps", "difference_rms_error_dps")}
        summary["stated_error_dps"] = summary["difference_max_error_dps"]
        summary["stated_error"] = ("largest |e(T) - e(T_cal)| over T and the boot-calibration temperature T_cal in "
                                   "[TMIN, TMAX], e = cubic - bundle's curve (ArduPilot removes the constant at boot)")
    if history is not None:
        from gyronet.recordings.data import load_recording

        recording = load_recording(history)
        summary["history"] = {"recording": str(history), **history_error(
            recording.time_s, recording.temp_c, fit.cubic, curve(recording.temp_c), stack)}
    summary["n_params"] = len(rows)
    if stack == "px4" and not device_id:  # after every check: a refused export is one line
        log.warning("TC_G%d_ID is 0: PX4 applies TC_G%d_* only to the gyro whose device id it names; give "
                    "device_id=<CAL_GYRO%d_ID of the calibrated board>", instance, instance, instance)
    output = Path(output)
    output.parent.mkdir(parents=True, exist_ok=True)
    write_text(output, params_text(rows, name, vehicle_id, component_id, source=str(bundle_dir)))
    write_json(output.with_suffix(".json"), summary)
    return summary


__all__ = ["Cubic", "CubicFit", "FORMS", "ardupilot_cubic", "ardupilot_rows", "bundle_cubic", "bundle_curve",
           "clamp_range", "export_params", "fit_cubic", "params_text", "px4_cubic", "px4_rows", "read_params",
           "steady_features"]
