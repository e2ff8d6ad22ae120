"""The compensator bundle (CONTRACT.md section 2): the only module that touches ``torch.jit``.

A bundle is a folder: ``model.pt`` (TorchScript: features in, drift per axis out, deg/s),
``meta.json`` (what the features are and what the model saw) and, when the Kalman stage is on,
``kalman.json``. Loading needs neither the training code nor Hydra. TorchScript is deprecated in
favour of ``torch.export``; keeping all of it here means switching changes one file.
"""
from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Any, Mapping

import torch

from gyronet.errors import BundleError

log = logging.getLogger(__name__)

BUNDLE_FORMAT = 1
MODEL_FILE, META_FILE, KALMAN_FILE = "model.pt", "meta.json", "kalman.json"


def gyronet_version() -> str:
    """The installed gyronet version, or 'unknown' when run from a bare checkout."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("gyronet")
    except PackageNotFoundError:
        return "unknown"


def save_bundle(model: torch.nn.Module, meta: Mapping[str, Any], out_dir: str | Path,
                kalman: Mapping[str, Any] | None = None) -> Path:
    """Script ``model`` and write it with its metadata (and Kalman stage) into ``out_dir``."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    model = model.eval()
    scripted = torch.jit.script(model)
    scripted.save(str(out_dir / MODEL_FILE))
    full_meta = {"format": BUNDLE_FORMAT, "gyronet_version": gyronet_version(), **meta,
                 "kalman": kalman is not None}
    (out_dir / META_FILE).write_text(json.dumps(full_meta, indent=2) + "\n")
    kalman_path = out_dir / KALMAN_FILE
    if kalman is not None:
        kalman_path.write_text(json.dumps(kalman, indent=2) + "\n")
    elif kalman_path.exists():
        kalman_path.unlink()
    log.info("bundle written to %s", out_dir)
    return out_dir


def load_bundle(bundle_dir: str | Path) -> tuple[torch.jit.ScriptModule, dict[str, Any], dict[str, Any] | None]:
    """Load ``model.pt``, ``meta.json`` and ``kalman.json`` (None when absent) from a bundle folder."""
    bundle_dir = Path(bundle_dir)
    for name in (MODEL_FILE, META_FILE):
        if not (bundle_dir / name).is_file():
            raise BundleError(f"{bundle_dir}: not a compensator bundle (no {name})")
    try:
        meta = json.loads((bundle_dir / META_FILE).read_text())
    except json.JSONDecodeError as err:
        raise BundleError(f"{bundle_dir / META_FILE}: not valid JSON ({err})") from None
    if meta.get("format") != BUNDLE_FORMAT:
        raise BundleError(f"{bundle_dir}: bundle format {meta.get('format')!r}, this gyronet reads {BUNDLE_FORMAT}")
    # frozen: parameters become constants, which trims the per-call overhead of a live sample
    model = torch.jit.freeze(torch.jit.load(str(bundle_dir / MODEL_FILE), map_location="cpu").eval())
    kalman_path = bundle_dir / KALMAN_FILE
    kalman = json.loads(kalman_path.read_text()) if meta.get("kalman") and kalman_path.is_file() else None
    return model, meta, kalman
