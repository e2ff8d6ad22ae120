"""gyronet: remove temperature-induced drift from MEMS gyroscopes.

The package is grouped by stage; a folder may import only the folders above it in this list
(``tests/test_layering.py`` checks it):

- ``errors``, ``atomic``: the error types and atomic file writes everything shares.
- ``recordings``: the recording format, fast CSV, importers, the sample guard and clock.
- ``allan``: Allan deviation, angle random walk N and bias instability B.
- ``sim``: the simulated sensor and thermal histories.
- ``figures``: plots and TensorBoard writers.
- ``model``: causal features, the RBF network, baselines (PX4 cubic), the Kalman stage, error bar.
- ``bundle``: the compensator bundle: format, save/load, the ``Compensator``, start-up offset.
- ``training``: fit, starts, capacity, campaigns of runs, GA, the training pipeline, fleets.
- ``deploy``: the live serial stream (LP-BUS, CSV), PX4/ArduPilot parameters, the C export.
- ``analysis``: Table 1, the real-data table, the survey, rate table, the diagnosis loop.

The library has no Hydra dependency. Old flat import paths (``gyronet.train``, ``gyronet.stream``,
...) still work and warn once (``gyronet._moved``).
"""
from importlib.metadata import PackageNotFoundError, version

from gyronet import _moved

try:
    __version__ = version("gyronet")
except PackageNotFoundError:  # a bare checkout, not installed
    __version__ = "unknown"

_moved.install()


def __getattr__(name: str):
    """``gyronet.train`` and the other old module attributes, imported on first use."""
    if name in _moved.MOVED:
        import importlib

        return importlib.import_module(f"gyronet.{name}")
    raise AttributeError(f"module 'gyronet' has no attribute {name!r}")
