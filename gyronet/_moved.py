"""Old import paths (``gyronet.train``, ``gyronet.stream``, ...) still work after the move by stage.

Each old name is the new module itself (one object, one state), found by a finder placed before
Python's own, and warns once with a DeprecationWarning naming the new path.
"""
from __future__ import annotations

import importlib
import importlib.abc
import importlib.machinery
import sys
import warnings

# old name under gyronet -> new name under gyronet
MOVED = {
    "data": "recordings.data", "fastcsv": "recordings.fastcsv", "csvtable": "recordings.csvtable",
    "importers": "recordings.importers", "guard": "recordings.guard", "skipping": "recordings.skipping",
    "rate_watch": "recordings.rate_watch",
    "features": "model.features", "filters": "model.filters", "small_model": "model.small_model",
    "baselines": "model.baselines", "px4": "model.px4", "kalman": "model.kalman",
    "error_bar": "model.error_bar",
    "bundle_schema": "bundle.schema", "export": "bundle.io", "compensator": "bundle.compensator",
    "offline": "bundle.offline", "startup": "bundle.startup",
    "train": "training.train", "starts": "training.starts", "capacity": "training.capacity",
    "runs": "training.runs", "run_offsets": "training.run_offsets", "dataset": "training.dataset",
    "ga": "training.ga", "error_bar_fit": "training.error_bar_fit", "sigma_table": "training.sigma_table",
    "pipeline": "training.pipeline", "fleet": "training.fleet",
    "plots": "figures.plots", "tb": "figures.tb",
    "stream": "deploy.stream",
    "table": "analysis.table", "campaign": "analysis.campaign", "rate_table": "analysis.rate_table",
    "diagnose": "analysis.diagnose", "survey": "analysis.survey",
}
_warned: set[str] = set()


def new_name(fullname: str) -> str | None:
    """The module an old dotted name now lives at, or None when the name did not move."""
    parts = fullname.split(".")
    if len(parts) < 2 or parts[0] != "gyronet" or parts[1] not in MOVED:
        return None
    return ".".join(["gyronet", MOVED[parts[1]], *parts[2:]])


class _Alias(importlib.abc.Loader):
    """Hands back the module at its new path instead of loading a second copy."""

    def __init__(self, new: str):
        self.new = new

    def create_module(self, spec):
        return importlib.import_module(self.new)

    def exec_module(self, module) -> None:
        pass


class MovedFinder(importlib.abc.MetaPathFinder):
    """Finds ``gyronet.<old>`` before the path finder could load a second copy from the new folder."""

    def find_spec(self, fullname, path=None, target=None):
        new = new_name(fullname)
        if new is None:
            return None
        old_top = fullname.split(".")[1]
        if old_top not in _warned:  # once per old module, not once per submodule under it
            _warned.add(old_top)
            warnings.warn(f"{fullname} is now {new}; the old path still works", DeprecationWarning, stacklevel=2)
        return importlib.machinery.ModuleSpec(fullname, _Alias(new))


def install() -> None:
    """Put the finder first on ``sys.meta_path`` (once)."""
    if not any(isinstance(f, MovedFinder) for f in sys.meta_path):
        sys.meta_path.insert(0, MovedFinder())
