"""The rows the screen works on: 60 s block means of the drift, of candidates and of a model's basis.

Everything is computed causally at the full rate by ``gyronet.model.features`` (the code the deployed
compensator runs) and only then averaged, so a block mean of a refitted output layer is exactly
the block mean of what the deployed model would output. One exception: lagged candidates are
scored as if their filter had started on the mean of the first block (``clean_start``), not on
the deployed filter's first noisy sample (see ``candidates.filter_tau``).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import numpy as np
import torch

from gyronet.recordings.data import Recording, block_means
from gyronet.training.dataset import featurize, static_rate_dps
from gyronet.analysis.diagnose.candidates import filter_tau
from gyronet.analysis.diagnose.screen import assign_folds

log = logging.getLogger(__name__)

_CHUNK = 8  # specs featurised at once: bounds the full-rate memory on long records


@dataclass
class ScreenRows:
    """Block-averaged rows of one training recording and, optionally, a separate validation one.

    Attributes
    ----------
    recordings
        The training recording first, then the validation recording if any.
    fs_hz
        The rate the features are computed for (the training recording's).
    block_s
        Block length, s (the contract's 60 s).
    time_s, recording, fold
        (n,) block mid-time, recording index and held-out fold (-1: never held out).
    target
        (n, 3) block means of gyro minus the static rate, deg/s.
    """

    recordings: list[Recording]
    fs_hz: float
    block_s: float
    time_s: np.ndarray
    recording: np.ndarray
    fold: np.ndarray
    target: np.ndarray
    keep: np.ndarray | None = None  # (all blocks,) which blocks the rows are; None: all

    @classmethod
    def build(cls, recordings: Sequence[Recording], fs_hz: float, block_s: float = 60.0, n_spans: int = 20,
              n_folds: int = 5, static_rate: Sequence[float] | None = None) -> "ScreenRows":
        """Rows of ``recordings`` (one: K-fold over time spans; two: fit on the first, score on the second)."""
        times, ids, folds, targets = [], [], [], []
        for index, rec in enumerate(recordings):
            drift = rec.gyro_dps - static_rate_dps(rec, static_rate)[None, :]
            mid_s = block_means(rec.time_s, rec.time_s, block_s)
            times.append(mid_s)
            ids.append(np.full(len(mid_s), index))
            targets.append(block_means(drift, rec.time_s, block_s))
            if len(recordings) == 1:
                folds.append(assign_folds(mid_s, n_spans, n_folds))
            else:
                folds.append(np.full(len(mid_s), -1 if index == 0 else 0))
        return cls(list(recordings), float(fs_hz), float(block_s), np.concatenate(times),
                   np.concatenate(ids), np.concatenate(folds), np.concatenate(targets))

    @classmethod
    def build_runs(cls, recordings: Sequence[Recording], fs_hz: float, block_s: float = 60.0, span_s: float = 600.0,
                   n_folds: int = 5, static_rate: Sequence[float] | None = None) -> "ScreenRows":
        """Rows of a campaign's runs: each run its own ``recording`` index (shifts stay within it) and
        K folds of interleaved ``span_s`` spans within every run, so every fold holds part of every run."""
        one = [cls.build([rec], fs_hz, block_s, max(2 * n_folds, int(round(np.ptp(rec.time_s) / span_s))), n_folds,
                         static_rate) for rec in recordings]
        return cls(list(recordings), float(fs_hz), float(block_s), np.concatenate([r.time_s for r in one]),
                   np.concatenate([np.full(len(r), i) for i, r in enumerate(one)]),
                   np.concatenate([r.fold for r in one]), np.concatenate([r.target for r in one]))

    @property
    def position(self) -> np.ndarray:
        """(n,) each row's place within its recording: 0 at its first block, 1 at its last."""
        out = np.zeros(len(self))
        for r in np.unique(self.recording):
            rows = self.recording == r
            t = self.time_s[rows]
            out[rows] = (t - t.min()) / max(float(np.ptp(t)), 1e-12)
        return out

    def __len__(self) -> int:
        return len(self.time_s)

    def within(self, temp_range_c: Sequence[float]) -> "ScreenRows":
        """The rows whose block temperature lies in ``temp_range_c`` (the range a model was trained on).

        Outside it the network is clamped and the compensator flags its output, so any candidate
        that extrapolates (a power of T above all) would win there for the wrong reason.
        """
        temp = self.features([{"kind": "temp"}])[:, 0]
        inside = (temp >= temp_range_c[0]) & (temp <= temp_range_c[1])
        keep = np.flatnonzero(self.keep if self.keep is not None else np.ones(len(self), bool))
        mask = np.zeros(len(keep) if self.keep is None else len(self.keep), bool)
        mask[keep[inside]] = True
        return ScreenRows(self.recordings, self.fs_hz, self.block_s, self.time_s[inside], self.recording[inside],
                          self.fold[inside], self.target[inside], mask)

    def _blocks(self, per_recording: list[np.ndarray]) -> np.ndarray:
        values = np.concatenate(per_recording)
        return values if self.keep is None else values[self.keep]

    def features(self, specs: Sequence[Mapping[str, Any]], clean_start: bool = True) -> np.ndarray:
        """Block means of causal features, shape (n, len(specs)).

        With ``clean_start``, a feature with a lag filter is corrected to start from the mean of
        the first block of its source instead of the first (noisy) sample: the filter's settling
        from one noisy sample is no effect of the channel (``candidates.filter_tau``).
        """
        out = np.empty((len(self), len(specs)))
        for start in range(0, len(specs), _CHUNK):
            chunk = specs[start:start + _CHUNK]
            out[:, start:start + len(chunk)] = self._blocks(
                [block_means(self._featurize(rec, chunk, clean_start), rec.time_s, self.block_s)
                 for rec in self.recordings])
        return out

    def _featurize(self, rec: Recording, specs: Sequence[Mapping[str, Any]], clean_start: bool) -> np.ndarray:
        values = featurize(rec, specs, self.fs_hz)
        if clean_start:
            elapsed_s = rec.time_s - rec.time_s[0]
            first = elapsed_s < self.block_s
            for j, spec in enumerate(specs):
                tau_s = filter_tau(spec)
                if tau_s:
                    source = rec.columns[spec.get("source", "temp_c")]
                    # y_clean = y - (x0 - level) exp(-t / tau): the same filter started on the level
                    values[:, j] -= (source[0] - source[first].mean()) * np.exp(-elapsed_s / tau_s)
        return values

    def basis(self, model: torch.nn.Module, specs: Sequence[Mapping[str, Any]],
              without: int | None = None) -> tuple[np.ndarray, np.ndarray] | None:
        """Block means of the regressors the model's output layer combines, evaluated at the full rate.

        An ``RBFNet`` gives its ``basis`` (Gaussians, inputs, powers of T); any other model gives
        its inputs and its own output, which a refitted linear layer can rescale. ``without``
        drops the regressors that depend on input ``without`` (a feature to re-examine); None if
        that would drop more than one (the input feeds the Gaussians).

        Returns
        -------
        basis, linear
            (n, p) block means, and (p,) which regressors are an input itself (scaled): the screen
            leaves those unpenalised, so a candidate that copies an input gains nothing.
        """
        blocks, linear = [], None
        for rec in self.recordings:
            x = torch.as_tensor(featurize(rec, specs, self.fs_hz), dtype=torch.float64)
            with torch.no_grad():
                full = self._regressors(model, x)
                if without is not None:
                    flat = x.clone()
                    flat[:, without] = x[:, without].mean()
                    moved = (self._regressors(model, flat) - full).abs().amax(0) > 0
                    if int(moved.sum()) != 1:
                        return None
                    full = full[:, ~moved]
            if linear is None:
                linear = _is_input(full.numpy(), x.numpy())
            blocks.append(block_means(full.numpy(), rec.time_s, self.block_s))
        return self._blocks(blocks), linear

    @staticmethod
    def _regressors(model: torch.nn.Module, x: torch.Tensor) -> torch.Tensor:
        return model.basis(x) if hasattr(model, "basis") else torch.cat([x, model(x)], dim=1)

    def predict(self, model: torch.nn.Module, specs: Sequence[Mapping[str, Any]]) -> np.ndarray:
        """Block means of the model's drift estimate, run causally at the full rate, (n, 3) deg/s."""
        blocks = []
        for rec in self.recordings:
            x = torch.as_tensor(featurize(rec, specs, self.fs_hz), dtype=torch.float64)
            with torch.no_grad():
                blocks.append(block_means(model(x).numpy(), rec.time_s, self.block_s))
        return self._blocks(blocks)


def _is_input(regressors: np.ndarray, inputs: np.ndarray) -> np.ndarray:
    """(p,) True where a regressor is an affine function of one input column."""
    def unit(columns: np.ndarray) -> np.ndarray:
        centred = columns - columns.mean(0)
        norm = np.linalg.norm(centred, axis=0)
        return centred / np.where(norm > 0, norm, np.inf)

    corr = np.abs(unit(regressors).T @ unit(inputs))
    return (corr > 1 - 1e-9).any(1) if corr.size else np.zeros(regressors.shape[1], bool)
