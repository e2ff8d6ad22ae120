"""The compensator bundle (CONTRACT.md section 2): the only module that reads or writes TorchScript files.

A bundle is a folder: ``model.pt`` (TorchScript: features in, drift per axis out, deg/s),
``meta.json`` (what the features are and what the model saw) and, when the Kalman stage is on,
``kalman.json``. Loading needs neither the training code nor Hydra. TorchScript is deprecated in
favour of ``torch.export``; with the files read and written here alone, switching the format changes
this file (the error bar also scripts its members in memory, for speed: ``gyronet.model.error_bar``).
"""
from __future__ import annotations

import hashlib
import io
import json
import logging
from pathlib import Path
from typing import Any, Mapping, NamedTuple

import torch

from gyronet.atomic import atomic_output, write_json, write_text
from gyronet.bundle.schema import (gyronet_version, BUNDLE_FORMAT, KALMAN_FILE, META_FILE, MODEL_FILE, TRAINED_FILE, ModelFacts,
                                   check_trained, trained_json)
from gyronet.errors import BundleError
from gyronet.model.torchscript import quiet_torchscript

log = logging.getLogger(__name__)

__all__ = ["BUNDLE_FORMAT", "KALMAN_FILE", "META_FILE", "MODEL_FILE", "LoadedBundle", "gyronet_version",
           "load_bundle", "read_bundle", "save_bundle", "sha256_file"]


def sha256_file(path: str | Path) -> str:
    """Hex SHA-256 of a file's bytes."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def save_bundle(model: torch.nn.Module, meta: Mapping[str, Any], out_dir: str | Path,
                kalman: Mapping[str, Any] | None = None) -> Path:
    """Script ``model`` and write it with its metadata (and Kalman stage) into ``out_dir``.

    ``meta.json`` records the SHA-256 of ``model.pt`` and ``kalman.json``, and ``model.pt`` carries a
    copy of the meta fields its numbers depend on, so that :func:`load_bundle` can refuse a
    damaged file or an edited field by name.
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    full_meta = {"format": BUNDLE_FORMAT, "gyronet_version": gyronet_version(), **meta,
                 "kalman": kalman is not None}
    buffer = io.BytesIO()  # saved by name, the archive's folder would be the temporary file's random name
    with quiet_torchscript():
        torch.jit.save(torch.jit.script(model.eval()), buffer, _extra_files={TRAINED_FILE: trained_json(full_meta)})
    with atomic_output(out_dir / MODEL_FILE) as tmp:
        tmp.write_bytes(buffer.getvalue())
    sums = {MODEL_FILE: sha256_file(out_dir / MODEL_FILE)}
    kalman_path = out_dir / KALMAN_FILE
    if kalman is not None:
        write_json(kalman_path, kalman)
        sums[KALMAN_FILE] = sha256_file(kalman_path)
    elif kalman_path.exists():
        kalman_path.unlink()
    full_meta["sha256"] = sums
    write_text(out_dir / META_FILE, json.dumps(full_meta, indent=2) + "\n")
    log.info("bundle written to %s", out_dir)
    return out_dir


class LoadedBundle(NamedTuple):
    """A bundle's files, read and checked: the frozen model, ``meta.json``, ``kalman.json`` (or None)."""

    model: torch.jit.ScriptModule
    meta: dict[str, Any]
    kalman: dict[str, Any] | None
    facts: ModelFacts  # what the model said about itself before freezing
    verified: bool  # False for a bundle written before checksums


def load_unfrozen(bundle_dir: str | Path) -> torch.jit.ScriptModule:
    """The bundle's TorchScript model with its buffers and parameters, for code generators (no checks:
    call after :func:`read_bundle`, whose frozen model has folded them into constants)."""
    with quiet_torchscript():
        return torch.jit.load(str(Path(bundle_dir) / MODEL_FILE), map_location="cpu")


def load_bundle(bundle_dir: str | Path) -> tuple[torch.jit.ScriptModule, dict[str, Any], dict[str, Any] | None]:
    """Load ``model.pt``, ``meta.json`` and ``kalman.json`` (None when absent) from a bundle folder.

    A missing, damaged or mismatched file is a one-line :class:`BundleError` (:func:`read_bundle`).
    """
    return read_bundle(bundle_dir)[:3]


def read_bundle(bundle_dir: str | Path) -> LoadedBundle:
    """Read and check a bundle folder's files; the schema itself is :func:`gyronet.bundle.schema.validate_meta`.

    Checked here: the files exist, ``meta.json`` and ``kalman.json`` are JSON objects, the format
    number, the SHA-256 of ``model.pt`` and ``kalman.json`` against ``meta.json``, ``model.pt`` loads
    as TorchScript and was trained with the fields ``meta.json`` now holds, and ``kalman.json``
    is present exactly when ``meta.json`` says ``kalman: true``. A bundle without checksums
    (written before they existed) loads with one warning.
    """
    bundle_dir = Path(bundle_dir)
    if not bundle_dir.is_dir():
        what = "a file; model= takes the bundle's folder" if bundle_dir.is_file() else "no such folder"
        raise BundleError(f"{bundle_dir}: not a compensator bundle ({what})")
    for name in (MODEL_FILE, META_FILE):
        if not (bundle_dir / name).is_file():
            inner = next((d for d in (bundle_dir / "compensator", bundle_dir / "best" / "compensator")
                          if (d / META_FILE).is_file()), None)  # a run's or a sweep's folder, not its bundle
            raise BundleError(f"{bundle_dir}: not a compensator bundle (no {name})"
                              + (f"; did you mean {inner}?" if inner is not None else ""))
    meta_path, model_path, kalman_path = (bundle_dir / n for n in (META_FILE, MODEL_FILE, KALMAN_FILE))
    meta = _read_json(meta_path)
    if meta.get("format") != BUNDLE_FORMAT or isinstance(meta.get("format"), bool):
        raise BundleError(f"{meta_path}: bundle format {meta.get('format')!r}, this gyronet reads {BUNDLE_FORMAT}")
    wants_kalman = meta.get("kalman", False)
    if wants_kalman is True and not kalman_path.is_file():
        raise BundleError(f"{meta_path}: says kalman: true, but {KALMAN_FILE} is missing; re-copy the bundle "
                          "(or retrain with kalman=disabled)")
    if wants_kalman is not True and kalman_path.exists():
        raise BundleError(f"{kalman_path}: present, but {META_FILE} says kalman: {json.dumps(wants_kalman)}; "
                          f"delete {KALMAN_FILE} to run without the Kalman stage, or re-copy the bundle")
    sums = meta.get("sha256")
    verified = isinstance(sums, dict) and MODEL_FILE in sums
    if verified:
        for name, path in ((MODEL_FILE, model_path), (KALMAN_FILE, kalman_path)):
            if path.is_file() and sums.get(name) != sha256_file(path):
                raise BundleError(f"{path}: checksum differs from the one {META_FILE} recorded at training "
                                  "(the file is damaged or from another bundle); re-copy the bundle or retrain")
        if wants_kalman is True and KALMAN_FILE not in sums:
            raise BundleError(f"{meta_path}: has no checksum for {KALMAN_FILE}; re-copy the bundle or retrain")
    else:
        log.warning("%s: written before bundles had checksums; its files cannot be verified (retrain or re-save "
                    "it to add them)", bundle_dir)
    model, facts, trained = _load_model(model_path)
    if trained is not None:
        check_trained(meta, trained, str(meta_path))
    elif verified:
        raise BundleError(f"{model_path}: carries no training fields although {META_FILE} has checksums")
    kalman = _read_json(kalman_path) if wants_kalman is True else None
    return LoadedBundle(model, meta, kalman, facts, verified)


def _read_json(path: Path) -> dict[str, Any]:
    try:
        data = json.loads(path.read_bytes().decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        raise BundleError(f"{path}: not valid JSON ({err})") from None
    except OSError as err:
        raise BundleError(f"{path}: cannot be read ({err.strerror or err})") from None
    if not isinstance(data, dict):
        raise BundleError(f"{path}: must hold a JSON object, not {type(data).__name__}")
    return data


def _load_model(path: Path) -> tuple[torch.jit.ScriptModule, ModelFacts, dict[str, Any] | None]:
    """TorchScript load, what the model says about itself, then freeze."""
    extra = {TRAINED_FILE: ""}
    try:
        with quiet_torchscript():
            loaded = torch.jit.load(str(path), map_location="cpu", _extra_files=extra).eval()
            facts = ModelFacts(str(loaded.original_name), _int_attr(loaded, "n_inputs", "x_mean"),
                               _int_attr(loaded, "temp_index") if not hasattr(loaded, "x_mean") else None)
            # frozen: parameters become constants, which trims the per-call overhead of a live sample
            model = torch.jit.freeze(loaded)
    except Exception as err:  # noqa: BLE001 - torch raises RuntimeError, ValueError, ... on a bad file
        first = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise BundleError(f"{path}: not a readable TorchScript model ({first[:160]})") from None
    trained = None
    if extra[TRAINED_FILE]:
        try:
            trained = json.loads(extra[TRAINED_FILE])
        except (UnicodeDecodeError, json.JSONDecodeError, TypeError):
            raise BundleError(f"{path}: its copy of the training fields is damaged; re-copy the bundle") from None
    return model, facts, trained


def _int_attr(module: torch.jit.ScriptModule, name: str, buffer: str | None = None) -> int | None:
    value = getattr(module, name, None)
    if isinstance(value, int) and not isinstance(value, bool):
        return value
    if buffer is not None and isinstance(getattr(module, buffer, None), torch.Tensor):
        return int(getattr(module, buffer).shape[0])
    return None
