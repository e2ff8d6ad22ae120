"""How the error bar's method constants were set: python scripts/sigma_variants.py [SENSOR ...] (default 10-15).

On calibration sensors only (never the ones scripts/sigma_table.py scores): each is simulated on the paper
staircase at 2 Hz, trained with the default model (in-process, so the held-out statistics of the fit are at
hand), and checked on a random (seed 5) and a cycle (seed 6) history against the truth. Printed: the share
of 60 s blocks within 1 sigma per sensor, history and axis for four calibration rules (floor and scale by
maximum likelihood; the floor alone, spread at face value, by maximum likelihood or as its posterior mean
under a flat prior, the default; the floor as the held-out RMS, no spread) and five
extrapolation shares (gyronet.training.error_bar_fit.EXTRAPOLATION_SHARE); and three with a term for the
distance inside the box from the trained features (tried, not adopted: docs/guides/error-bars.md). Per rule
also the cells below the range a bar that holds allows (calibrated_range). Records go to outputs/sigma_variants/.
"""
import sys
from pathlib import Path

import numpy as np
from hydra.utils import instantiate
from omegaconf import OmegaConf
from scipy.spatial import cKDTree

from gyronet.training import error_bar_fit
from gyronet.bundle.compensator import Compensator
from gyronet.recordings.data import AXES, load_recording, load_truth
from gyronet.training.dataset import DriftData, residual_block_means
from gyronet.training.pipeline import train_run
from gyronet.training.sigma_table import GOAL, block_coverage
from gyronet.sim import simulate, write_simulation

ROOT = Path("outputs/sigma_variants")
SHARES = (0.0, 0.05, 0.1, 0.2, 0.3)
HISTORIES = (("random", 5), ("cycle", 6))
GAP_GRID = np.concatenate([[0.0], np.geomspace(1e-4, 0.1, 91)])  # the distance term's scale, deg/s per unit
DISTANCE_RULES = {"distance, (g d)^2, g by maximum likelihood": (2, False),
                  "distance, (g d)^2, floor and g by their posterior means": (2, True),
                  "distance, g^2 d, g by maximum likelihood": (1, False)}


def _floor(stats: dict, rule: str) -> tuple[np.ndarray, np.ndarray]:
    if rule == "floor and scale":
        floor, scale, _ = error_bar_fit.calibrate(stats, fit_scale=True)
    elif rule == "floor, maximum likelihood":
        floor, scale, _ = error_bar_fit.calibrate(stats, posterior=False)
    elif rule == "floor, posterior mean":  # the default
        floor, scale, _ = error_bar_fit.calibrate(stats)
    else:  # the held-out RMS less the noise, no spread
        floor = np.sqrt(np.maximum((stats["residual"] ** 2).mean(0) - stats["noise_var"], 1e-12))
        scale = np.zeros(3)
    return floor, scale


def _distance(x_train: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Each row of ``x``'s distance to the nearest row of ``x_train``, in units of the training features' std."""
    mean, std = x_train.mean(0), np.maximum(x_train.std(0), 1e-12)
    return cKDTree((x_train - mean) / std).query((x - mean) / std)[0]


def _with_distance(stats: dict, distance: np.ndarray, power: int, posterior: bool) -> tuple[np.ndarray, np.ndarray]:
    """Floor and distance scale g per axis; a held-out block's variance: floor^2 + spread^2 + g^2 d^power + the rest."""
    floor, gap = np.zeros(3), np.zeros(3)
    for a in range(3):
        r2 = stats["residual"][:, a] ** 2
        grid = error_bar_fit._FLOOR_GRID * np.sqrt(r2.mean())
        fixed = stats["outside"][:, a] ** 2 + stats["spread"][:, a] ** 2 + stats["noise_var"][a]
        var = grid[:, None, None] ** 2 + GAP_GRID[None, :, None] ** 2 * distance[None, None] ** power + fixed
        nll = np.sum(np.log(var) + r2 / var, axis=2)
        i, j = np.unravel_index(int(np.argmin(nll)), nll.shape)
        weight = np.exp(-0.5 * (nll - nll[i, j])) * np.gradient(grid)[:, None]  # flat priors
        if posterior:
            weight = weight * np.gradient(GAP_GRID)[None]
        else:
            weight = np.where(np.arange(len(GAP_GRID)) == j, weight, 0.0)  # g at its maximum
        floor[a] = np.sqrt(np.sum(weight * grid[:, None] ** 2) / np.sum(weight))
        gap[a] = np.sqrt(np.sum(weight * GAP_GRID[None] ** 2) / np.sum(weight))
    return floor, gap


def main(sensors: list[int]) -> None:
    ROOT.mkdir(parents=True, exist_ok=True)
    model_cfg = OmegaConf.load(Path(__file__).resolve().parent.parent / "conf" / "model" / "default.yaml")
    results: dict[str, list] = {}
    for sensor in sensors:
        train_path = ROOT / f"paper{sensor}.csv"
        write_simulation(simulate("paper", fs_hz=2.0, seed=1, sensor_seed=sensor), train_path)
        data = DriftData(str(train_path))
        model = instantiate(model_cfg, n_inputs=data.n_features)
        train_run(data, model, None, ROOT / f"run{sensor}", {"progress": False, "for_bundle": True})
        stats, parts = model.__dict__[error_bar_fit.STATS_ATTR], model.__dict__[error_bar_fit.MEMBERS_ATTR]
        x_fit = np.concatenate([data.train.x, data.val.x])
        held_time_s, held_x, _ = data.val_full
        held_distance = residual_block_means(held_time_s, _distance(data.train.x, held_x)[:, None])[:, 0]
        compensator = Compensator.load(ROOT / f"run{sensor}" / "compensator")
        for profile, seed in HISTORIES:
            path = ROOT / f"{profile}{sensor}.csv"
            write_simulation(simulate(profile, fs_hz=2.0, seed=seed, sensor_seed=sensor), path)
            recording, truth = load_recording(path), load_truth(path).columns
            compensator.reset()
            out = compensator.process(recording.columns)
            compensator.reset()
            features = compensator.extractor.process(recording.columns)
            error = out.drift_dps - np.column_stack([truth[f"drift_{a}_dps"] for a in AXES])
            distance = _distance(x_fit, features)
            print(f"sensor {sensor} {profile}: distance from the trained features, 90th percentile "
                  f"{np.quantile(distance, 0.9):.2f} (held-out blocks: at most {held_distance.max():.2f})")

            def score(sigma: np.ndarray) -> list:
                got = block_coverage(recording.time_s, error, sigma, out.out_of_range, ranges=True)
                return [[got["within_1_sigma"][a], *got["calibrated_range"][a]] for a in AXES]

            for share in SHARES:
                bar = error_bar_fit.shape_of(model, parts, x_fit)
                bar.slope_low_dps, bar.slope_high_dps = error_bar_fit.edge_slopes(
                    model, x_fit, error_bar_fit.box_of(model, x_fit), share)
                spread, outside = bar.spread(features), bar.outside_dps(features)
                for rule in ("floor and scale", "floor, maximum likelihood", "floor, posterior mean", "held-out RMS"):
                    floor, scale = _floor(stats, rule)
                    sigma = np.sqrt(floor ** 2 + (scale * spread) ** 2 + outside ** 2)
                    results.setdefault(f"{rule}, share {share}", []).append(score(sigma))
                if share == 0.0:
                    for rule, (power, posterior) in DISTANCE_RULES.items():
                        floor, gap = _with_distance(stats, held_distance, power, posterior)
                        gap_var = gap ** 2 * distance[:, None] ** power
                        sigma = np.sqrt(floor ** 2 + spread ** 2 + outside ** 2 + gap_var)
                        results.setdefault(f"{rule}, share 0.0", []).append(score(sigma))
            print(f"sensor {sensor} {profile} done", flush=True)
    print("rule, share: within 1 sigma per (sensor, history) x / y / z; mean; cells in 60-76 %; mean distance from 68 %; "
          "cells below the range")
    for key, values in results.items():
        within, low = np.array(values)[..., 0], np.array(values)[..., 1]
        print(f"{key}: {np.round(within, 2).tolist()} mean {within.mean():.3f}; in {100 * GOAL[0]:.0f}-{100 * GOAL[1]:.0f} %: "
              f"{np.sum((within >= GOAL[0]) & (within <= GOAL[1]))} of {within.size}; distance from 68 %: "
              f"{100 * np.mean(np.abs(within - 0.6827)):.1f} points; below: {np.sum(within < low)}")


if __name__ == "__main__":
    main([int(a) for a in sys.argv[1:]] or list(range(10, 16)))
