"""Thermal-calibration ULogs with a known drift, and PX4's own script's answer on them (px4_reference.json).

The ULog is written with pyulog: a tiny seed log gives pyulog the ``sensor_gyro`` and
``sensor_baro`` formats (PX4's ``process_sensor_caldata.py`` needs a baro), and its data are then
replaced by the samples below and written back with ``ULog.write_ulog``. The board warms from 2 to
42 degC at 1 degC/min with 8-minute dwells at 15 and 30 degC, the temperature quantised to
1/16 degC as IMU drivers report it (so many samples sit exactly on PX4's bin edges); the bias is a
cubic plus a knee, with white noise and a few spikes for the median filter. A second case reports
0.01 degC steps over -7.1 .. 33.3 degC, where only PX4's float32 arithmetic puts every sample in
PX4's bin (``CASES``).

Regenerate the fixture (PX4's script run unmodified; it needs pyulog, scipy, matplotlib):

    git -C <PX4 checkout> show af44da25f0:Tools/process_sensor_caldata.py > /tmp/process_sensor_caldata.py
    python tests/data/px4_reference.py /tmp/process_sensor_caldata.py tests/data/px4_reference.json
"""
from __future__ import annotations

import hashlib
import json
import os
import struct
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

GENERATOR = {"seed": 14, "fs_hz": 5.0, "start_c": 2.0, "stop_c": 42.0, "rate_c_per_min": 1.0,
             "dwells_c": [15.0, 30.0], "dwell_s": 480.0, "quantum_c": 0.0625, "noise_rad_s": 0.002,
             "n_spikes": 40, "device_id": 2359306}
# the cases of the fixture: the first as above; the second reports 0.01 degC steps over -7.1 .. 33.3 degC,
# where computing the bins in float64 instead of PX4's float32 moves the curve by 3e-5 deg/s
CASES = {"quantum_1_16": GENERATOR,
         "quantum_0_01": {**GENERATOR, "seed": 6, "start_c": -7.1, "stop_c": 33.3, "quantum_c": 0.01,
                          "dwells_c": [0.0, 20.0]}}
SCRIPT_COMMIT = "af44da25f0fcbc597150c252d47872439160eb0e"

_GYRO = ("sensor_gyro:uint64_t timestamp;uint64_t timestamp_sample;uint32_t device_id;float x;float y;float z;"
         "float temperature;uint32_t error_count;")
_BARO = "sensor_baro:uint64_t timestamp;uint64_t timestamp_sample;uint32_t device_id;float pressure;float temperature;"


def _msg(kind: str, payload: bytes) -> bytes:
    return struct.pack("<HB", len(payload), ord(kind)) + payload


def _seed_bytes() -> bytes:
    """A ULog with the two formats, their subscriptions and one message each (replaced later)."""
    out = b"ULog\x01\x12\x35" + struct.pack("<BQ", 1, 0)
    out += _msg("B", bytes(16) + bytes(24))
    out += _msg("F", _GYRO.encode()) + _msg("F", _BARO.encode())
    out += _msg("A", struct.pack("<BH", 0, 0) + b"sensor_gyro") + _msg("A", struct.pack("<BH", 0, 1) + b"sensor_baro")
    out += _msg("D", struct.pack("<H", 0) + struct.pack("<QQIffffI", 1, 1, 1, 0, 0, 0, 20, 0))
    out += _msg("D", struct.pack("<H", 1) + struct.pack("<QQIff", 1, 1, 2, 1000, 20))
    return out


def profile(params: dict = GENERATOR) -> dict[str, np.ndarray]:
    """Time (us since boot), reported temperature (degC, float32) and gyro (rad/s, float32) of the run."""
    rng = np.random.default_rng(params["seed"])
    rate_c_per_s = params["rate_c_per_min"] / 60.0
    knots_t, knots_c = [0.0], [params["start_c"]]
    for target in [*params["dwells_c"], params["stop_c"]]:
        knots_t.append(knots_t[-1] + (target - knots_c[-1]) / rate_c_per_s)
        knots_c.append(target)
        if target != params["stop_c"]:
            knots_t.append(knots_t[-1] + params["dwell_s"])
            knots_c.append(target)
    time_s = np.arange(0.0, knots_t[-1], 1.0 / params["fs_hz"])
    true_c = np.interp(time_s, knots_t, knots_c)
    temp_c = (np.round(true_c / params["quantum_c"]) * params["quantum_c"]).astype(np.float32)
    u = (true_c - 22.0) / 20.0
    bias = np.column_stack([0.010 + 0.004 * u - 0.003 * u**2 + 0.002 * u**3 + 0.0015 * np.tanh((true_c - 25.0) / 2.0),
                            -0.005 + 0.006 * u + 0.001 * u**3,
                            0.002 - 0.002 * u + 0.004 * u**2 - 0.001 * np.tanh((true_c - 12.0) / 3.0)])
    gyro = bias + params["noise_rad_s"] * rng.standard_normal(bias.shape)
    spikes = rng.choice(len(time_s), params["n_spikes"], replace=False)
    gyro[spikes] += rng.choice([-0.5, 0.5], (params["n_spikes"], 3))
    return {"time_us": np.round(1e6 * (time_s + 1.0)).astype(np.uint64), "temp_c": temp_c,
            "gyro_rad_s": gyro.astype(np.float32)}


def write_caldata_ulog(path: str | os.PathLike, params: dict = GENERATOR) -> Path:
    """Write the run as a ULog with pyulog (``sensor_gyro`` instance 0 and ``sensor_baro``)."""
    from pyulog import ULog

    run = profile(params)
    with tempfile.TemporaryDirectory() as tmp:
        seed = Path(tmp) / "seed.ulg"
        seed.write_bytes(_seed_bytes())
        ulog = ULog(str(seed))
    n = len(run["time_us"])
    for data in ulog.data_list:
        fields = {"timestamp": run["time_us"], "timestamp_sample": run["time_us"] - np.uint64(50),
                  "temperature": run["temp_c"]}
        if data.name == "sensor_gyro":
            fields.update(device_id=np.full(n, params["device_id"], np.uint32), error_count=np.zeros(n, np.uint32),
                          x=run["gyro_rad_s"][:, 0], y=run["gyro_rad_s"][:, 1], z=run["gyro_rad_s"][:, 2])
        else:
            fields.update(device_id=np.full(n, 0x1234, np.uint32),
                          pressure=(1000.0 + 0.01 * run["temp_c"]).astype(np.float32))
        data.data = fields
    path = Path(path)
    ulog.write_ulog(str(path))
    return path


def sha256(path: str | os.PathLike) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def read_params(path: str | os.PathLike) -> dict[str, float]:
    """Name -> value from a QGroundControl .params file (tab-separated; '#' lines are comments)."""
    out = {}
    for line in Path(path).read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            fields = line.split("\t")
            out[fields[2]] = float(fields[3])
    return out


def gyro0(params: dict[str, float]) -> dict:
    """TC_G0_*: the temperatures and, per axis, the coefficients X0..X3 (rad/s per degC^k).

    The script writes TMIN, TMAX, TREF as numpy float32 (the shortest text of the float32): they
    are read back as float32, which recovers them exactly.
    """
    temps = {k: float(np.float32(params[f"TC_G0_{k}"])) for k in ("TMIN", "TMAX", "TREF")}
    return {**temps, "ID": int(params["TC_G0_ID"]),
            "coef_rad_s": [[params[f"TC_G0_X{k}_{axis}"] for axis in range(3)] for k in range(4)]}


def main(script: str, out: str) -> None:
    from importlib.metadata import version

    cases = {}
    with tempfile.TemporaryDirectory() as tmp:
        for case, params in CASES.items():
            log_path = write_caldata_ulog(Path(tmp) / f"{case}.ulg", params)
            cases[case] = {"generator": params, "ulog_sha256": sha256(log_path)}
            for name, extra in (("default", []), ("no_resample", ["--no_resample"])):
                env = {**os.environ, "MPLBACKEND": "Agg"}
                subprocess.run([sys.executable, script, str(log_path), *extra], check=True, env=env, cwd=tmp,
                               stdout=subprocess.DEVNULL)
                cases[case][name] = gyro0(read_params(str(log_path) + ".params"))
    fixture = {
        "note": "PX4's Tools/process_sensor_caldata.py run unmodified on the ULog that tests/data/px4_reference.py "
                "writes (write_caldata_ulog with each case's generator settings); TC_G0_* as it wrote them to "
                "<log>.params (TMIN, TMAX, TREF read back as float32). "
                "Regenerate: python tests/data/px4_reference.py <script> tests/data/px4_reference.json",
        "px4_script": {"path": "Tools/process_sensor_caldata.py", "repository": "PX4/PX4-Autopilot",
                       "commit": SCRIPT_COMMIT, "read_from": "m4v3r/PX4-Arrow at 86822171b9 (same file)",
                       "sha256": sha256(script)},
        "versions": {name: version(name) for name in ("numpy", "scipy", "pyulog", "matplotlib")},
        "cases": cases,
    }
    Path(out).write_text(json.dumps(fixture, indent=1) + "\n")


if __name__ == "__main__":
    main(*sys.argv[1:3])
