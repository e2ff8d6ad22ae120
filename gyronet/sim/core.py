"""Put the pieces together: ``simulate()`` a static gyro in a chamber, ``write_simulation()``."""
from __future__ import annotations

import json
import logging
import os
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from gyronet.recordings.data import AXES, truth_path, write_recording
from gyronet.errors import GyronetError
from gyronet.recordings.fastcsv import write_csv
from gyronet.sim.effects import apply_effect
from gyronet.sim.noise import NoiseSpec, earth_rate_dps, gravity_g, gyro_noise_dps, quantise
from gyronet.sim.profiles import chamber_profile
from gyronet.sim.run import (decimate_columns, g_sensitivity_matrix, lose_rows, orientation_deg, run_bump_dps,
                             run_settle_dps, turn_on_bias_dps)
from gyronet.sim.draw import draw_sensor
from gyronet.sim.sensor import N_AXES, per_axis
from gyronet.sim.specs import AccelSpec, EarthSpec, Simulation, TemperatureSpec, as_spec, rate_steps_dps

log = logging.getLogger(__name__)

SENSOR_NAME = "gyronet-sim"


def _columns(prefix: str, values: np.ndarray, suffix: str = "_dps") -> dict[str, np.ndarray]:
    return {f"{prefix}_{axis}{suffix}": values[:, i] for i, axis in enumerate(AXES)}


def simulate(profile: str = "paper", fs_hz: float = 10.0, seed: int = 0, sensor_seed: int = 0,
             duration_s: float | None = None, profile_options: Mapping[str, Any] | None = None,
             noise: NoiseSpec | Mapping[str, Any] | None = None,
             temperature: TemperatureSpec | Mapping[str, Any] | None = None,
             sensor: Mapping[str, Any] | None = None,
             earth: EarthSpec | Mapping[str, Any] | None = None,
             accel: AccelSpec | Mapping[str, Any] | None = None,
             rate_steps: Sequence[Mapping[str, Any]] | None = None,
             effects: Mapping[str, Mapping[str, Any] | None] | None = None,
             orientation: str | None = None, decimate: int = 1,
             loss: Mapping[str, Any] | None = None, noise_seed: int | None = None) -> Simulation:
    """Simulate a static three-axis MEMS gyro in a thermal chamber.

    Parameters
    ----------
    profile
        Chamber profile kind: ``paper``, ``cycle``, ``random`` or ``constant``.
    fs_hz
        Sampling rate, Hz.
    seed
        Seed of everything that is not the sensor: the random profile, the noise (unless
        ``noise_seed``), the effects' auxiliary channels, the lost rows.
    sensor_seed
        Seed of the sensor's coefficients (:func:`gyronet.sim.sensor.draw_sensor`).
    noise_seed
        Seed of the gyro's, the temperature reading's and the accelerometer's noise (default ``seed``):
        two sensors in one chamber run share its history, not its noise.
    duration_s
        Record length, s (see :func:`gyronet.sim.profiles.chamber_profile`).
    profile_options
        The profile's own options, e.g. ``{"rate_c_per_min": 2.0}``, and ``corner_s``.
    noise, temperature, earth, accel
        :class:`NoiseSpec`, :class:`TemperatureSpec`, :class:`EarthSpec`, :class:`AccelSpec` or a
        mapping of their fields.
    sensor
        ``distribution`` (``default`` or ``survey``, :func:`gyronet.sim.sensor.draw_sensor`), overrides
        of the drawn sensor (``swing_dps`` or any :class:`SensorModel` field), and the run-level
        ``turn_on_bias_dps``, ``g_sensitivity_dps_per_g``, ``run_bump_dps`` and ``run_settle_dps`` of
        :mod:`gyronet.sim.run` (without ``turn_on_bias_dps``, a survey sensor's own ``turn_on_bias_std_dps``).
    rate_steps
        True rotation steps, see :func:`rate_steps_dps`.
    effects
        ``{name: {params}}`` of :mod:`gyronet.sim.effects`; a None value or ``enabled: false``
        leaves the effect off.
    orientation, decimate, loss
        Which axis is along gravity, averaging of ``decimate`` samples into one, and lost rows;
        see :mod:`gyronet.sim.run` (all off by default).

    Returns
    -------
    Simulation
    """
    noise_spec = as_spec(NoiseSpec, noise, "noise")
    temp_spec = as_spec(TemperatureSpec, temperature, "temperature")
    earth_spec = as_spec(EarthSpec, earth, "earth")
    accel_spec = as_spec(AccelSpec, accel, "accel")
    noise_seed = int(seed if noise_seed is None else noise_seed)
    for name, value in (("seed", seed), ("sensor_seed", sensor_seed), ("noise_seed", noise_seed)):
        if int(value) < 0:  # numpy's generators take no negative seed
            raise GyronetError(f"{name} must be 0 or more, got {value}")
    time_s, chamber_c = chamber_profile(profile, fs_hz, np.random.default_rng([int(seed), 1]),
                                        duration_s=duration_s, **dict(profile_options or {}))
    n = len(time_s)
    sensor = dict(sensor or {})
    bias_std_dps = sensor.pop("turn_on_bias_dps", None)
    g_sensitivity = g_sensitivity_matrix(sensor_seed, sensor.pop("g_sensitivity_dps_per_g", 0.0))
    bump_std_dps = sensor.pop("run_bump_dps", 0.0)
    settle_std_dps = sensor.pop("run_settle_dps", 0.0)
    model = draw_sensor(sensor_seed, **sensor)
    bias_seed = None if bias_std_dps is not None else sensor_seed
    if bias_std_dps is None:  # the sensor's own spread (zero but for the survey distribution), its own draw
        bias_std_dps = model.turn_on_bias_std_dps
    die_c = model.die_temperature_c(time_s, chamber_c, fs_hz)
    temp_rng = np.random.default_rng([noise_seed, 2])
    temp_c = quantise(die_c + temp_spec.noise_c * temp_rng.standard_normal(n), temp_spec.lsb_c)

    drift = model.history_drift_dps(time_s, die_c, fs_hz)
    truth_effects: dict[str, np.ndarray] = {}
    aux_columns: dict[str, np.ndarray] = {}
    applied = []
    for name, params in (effects or {}).items():
        params = dict(params or {})
        if not params.pop("enabled", True):
            continue
        out = apply_effect(name, params, time_s, fs_hz, die_c, chamber_c, seed)
        clash = set(out.columns) & ({"time_s", "temp_c"} | set(aux_columns))
        if clash or any(c.startswith(("gyro_", "acc_")) for c in out.columns):
            raise GyronetError(f"effect {name!r}: column name(s) {sorted(out.columns)} already used")
        drift = drift + out.drift_dps
        truth_effects.update(_columns(f"effect_{name}", out.drift_dps))
        aux_columns.update(out.columns)
        applied.append(name)

    run_parts: dict[str, np.ndarray] = {}
    turned_deg = orientation_deg(orientation, earth_spec.orientation_deg)
    if np.any(per_axis(bias_std_dps, "sensor.turn_on_bias_dps") != 0):
        run_parts["turn_on_bias"] = np.broadcast_to(turn_on_bias_dps(seed, bias_std_dps, bias_seed), (n, N_AXES))
    if np.any(g_sensitivity != 0):
        # drift += G f, f the specific force of this orientation (g)
        run_parts["g_sensitivity"] = np.broadcast_to(g_sensitivity @ gravity_g(turned_deg), (n, N_AXES))
    if np.any(per_axis(bump_std_dps, "sensor.run_bump_dps") != 0):
        run_parts["run_bump"] = run_bump_dps(seed, bump_std_dps, die_c, sensor_seed)
    if np.any(per_axis(settle_std_dps, "sensor.run_settle_dps") != 0):
        run_parts["run_settle"] = run_settle_dps(seed, settle_std_dps, time_s, sensor_seed)
    for part in run_parts.values():
        drift = drift + part
    earth_dps = earth_rate_dps(earth_spec.latitude_deg, turned_deg, earth_spec.rate_deg_hr)
    true_rate = earth_dps[None, :] + rate_steps_dps(time_s, rate_steps)
    ideal = true_rate + drift
    gyro = quantise(ideal + gyro_noise_dps(n, fs_hz, noise_spec, noise_seed), noise_spec.lsb_dps)
    added_noise = gyro - ideal  # the noise actually added, quantisation error included

    recording = {"time_s": time_s, "temp_c": temp_c, **_columns("gyro", gyro)}
    if accel_spec.enabled:
        acc_rng = np.random.default_rng([noise_seed, 4])
        acc = gravity_g(turned_deg)[None, :] \
            + accel_spec.noise_g * acc_rng.standard_normal((n, N_AXES))
        recording.update(_columns("acc", quantise(acc, accel_spec.lsb_g), suffix="_g"))
    recording.update(aux_columns)
    truth = {"time_s": time_s, "die_temp_c": die_c, "chamber_temp_c": chamber_c,
             **_columns("drift", drift), **_columns("noise", added_noise),
             **_columns("true_rate", true_rate), **truth_effects}
    for name, part in run_parts.items():
        truth.update(_columns(name, np.array(part)))
    recording, truth = decimate_columns(recording, decimate), decimate_columns(truth, decimate)
    out_fs_hz = fs_hz / int(decimate)
    recording, truth = lose_rows(recording, truth, out_fs_hz, seed, loss)
    meta = {"fs_hz": f"{out_fs_hz:g}", "sensor": SENSOR_NAME, "seed": str(seed),
            "sensor_seed": str(sensor_seed), "profile": profile,
            "effects": ",".join(applied) or "none",
            "arw_deg_rthr": _triple(noise_spec.arw_deg_rthr),
            "bias_instability_deg_hr": _triple(noise_spec.bias_instability_deg_hr),
            "rrw_deg_hr_rthr": _triple(noise_spec.rrw_deg_hr_rthr),
            # the true rate of the static test (the Earth's), which training subtracts: a user
            # writes it from the latitude and the mounting, as here
            "static_rate_dps": ",".join(f"{v:.9g}" for v in earth_dps)}
    if orientation is not None:
        meta["orientation"] = orientation
    if sensor.get("distribution", "default") != "default":
        meta["sensor_distribution"] = sensor["distribution"]
    if int(decimate) != 1:
        meta["decimated_from_hz"] = f"{fs_hz:g}"
    if noise_seed != int(seed):
        meta["noise_seed"] = str(noise_seed)
    log.info("simulated %d samples (%.2f h, profile %s, effects %s)", len(recording["time_s"]),
             n / fs_hz / 3600, profile, meta["effects"])
    run = {"turn_on_bias_dps": run_parts["turn_on_bias"][0].tolist()} if "turn_on_bias" in run_parts else {}
    if "g_sensitivity" in run_parts:
        run["g_sensitivity_dps_per_g"] = g_sensitivity.tolist()
    return Simulation(recording, truth, meta, model, applied, run)


def _triple(value: Any) -> str:
    return "/".join(f"{v:g}" for v in per_axis(value, "noise"))


def write_simulation(sim: Simulation, path: str | os.PathLike, fast: bool = True) -> tuple[Path, Path]:
    """Write the recording to ``path`` (``F.csv``) and its truth to ``F.truth.csv``.

    Parameters
    ----------
    sim
        The output of :func:`simulate`.
    path
        The recording's CSV path.
    fast
        Use the vectorised writer (:mod:`gyronet.recordings.fastcsv`, same format and 9 significant digits
        of each column's largest value); False uses :func:`gyronet.recordings.data.write_recording`
        (``%.9g``, several times slower).

    Returns
    -------
    recording_path, truth_path
    """
    writer = write_csv if fast else write_recording
    truth_meta = {**sim.meta, "truth": "1", "sensor_model": json.dumps(sim.sensor.to_dict())}
    if sim.run:
        truth_meta["run"] = json.dumps(sim.run)
    recording = writer(path, sim.recording, sim.meta)
    truth = writer(truth_path(path), sim.truth, truth_meta)
    log.info("wrote %s and %s", recording, truth)
    return Path(recording), Path(truth)
