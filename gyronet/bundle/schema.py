"""What a bundle's ``meta.json`` must hold, checked field by field, so a damaged or edited bundle
is refused in one line that names the file and the field instead of failing later or, worse,
compensating with the wrong features or rate.

The checks here are pure (dicts and a model in, a :class:`~gyronet.errors.BundleError` out);
:mod:`gyronet.bundle.io` reads the files and checks the checksums, :class:`gyronet.bundle.compensator.Compensator`
calls :func:`validate_meta` and :func:`check_model`.
"""
from __future__ import annotations

import json
import math
import re
from numbers import Real
from typing import Any, Mapping, NamedTuple

from gyronet.recordings.data import GYRO_COLUMNS
from gyronet.errors import BundleError
from gyronet.model.features import FeatureExtractor, feature_name, required_columns

BUNDLE_FORMAT = 1
MODEL_FILE, META_FILE, KALMAN_FILE = "model.pt", "meta.json", "kalman.json"
# a copy of the fields the model's numbers depend on, saved inside model.pt: an edit of meta.json
# that would change the output (fs_hz, features) is caught and named at load time
TRAINED_FILE = "gyronet/trained.json"
TRAINED_FIELDS = ("input_columns", "features", "feature_names", "fs_hz", "temp_range_c", "axes", "kalman",
                  "error_bar")  # error_bar: gyronet.model.error_bar (absent in older bundles)
AXES = ["x", "y", "z"]
# which gyro the training data held (optional; absent in older bundles, read as "raw"): the sensor's raw
# rate (LP-BUS, record.py, the simulator) or the host-corrected one of an LPMS-Control log
GYRO_SOURCES = ("raw", "host_corrected")
_ABSENT = object()

# kind -> {parameter: (required, check)}; parameters not listed are ignored
_POSITIVE = ("a number > 0", lambda v: _is_number(v) and v > 0)
_NON_NEGATIVE = ("a number >= 0", lambda v: _is_number(v) and v >= 0)
_NUMBER = ("a number", lambda v: _is_number(v))
_NAME = ("a column name", lambda v: isinstance(v, str) and v != "")
_FEATURE_KINDS: dict[str, dict[str, tuple[bool, tuple]]] = {
    "temp": {},
    "rate": {"tau_s": (False, _POSITIVE), "source": (False, _NAME)},
    "product": {},
    "lag": {"tau_s": (True, _POSITIVE), "source": (False, _NAME)},
    "column": {"source": (True, _NAME), "tau_s": (False, _NON_NEGATIVE)},
    "hysteresis": {"width": (True, _NON_NEGATIVE), "source": (False, _NAME)},
    "power": {"exponent": (True, _NUMBER), "centre": (False, _NUMBER), "source": (False, _NAME)},
    "time": {"tau_s": (False, ("a number > 0 or null", lambda v: v is None or (_is_number(v) and v > 0)))},
}


class ModelFacts(NamedTuple):
    """What a scripted model says about itself before freezing (freezing folds it away)."""

    class_name: str | None  # the eager class it was scripted from
    n_inputs: int | None  # its input width, when it records one (None: reads any width)
    temp_index: int | None  # the one column a temperature-only model reads


def _is_number(value: Any) -> bool:
    return isinstance(value, Real) and not isinstance(value, bool) and math.isfinite(value)


def _fail(source: str, what: str) -> BundleError:
    return BundleError(f"{source}: {what}")


def validate_meta(meta: Any, source: str = META_FILE) -> None:
    """Raise a one-line BundleError naming the first field of ``meta`` that is missing or wrong."""
    if not isinstance(meta, Mapping):
        raise _fail(source, f"must hold a JSON object, not {type(meta).__name__}")
    fmt = meta.get("format", BUNDLE_FORMAT)  # absent only in a meta not yet saved (build_meta's)
    if not (isinstance(fmt, int) and not isinstance(fmt, bool)) or fmt != BUNDLE_FORMAT:
        raise _fail(source, f"bundle format {fmt!r}; this gyronet reads format {BUNDLE_FORMAT}")
    _check_version(meta.get("gyronet_version", _ABSENT), source)
    for field in ("output", "data_sha256"):  # informational, but a schema is a schema
        if field in meta and not isinstance(meta[field], str):
            raise _fail(source, f"{field!r} must be a string, got {meta[field]!r}")
    for field in ("features", "feature_names", "fs_hz", "temp_range_c", "axes", "input_columns"):
        if field not in meta:
            raise _fail(source, f"missing field {field!r}; the bundle is incomplete (retrain or re-copy it)")
    features = meta["features"]
    if not isinstance(features, list) or not features:
        raise _fail(source, "'features' must be a non-empty list of feature specs")
    for i, spec in enumerate(features):
        _check_spec(spec, f"{source}: features[{i}]")
    fs_hz = meta["fs_hz"]
    if not _is_number(fs_hz) or fs_hz <= 0:
        raise _fail(source, f"'fs_hz' must be a sampling rate > 0 in Hz, got {fs_hz!r}")
    try:
        FeatureExtractor(features, float(fs_hz))
    except (ValueError, KeyError, TypeError) as err:
        raise _fail(source, f"'features' cannot be built ({err})") from None
    names = [feature_name(s) for s in features]
    if meta["feature_names"] != names:
        raise _fail(source, f"'feature_names' {meta['feature_names']!r} do not match the features {names!r}")
    low_high = meta["temp_range_c"]
    if not (isinstance(low_high, list) and len(low_high) == 2 and all(map(_is_number, low_high))
            and low_high[0] <= low_high[1]):
        raise _fail(source, f"'temp_range_c' must be [low, high] in degC with low <= high, got {low_high!r}")
    if meta["axes"] != AXES:
        raise _fail(source, f"'axes' must be {AXES!r}, got {meta['axes']!r}")
    columns = meta["input_columns"]
    if not (isinstance(columns, list) and all(isinstance(c, str) for c in columns)):
        raise _fail(source, f"'input_columns' must be a list of column names, got {columns!r}")
    needed = [c for c in dict.fromkeys([*required_columns(features), *GYRO_COLUMNS]) if c not in columns]
    if needed:
        raise _fail(source, f"'input_columns' lacks {', '.join(needed)}, which the features and output need")
    gyro = meta.get("gyro_source", "raw")
    if gyro not in GYRO_SOURCES:
        raise _fail(source, f"'gyro_source' must be one of {list(GYRO_SOURCES)}, got {gyro!r}")
    if not isinstance(meta.get("kalman", False), bool):
        raise _fail(source, f"'kalman' must be true or false, got {meta['kalman']!r}")
    sums = meta.get("sha256", {})
    if not (isinstance(sums, Mapping) and all(isinstance(v, str) and re.fullmatch(r"[0-9a-f]{64}", v)
                                              for v in sums.values())):
        raise _fail(source, "'sha256' must map file names to 64-digit hex checksums")
    model = meta.get("model", {})
    if not isinstance(model, Mapping) or not isinstance(model.get("class", ""), str):
        raise _fail(source, f"'model' must be an object with a 'class' name, got {model!r}")


def _check_spec(spec: Any, where: str) -> None:
    if not isinstance(spec, Mapping):
        raise BundleError(f"{where} must be an object like {{\"kind\": \"temp\"}}, got {spec!r}")
    kind = spec.get("kind")
    if kind not in _FEATURE_KINDS:
        raise BundleError(f"{where}: unknown kind {kind!r} (one of {', '.join(_FEATURE_KINDS)})")
    if "name" in spec and not isinstance(spec["name"], str):
        raise BundleError(f"{where}: 'name' must be a string, got {spec['name']!r}")
    for key, (required, (wanted, ok)) in _FEATURE_KINDS[kind].items():
        if key not in spec:
            if required:
                raise BundleError(f"{where}: kind {kind!r} needs {key!r} ({wanted})")
        elif not ok(spec[key]):
            raise BundleError(f"{where}: {key!r} must be {wanted}, got {spec[key]!r}")


def gyronet_version() -> str:
    """The installed gyronet version, or 'unknown' when run from a bare checkout."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("gyronet")
    except PackageNotFoundError:
        return "unknown"



def _major(version: str) -> int | None:
    match = re.match(r"\s*v?(\d+)", version)
    return int(match.group(1)) if match else None


def _check_version(version: Any, source: str) -> None:
    """A bundle from a newer major gyronet may mean something else by the same fields: refused."""
    if version is _ABSENT:
        return
    if not isinstance(version, str):
        raise _fail(source, f"'gyronet_version' must be a string, got {version!r}")
    ours, theirs = _major(gyronet_version()), _major(version)
    if ours is not None and theirs is not None and theirs > ours:
        raise _fail(source, f"written by gyronet {version}, newer than this gyronet {gyronet_version()}; "
                            "upgrade gyronet to use it")


def gyro_source_of(recording_metas) -> str | None:
    """The ``gyro_source`` a bundle records for its training recordings' metadata (None: none says).

    Any host-corrected recording makes the bundle host-corrected: on the raw stream it would be wrong.
    """
    said = {m.get("gyro_source") for m in recording_metas} - {None}
    if not said:
        return None
    return "host_corrected" if "host_corrected" in said else "raw"


def trained_fields(meta: Mapping[str, Any]) -> dict[str, Any]:
    """The fields of ``meta`` that the model's numbers depend on (saved inside ``model.pt``)."""
    return {k: meta[k] for k in TRAINED_FIELDS if k in meta}


def trained_json(meta: Mapping[str, Any]) -> str:
    """:func:`trained_fields` as canonical JSON."""
    return json.dumps(trained_fields(meta), sort_keys=True, allow_nan=False)


_DEFAULTS = {"kalman": False}


def check_trained(meta: Mapping[str, Any], saved: Mapping[str, Any], source: str) -> None:
    """Refuse a ``meta.json`` whose output-relevant fields differ from those saved with the model."""
    for key in TRAINED_FIELDS:
        now = meta.get(key, _DEFAULTS.get(key, "<missing>"))
        if key in saved and _canonical(now) != _canonical(saved[key]):
            raise _fail(source, f"{key!r} is {_short(now)} but model.pt was trained with {_short(saved[key])}; "
                                "meta.json was edited after training: restore it or retrain")


def _canonical(value: Any) -> str:
    """JSON with every number as a float: 2 and 2.0 are the same rate."""
    def numbers_as_floats(v: Any) -> Any:
        if isinstance(v, bool) or not isinstance(v, (int, float, list, dict)):
            return v
        if isinstance(v, list):
            return [numbers_as_floats(x) for x in v]
        if isinstance(v, dict):
            return {k: numbers_as_floats(x) for k, x in v.items()}
        return float(v)

    return json.dumps(numbers_as_floats(value), sort_keys=True)


def _short(value: Any, limit: int = 80) -> str:
    text = json.dumps(value, sort_keys=True) if not isinstance(value, str) else repr(value)
    return text if len(text) <= limit else text[:limit - 3] + "..."


def check_model(model: Any, facts: ModelFacts, meta: Mapping[str, Any], source: str) -> None:
    """Refuse a model that is not the one ``meta`` describes or does not take its features.

    ``model`` is called once on two rows of ``len(features)`` inputs (the temperature feature at the
    middle of the trained range, the others 0) and must return drift of shape (2, 3).
    """
    import torch

    n_features = len(meta["features"])
    described = meta.get("model", {}).get("class")
    if described and facts.class_name and described != facts.class_name:
        raise _fail(source, f"model.pt is a {facts.class_name}, but meta.json describes a {described}; "
                            "the files come from different bundles")
    if facts.n_inputs is not None and facts.n_inputs != n_features:
        raise _fail(source, f"model.pt takes {facts.n_inputs} inputs, but meta.json lists {n_features} features "
                            f"({', '.join(meta['feature_names'])})")
    if facts.temp_index is not None and facts.temp_index >= n_features:
        raise _fail(source, f"model.pt reads input {facts.temp_index}, but meta.json lists {n_features} features")
    probe = torch.zeros((2, n_features), dtype=torch.float64)
    low, high = meta["temp_range_c"]
    for i, spec in enumerate(meta["features"]):
        if spec["kind"] == "temp":
            probe[:, i] = 0.5 * (low + high)
    try:
        with torch.no_grad():
            out = model(probe)
    except Exception as err:  # noqa: BLE001 - any failure of a foreign TorchScript file is the bundle's
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise _fail(source, f"model.pt fails on {n_features} inputs ({first[:160]})") from None
    if not isinstance(out, torch.Tensor) or tuple(out.shape) != (2, len(AXES)):
        shape = tuple(out.shape) if isinstance(out, torch.Tensor) else type(out).__name__
        raise _fail(source, f"model.pt returns {shape} for 2 samples, not drift of shape (2, {len(AXES)})")
