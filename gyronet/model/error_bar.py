"""A 1-sigma error bar on every sample's removed drift: how far to trust a compensated sample.

Per axis ``a`` and sample ``x`` (the causal features the drift is computed from)::

    sigma_a(x)^2 = floor_a^2 + (spread_scale_a * spread_a(x))^2 + sum_f (slope_af * d_f(x))^2

- ``spread_a(x)``: the standard deviation over the bundle's members (the starts that the default
  fit mixes, ``gyronet.training.starts``; any number of them, one gives 0) of their drift at ``x``: where the
  fits disagree, the data did not pin the drift down.
- ``d_f(x)``: how far feature ``f`` lies outside the trained box (normalised units, 0 inside).
  Outside it the model holds its edge value (temperature) or continues a straight line (the rate
  terms); ``slope_af`` is the model's own RMS sensitivity to that feature over the training
  samples nearest that edge, so the bar grows as fast as the drift was changing where the data end.
- ``floor_a`` and ``spread_scale_a``: from the Gaussian likelihood of the training's own held-out
  60 s blocks (``gyronet.training.error_bar_fit.calibrate``; never on evaluation data), with the
  white noise of a 60 s mean (from the held-out samples' first differences) as a known extra
  variance, so that ``sigma`` is the error of the drift alone, not of the noise.

The same numbers in floats for one row (the live path) and in C (``gyronet.deploy.c._error_bar``).
A bundle without an error bar (trained before it existed) gives NaN.
"""
from __future__ import annotations

import copy
import logging
import math
from typing import Any, Mapping, Sequence

import numpy as np
import torch

from gyronet.errors import BundleError
from gyronet.model.torchscript import quiet_torchscript

log = logging.getLogger(__name__)

BLOCK_S = 60.0  # the contract's residual block: what the bar is calibrated on
# Rows per model call on a long batch, for the bundle's model (gyronet.bundle.compensator) and the bar's members
# alike: 8 k rows' intermediates stay in cache, several times faster on a whole recording than one call (bench.py);
# 64 k rows did as well for one start's 12 Gaussians, and 13-23 % worse than 8 k for the mixed default and its bar.
CHUNK_ROWS = 8192
EDGE_FRACTION = 0.1  # the share of the box's width at each edge where the edge slopes are taken
META_KEY = "error_bar"
FORMAT = 1
CROSS_CHECK_LOW = 0.60  # a campaign's held-out runs with fewer blocks within 1 sigma: the bar is too narrow
_MEMBER_STATE = ("x_mean", "x_std", "z_low", "z_high", "y_mean", "y_std", "centers", "raw_width",
                 "head.weight", "head.bias", "linear.weight", "poly.weight")


class ErrorBar:
    """The error-bar model of one bundle: members, floor, spread scale and the box's edge slopes.

    Parameters
    ----------
    floor_dps, spread_scale
        (3,) per axis: the bar inside the box where the members agree (deg/s), and the factor on
        their spread.
    box_mean, box_std, box_low, box_high
        (n_features,): the features' normalisation and the trained box in normalised units.
    slope_low_dps, slope_high_dps
        (3, n_features): deg/s per normalised unit below the box's low and above its high edge.
    members
        An ``RBFNet`` whose ``3 * n_members`` outputs are every member's drift side by side (member
        k's axis a at ``3 k + a``), or None (one member: no spread).
    calibration
        What the calibration saw (blocks, coverage on them), for the record.
    """

    def __init__(self, floor_dps: Sequence[float], spread_scale: Sequence[float], box_mean: Sequence[float],
                 box_std: Sequence[float], box_low: Sequence[float], box_high: Sequence[float],
                 slope_low_dps: Sequence[Sequence[float]], slope_high_dps: Sequence[Sequence[float]],
                 members: torch.nn.Module | None = None, calibration: Mapping[str, Any] | None = None):
        self.floor_dps = np.asarray(floor_dps, dtype=np.float64)
        self.spread_scale = np.asarray(spread_scale, dtype=np.float64)
        self.box_mean, self.box_std = np.asarray(box_mean, np.float64), np.asarray(box_std, np.float64)
        self.box_low, self.box_high = np.asarray(box_low, np.float64), np.asarray(box_high, np.float64)
        self.slope_low_dps = np.asarray(slope_low_dps, dtype=np.float64)
        self.slope_high_dps = np.asarray(slope_high_dps, dtype=np.float64)
        self.members = members.eval() if members is not None else None
        self.n_members = 1 if members is None else int(members.n_outputs) // 3
        self.calibration = dict(calibration or {})
        self._row_members = None
        self._scripted = None  # the members network, scripted and frozen on first use

    @property
    def startup_s(self) -> float:
        """The start-up window its held-out runs were scored with (0: none, so a window's offset noise is not in it)."""
        return float(self.calibration.get("startup_s") or 0.0)

    # -- evaluation -------------------------------------------------------------------------------

    def member_drift(self, features: np.ndarray) -> np.ndarray:
        """Every member's drift, (n, n_members, 3), deg/s (TorchScript, frozen, in chunks as the drift is)."""
        if self._scripted is None:
            with quiet_torchscript():
                self._scripted = torch.jit.freeze(torch.jit.script(copy.deepcopy(self.members)))
        features = np.ascontiguousarray(features, dtype=np.float64)
        x = torch.from_numpy(features if features.flags.writeable else features.copy())  # torch reads, but warns
        with torch.no_grad():
            out = torch.cat([self._scripted(chunk) for chunk in x.split(CHUNK_ROWS)]) if len(x) else x.new_zeros(
                (0, 3 * self.n_members))
        return out.numpy().reshape(len(features), self.n_members, 3)

    def spread(self, features: np.ndarray) -> np.ndarray:
        """The members' standard deviation per axis, (n, 3), deg/s (0 with one member)."""
        if self.members is None:
            return np.zeros((len(features), 3))
        out = self.member_drift(features)
        deviation = out - out.mean(axis=1, keepdims=True)
        return np.sqrt(np.einsum("nka,nka->na", deviation, deviation) / self.n_members)

    def outside_dps(self, features: np.ndarray) -> np.ndarray:
        """The box term per axis, (n, 3), deg/s: sqrt(sum_f (slope_af d_f)^2), 0 inside the box."""
        z = (np.asarray(features, dtype=np.float64) - self.box_mean) / self.box_std
        below = np.maximum(self.box_low - z, 0.0)
        above = np.maximum(z - self.box_high, 0.0)
        return np.sqrt(below ** 2 @ (self.slope_low_dps ** 2).T + above ** 2 @ (self.slope_high_dps ** 2).T)

    def sigma(self, features: np.ndarray) -> np.ndarray:
        """The 1-sigma error bar of the drift at each row of ``features``, (n, 3), deg/s."""
        spread = self.spread(features)
        outside = self.outside_dps(features)
        return np.sqrt(self.floor_dps ** 2 + (self.spread_scale * spread) ** 2 + outside ** 2)

    def sigma_row(self, features: list) -> list:
        """``sigma`` on one row of plain floats (the live path's one-frame chunk); the same to rounding."""
        if self.members is not None and self._row_members is None:
            from gyronet.model.small_model import row_model

            self._row_members = row_model(self.members)
        var = [f * f for f in self.floor_dps.tolist()]
        if self._row_members is not None:
            out = self._row_members(features)
            m = self.n_members
            for a in range(3):
                values = out[a::3]
                mean = sum(values) / m
                s = self.spread_scale[a] * math.sqrt(sum((v - mean) ** 2 for v in values) / m)
                var[a] += s * s
        for f, (v, mu, sd, lo, hi) in enumerate(zip(features, self.box_mean.tolist(), self.box_std.tolist(),
                                                     self.box_low.tolist(), self.box_high.tolist())):
            z = (v - mu) / sd
            d, slopes = (lo - z, self.slope_low_dps) if z < lo else (z - hi, self.slope_high_dps)
            if d > 0:
                for a in range(3):
                    s = slopes[a, f] * d
                    var[a] += s * s
        return [math.sqrt(v) for v in var]

    def trust_line(self) -> str:
        """What the bar rests on, one line for a deployment's log: how far to trust ``drift_sigma``."""
        blocks = f"{self.calibration.get('n_blocks', 0)} {BLOCK_S:g} s blocks"
        runs, cross = self.calibration.get("held_out"), self.calibration.get("cross_within_1_sigma")
        if runs:
            checked = "" if not cross else ("; each run's blocks within a bar fitted on the other runs: "
                                            + "/".join(f"{v:.0%}" for v in cross) + " (x/y/z; goal 60-76 %)")
            if self.narrow_axes():
                checked += f": too narrow on {', '.join(self.narrow_axes())}, expect larger errors on a next run"
            return f"drift_sigma: calibrated on {blocks} of {len(runs)} runs, each held out in turn{checked}"
        return (f"drift_sigma: calibrated on {blocks} held out of one recording; on a real sensor's next run the "
                "error was 3-15x it (docs/results/error-bars.md): a campaign (data.paths) calibrates it across runs")

    def narrow_axes(self) -> list[str]:
        """The axes a campaign's cross-check found too narrow (under ``CROSS_CHECK_LOW`` of blocks within 1 sigma)."""
        return [a for a, v in zip("xyz", self.calibration.get("cross_within_1_sigma") or ()) if v < CROSS_CHECK_LOW]

    # -- meta.json ----------------------------------------------------------------------------------

    def to_dict(self) -> dict[str, Any]:
        """The ``meta.json`` block (``error_bar``): plain numbers."""
        return {"format": FORMAT, "floor_dps": self.floor_dps.tolist(), "spread_scale": self.spread_scale.tolist(),
                "box": {"mean": self.box_mean.tolist(), "std": self.box_std.tolist(),
                        "low": self.box_low.tolist(), "high": self.box_high.tolist()},
                "slope_low_dps": self.slope_low_dps.tolist(), "slope_high_dps": self.slope_high_dps.tolist(),
                "n_members": self.n_members,
                "members": None if self.members is None else _members_to_dict(self.members),
                "calibration": _plain(self.calibration)}

    @classmethod
    def from_dict(cls, data: Any, n_features: int, source: str) -> "ErrorBar":
        """The block back; a damaged one is a one-line BundleError naming ``source`` and the field."""
        def array(value: Any, shape: tuple, what: str) -> np.ndarray:
            try:
                out = np.asarray(value, dtype=np.float64)
            except (TypeError, ValueError):
                out = None
            if out is None or out.shape != shape or not np.isfinite(out).all():
                raise BundleError(f"{source}: 'error_bar.{what}' must be {shape} finite numbers, got {value!r:.80}")
            return out

        if not isinstance(data, Mapping) or data.get("format") != FORMAT:
            raise BundleError(f"{source}: 'error_bar' must be an object of format {FORMAT}")
        box = data.get("box")
        if not isinstance(box, Mapping):
            raise BundleError(f"{source}: 'error_bar.box' must be an object with mean, std, low, high")
        f = (n_features,)
        parts = {k: array(box.get(k), f, f"box.{k}") for k in ("mean", "std", "low", "high")}
        if not (parts["std"] > 0).all():
            raise BundleError(f"{source}: 'error_bar.box.std' must be > 0")
        floor = array(data.get("floor_dps"), (3,), "floor_dps")
        scale = array(data.get("spread_scale"), (3,), "spread_scale")
        if (floor < 0).any() or (scale < 0).any():
            raise BundleError(f"{source}: 'error_bar.floor_dps' and 'spread_scale' must be >= 0")
        members = data.get("members")
        try:
            members = None if members is None else _members_from_dict(members, n_features)
        except (KeyError, TypeError, ValueError, RuntimeError) as err:
            raise BundleError(f"{source}: 'error_bar.members' is not a members network ({err})"[:200]) from None
        return cls(floor, scale, parts["mean"], parts["std"], parts["low"], parts["high"],
                   array(data.get("slope_low_dps"), (3, n_features), "slope_low_dps"),
                   array(data.get("slope_high_dps"), (3, n_features), "slope_high_dps"),
                   members, data.get("calibration") if isinstance(data.get("calibration"), Mapping) else {})


def from_meta(meta: Mapping[str, Any], source: str) -> ErrorBar | None:
    """The bundle's error bar, or None (with one warning) for a bundle trained before it existed."""
    if META_KEY not in meta:
        log.warning("%s: no error bar in this bundle (trained before gyronet had one): the drift_sigma_*_dps "
                    "columns are NaN; retrain to get them", source)
        return None
    return ErrorBar.from_dict(meta[META_KEY], len(meta["features"]), source)


# -- the members network --------------------------------------------------------------------------


@torch.no_grad()
def stack_members(parts: Sequence[torch.nn.Module]) -> torch.nn.Module | None:
    """One ``RBFNet`` whose outputs are every part's drift side by side (part k's axis a at 3 k + a).

    None for a single part or a model that is not an ``RBFNet``. The parts must share their
    normalisation and box (fits on the same data, as the starts are).
    """
    from gyronet.model.rbf import RBFNet

    if len(parts) < 2 or not all(type(p).__name__ == "RBFNet" for p in parts):
        return None
    first = parts[0]
    for name in ("x_mean", "x_std", "z_low", "z_high", "rbf_index", "group_columns", "axis_group"):
        if not all(torch.equal(getattr(p, name), getattr(first, name)) for p in parts):
            raise ValueError(f"the members normalise differently ({name}): they must share their data")
    n_out = 3 * len(parts)
    net = RBFNet(first.n_inputs, n_out, sum(p.n_centers for p in parts), rbf_inputs=first.rbf_inputs,
                 linear=first.use_linear, temp_degree=first.temp_degree, temp_index=first.temp_index,
                 clamp=first.clamp, axis_columns=first.axis_columns * len(parts))
    net.min_width = first.min_width
    for name in ("x_mean", "x_std", "z_low", "z_high"):
        getattr(net, name).copy_(getattr(first, name))
    net.y_mean.copy_(torch.cat([p.y_mean for p in parts]))
    net.y_std.copy_(torch.cat([p.y_std for p in parts]))
    net.centers.copy_(torch.cat([p.centers for p in parts]))
    net.raw_width.copy_(torch.cat([p.raw_width for p in parts]))
    net.head.weight.zero_()
    column = 0
    for k, p in enumerate(parts):
        net.head.weight[3 * k:3 * k + 3, column:column + p.n_centers] = p.head.weight
        column += p.n_centers
    net.head.bias.copy_(torch.cat([p.head.bias for p in parts]))
    net.linear.weight.copy_(torch.cat([p.linear.weight for p in parts]))
    net.poly.weight.copy_(torch.cat([p.poly.weight for p in parts]))
    return net.eval()


def _members_to_dict(net: torch.nn.Module) -> dict[str, Any]:
    state = net.state_dict()
    return {"n_inputs": net.n_inputs, "n_outputs": net.n_outputs, "n_centers": net.n_centers,
            "rbf_inputs": list(net.rbf_inputs), "linear": bool(net.use_linear), "temp_degree": net.temp_degree,
            "temp_index": net.temp_index, "clamp": bool(net.clamp), "min_width": float(net.min_width),
            **({} if net.identity_columns else {"axis_columns": net.axis_columns}),
            "state": {k: state[k].tolist() for k in _MEMBER_STATE}}


def _members_from_dict(data: Mapping[str, Any], n_features: int) -> torch.nn.Module:
    from gyronet.model.rbf import RBFNet

    if int(data["n_inputs"]) != n_features or int(data["n_outputs"]) % 3:
        raise ValueError(f"{data['n_inputs']} inputs and {data['n_outputs']} outputs for {n_features} features")
    net = RBFNet(int(data["n_inputs"]), int(data["n_outputs"]), int(data["n_centers"]),
                 rbf_inputs=[int(i) for i in data["rbf_inputs"]], linear=bool(data["linear"]),
                 temp_degree=int(data["temp_degree"]), temp_index=int(data["temp_index"]), clamp=bool(data["clamp"]),
                 axis_columns=data.get("axis_columns"))
    net.min_width = float(data["min_width"])
    state = net.state_dict()
    state.update({k: torch.tensor(data["state"][k], dtype=torch.float64).reshape(state[k].shape)
                  for k in _MEMBER_STATE})
    net.load_state_dict(state)
    return net.eval()


def _plain(value: Any) -> Any:
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple, np.ndarray)):
        return [_plain(v) for v in list(value)]
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    return value


__all__ = ["BLOCK_S", "ErrorBar", "from_meta", "stack_members"]
