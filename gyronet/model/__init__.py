"""The drift model: causal features (T, dT/dt, T*dT/dt), the RBF network, baselines, Kalman stage.

``rbf`` holds ``RBFNet``; ``features`` the causal inputs; ``baselines`` and ``px4`` the cubics gyronet
must beat; ``kalman`` the filter after the network; ``error_bar`` the per-sample 1-sigma, and
``recalibration`` when a still record outgrows it.
May import: ``gyronet.errors``, ``gyronet.atomic``, ``gyronet.recordings``, ``gyronet.allan``.
"""
import importlib

_RBF_NAMES = {"RBFNet", "SelectionError", "forward_select", "CENTER_INITS", "OLS_STEP_C",
              "OLS_WIDTHS_C", "OLS_NARROW_WIDTHS_C"}


def __getattr__(name: str):
    """``gyronet.model.rbf.RBFNet`` (the old module's names, as in older bundles' configs), loaded on use."""
    if name in _RBF_NAMES:
        return getattr(importlib.import_module("gyronet.model.rbf"), name)
    raise AttributeError(f"module 'gyronet.model.rbf' has no attribute {name!r}")
