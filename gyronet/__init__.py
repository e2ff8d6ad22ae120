"""gyronet: remove temperature-induced drift from MEMS gyroscopes.

The library has no Hydra dependency: ``gyronet.data`` (recordings), ``gyronet.features`` (causal
inputs), ``gyronet.model`` (the RBF network), ``gyronet.train`` (fit, evaluate),
``gyronet.compensator`` (a bundle, run causally offline and live), ``gyronet.allan``,
``gyronet.kalman``, ``gyronet.sim``, ``gyronet.stream``, ``gyronet.diagnose``, ``gyronet.importers``.
"""
from importlib.metadata import PackageNotFoundError, version

try:
    __version__ = version("gyronet")
except PackageNotFoundError:  # a bare checkout, not installed
    __version__ = "unknown"
