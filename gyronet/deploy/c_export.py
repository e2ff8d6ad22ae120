"""``format=c``: a bundle as a dependency-free C99 compensator for microcontrollers.

``write_c`` writes ``gyronet_compensator.h`` and ``.c``: float32, no heap, no library calls but
``expf`` and ``sqrtf``, the whole causal compensator of ``Compensator.process`` for one sample
(temperature guard, feature filters with their gap bridging and restarts, the model with its clamp,
the out-of-range and bad-input flags, the start-up offset, the Kalman stage when the bundle has
one). The templates are ``gyronet/deploy/c/*.in``; the generated parts come from
``gyronet/deploy/c/_features.py``, ``_model.py`` and ``_kalman.py``.
"""
from __future__ import annotations

import logging
import re
from pathlib import Path
from typing import Any

from gyronet.atomic import write_text
from gyronet.bundle.schema import MODEL_FILE
from gyronet.deploy.c import HERE, c_float
from gyronet.deploy.c._error_bar import error_bar_code
from gyronet.deploy.c._features import aux_inputs, feature_code
from gyronet.deploy.c._kalman import kalman_code, no_kalman
from gyronet.deploy.c._model import model_code
from gyronet.errors import BundleError, ConfigError
from gyronet.model.features import GAP_FACTOR

log = logging.getLogger(__name__)

PREFIX = "gyronet"  # of every exported C name, and of the files' names
_BUNDLE_MARK = "\x00bundle\x00"  # the bundle's path, filled in after the names are prefixed
HEADER, SOURCE = "gyronet_compensator.h", "gyronet_compensator.c"
DRIVER = HERE / "csv_driver.c"  # a host program that runs the compensator over a CSV (tests, bench)

# (C type, name, count key or 1, comment): the state struct, in declaration order
_STATE = [
    ("double", "start_time_s", 1, "of the first sample since init (time features)"),
    ("double", "last_time_s", 1, "of the last accepted sample"),
    ("double", "guard_time_s", 1, "the temperature guard's last accepted reading"),
    ("double", "candidate_start_s", 1, "a run of rejected readings that agree: a step being confirmed"),
    ("double", "candidate_time_s", 1, ""),
    ("double", "offset_still_s", 1, "start-up offset window"),
    ("double", "offset_start_s", 1, ""),
    ("double", "offset_sum_dps", 3, ""),
    ("double", "offset_diff_sq", 3, "the window's squared first differences: its noise"),
    ("double", "watch_times", 33, "the rate watch (gyronet/recordings/rate_watch.py): the last SPAN + 1 stamps, a ring"),
    ("double", "watch_vote_times", 32, "the stamp of each of the last VOTES voting samples, a ring"),
    ("double", "watch_period_s", 1, "the sample period the stamps show (0: not yet, the bundle's)"),
    ("float", "last_row", "n_features", "features of the last accepted sample"),
    ("float", "filter", "n_filter", "lag: output as a float pair; rate tracker: last input, level - input, slope"),
    ("float", "play", "n_play", "hysteresis play operators"),
    ("float", "guard_temp_c", 1, ""),
    ("float", "candidate_temp_c", 1, ""),
    ("float", "offset_dps", 3, "subtracted before the Kalman stage"),
    ("float", "offset_last_dps", 3, "the window's last good sample"),
    ("float", "offset_var_dps2", 3, "the offset's noise variance, added to the error bar (WIDEN_FOR_OFFSET)"),
    ("float", "static_rate_dps", 3, ""),
    ("float", "last_out_dps", 3, "what a bad gyro axis becomes"),
    ("float", "drift_sigma_dps", 3, "the last sample's 1-sigma error bar of the removed drift (NaN: none)"),
    ("float", "kalman_x", "n_kalman", "Kalman state, the axes side by side"),
    ("float", "kalman_p", "n_kalman_p", "its covariance blocks, during the gain transient"),
    ("uint32_t", "kalman_n", 1, "samples filtered, up to the end of the gain transient"),
    ("uint32_t", "offset_count", 1, ""),
    ("uint32_t", "n_out_of_range", 1, "counts since init"),
    ("uint32_t", "n_bad_input", 1, ""),
    ("int", "started", 1, ""),
    ("int", "have_last", 1, ""),
    ("int", "guard_have", 1, ""),
    ("int", "n_candidate", 1, ""),
    ("int", "offset_mode", 1, "0 none, 1 armed, 2 in the window, 3 applied"),
    ("int", "watch_votes", 32, "+1 slower, -1 faster, 0: a ring"),
    ("int", "watch_head", 1, "the oldest stamp in watch_times"),
    ("int", "watch_vote_head", 1, "the oldest vote"),
    ("int", "watch_n_votes", 1, ""),
    ("int", "watch_since", 1, "samples since init or the last rate change, up to 41 (compared with 32 and 8)"),
    ("int", "rate_changed", 1, "1 once the rate changed to one not the bundle's: GYRONET_RATE_CHANGED from then on"),
]
# the template's optional helpers, and what a generated body calls them by
_HELPERS = {"LAG": "lag_", "TRACKER": "tracker_", "CLAMP": "clampf(", "IPOW": "ipow("}
_SIZES = {"double": 8, "float": 4, "uint32_t": 4, "int": 4}  # and their alignment (ILP32 and LP64 alike)


def _state(counts: dict[str, int]) -> tuple[str, int]:
    """The struct's fields as C, and its size in bytes (doubles first: no padding but at the end)."""
    lines, size = [], 0
    for ctype, name, count, comment in _STATE:
        n = counts[count] if isinstance(count, str) else count
        size += _SIZES[ctype] * n
        field = f"{name}[{n}]" if n > 1 or isinstance(count, str) else name
        lines.append(f"    {ctype} {field};" + (f" /* {comment} */" if comment else ""))
    return "\n".join(lines), -(-size // 8) * 8


def _fill(template: str, values: dict[str, str]) -> str:
    for key, value in values.items():
        template = template.replace(f"@{key}@", value)
    left = re.search(r"@[A-Z_]+@", template)
    if left:
        raise AssertionError(f"template placeholder {left.group(0)} not filled")
    return template


def write_c(bundle_dir: Path, out_dir: Path, prefix: str = PREFIX) -> dict[str, Any]:
    """Write ``out_dir/gyronet_compensator.{h,c}`` for the bundle; a bundle it cannot export is one BundleError line.

    ``prefix`` replaces ``gyronet`` in every name the files export (``<prefix>_step``, ``<PREFIX>_FS_HZ``,
    ``<prefix>_compensator.h``), so that one firmware can link a compensator per IMU.
    Returns a summary: ``files`` written, model ``kind``, ``state_bytes`` (``sizeof(gyronet_state)``),
    ``aux_inputs``, ``kalman`` and ``kalman_transient_samples``.
    """
    if not re.fullmatch(r"[a-z][a-z0-9_]*", prefix):  # lower case: imu and IMU would share the macros' names
        raise ConfigError(f"prefix must be a lower-case C identifier (a letter, then letters, digits or _), got "
                          f"{prefix!r}")
    from gyronet.bundle.compensator import Compensator
    from gyronet.bundle.io import load_unfrozen

    bundle_dir, out_dir = Path(bundle_dir), Path(out_dir)
    if out_dir.exists() and not out_dir.is_dir():  # before the work of generating the code
        raise ConfigError(f"output={out_dir} is a file; format=c writes two files into a folder: name one")
    compensator = Compensator.load(bundle_dir)  # every check a consumer makes, with its messages
    meta = compensator.meta
    specs, fs_hz = meta["features"], float(meta["fs_hz"])
    aux = aux_inputs(specs, meta["input_columns"])
    feats = feature_code(specs, fs_hz, aux, f"{bundle_dir}/meta.json")
    model_path = f"{bundle_dir}/{MODEL_FILE}"
    module = load_unfrozen(bundle_dir)
    centre, scale = _probe_box(module, meta)
    model = model_code(module, scale, centre, model_path)
    bar = error_bar_code(compensator.error_bar, len(specs), f"{bundle_dir}/meta.json")
    kalman = no_kalman() if compensator.kalman is None else kalman_code(compensator.kalman.to_dict())
    fields, state_bytes = _state({"n_features": len(specs), "n_filter": feats.n_filter, "n_play": feats.n_play,
                                  "n_kalman": kalman.n_states, "n_kalman_p": kalman.n_covariance})
    low, high = compensator.temp_range_c
    aux_param = "\n                 const float *aux," if aux else ""
    values = {
        "VERSION": str(meta.get("gyronet_version", "unknown")),
        "BUNDLE": (bundle_dir.name or str(bundle_dir)).replace("*/", "* /"),  # it goes into a comment
        "MODEL_CLASS": model.kind, "FS_HZ": repr(fs_hz),
        "FEATURE_NAMES": ", ".join(meta["feature_names"]).replace("*/", "* /"),
        "TEMP_LOW_C": c_float(low), "TEMP_HIGH_C": c_float(high), "N_AUX": str(len(aux)),
        "AUX_NAMES": ", ".join(aux).replace("*/", "* /") or "none", "HAS_KALMAN": str(int(compensator.kalman is not None)),
        "STATE_FIELDS": fields, "AUX_PARAM": aux_param, "N_FEATURES": str(len(specs)),
        "GAP_S": repr(GAP_FACTOR * (1.0 / fs_hz)),  # as FeatureExtractor computes it, to the last bit
        "AUX_COPY": "\n".join(f"    v[{k + 1}] = aux[{k}];" for k in range(len(aux))),
        "CONSTANTS": "\n".join(part for part in (feats.constants, model.constants, bar.constants, kalman.constants)
                               if part),
        "HAS_ERROR_BAR": str(int(compensator.error_bar is not None)),
        "WIDEN_FOR_OFFSET": str(int(compensator.error_bar is not None and not compensator.error_bar.startup_s)),
        "ERROR_BAR_MEMBERS": "" if not bar.members_body else (
            "/* the error bar's members: every start's drift side by side */\n"
            "static void members_drift(const float *x, float *members)\n{\n" + bar.members_body + "\n}\n"),
        "ERROR_BAR_BODY": bar.body,
        "FEATURES_ACCEPTED": feats.accepted, "FEATURES_POWER_ON": feats.power_on, "TIME_FEATURES": feats.time,
        "MODEL_BODY": model.body, "KALMAN_BODY": kalman.body,
    }
    code = "\n".join([feats.accepted, feats.power_on, model.body, bar.members_body])
    values["USES"] = "\n".join(f"#define USES_{name} {int(call in code)}" for name, call in _HELPERS.items())
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []
    for name in (HEADER, SOURCE):
        text = _fill((HERE / f"{name}.in").read_text(), {**values, "BUNDLE": _BUNDLE_MARK})
        if prefix != PREFIX:  # the exported names, not the bundle's path in the comment (filled after)
            text = re.sub(r"\bGYRONET_", f"{prefix.upper()}_", re.sub(r"\bgyronet_", f"{prefix}_", text))
        text = text.replace(_BUNDLE_MARK, values["BUNDLE"])
        path = out_dir / name.replace(PREFIX, prefix, 1)
        write_text(path, text)
        written.append(str(path))
    summary = {"files": written, "kind": model.kind, "state_bytes": state_bytes, "aux_inputs": aux,
               "kalman": compensator.kalman is not None, "kalman_transient_samples": kalman.n_transient,
               "model_numbers": model.n_numbers, "error_bar_numbers": bar.n_numbers,
               "error_bar": compensator.error_bar is not None, "features": list(meta["feature_names"])}
    log.info("C compensator (%s, state %d bytes) written to %s", model.kind, state_bytes, out_dir)
    return summary


def _probe_box(module: Any, meta: dict[str, Any]):
    """Where to probe the model: its own normalisation when it has one, else the trained temperature range."""
    import numpy as np

    if hasattr(module, "x_std") and hasattr(module, "x_mean"):
        return module.x_mean.double().numpy(), module.x_std.double().numpy()
    low, high = meta["temp_range_c"]
    n = len(meta["features"])
    centre, scale = np.zeros(n), np.ones(n)
    for i, spec in enumerate(meta["features"]):
        if spec["kind"] == "temp":
            centre[i], scale[i] = 0.5 * (low + high), max(0.5 * (high - low), 1.0)
    return centre, scale


__all__ = ["BundleError", "DRIVER", "HEADER", "SOURCE", "write_c"]
