"""How the error bar's method constants were set: python scripts/sigma_variants.py [SENSOR ...] (default 10-15).

On calibration sensors only (never the ones scripts/sigma_table.py scores): each is simulated on the paper
staircase at 2 Hz, trained with the default model (in-process, so the held-out statistics of the fit are at
hand), and checked on a random (seed 5) and a cycle (seed 6) history against the truth. Printed: the share
of 60 s blocks within 1 sigma per sensor, history and axis for four calibration rules (floor and scale by
maximum likelihood; the floor alone, spread at face value, by maximum likelihood or as its posterior mean
under a flat prior, the default; the floor as the held-out RMS, no spread) and five
extrapolation shares (gyronet.training.error_bar_fit.EXTRAPOLATION_SHARE). Records go to outputs/sigma_variants/.
"""
import sys
from pathlib import Path

import numpy as np
from hydra.utils import instantiate
from omegaconf import OmegaConf

from gyronet.training import error_bar_fit
from gyronet.bundle.compensator import Compensator
from gyronet.recordings.data import AXES, load_recording, load_truth
from gyronet.training.dataset import DriftData
from gyronet.training.pipeline import train_run
from gyronet.training.sigma_table import block_coverage
from gyronet.sim import simulate, write_simulation

ROOT = Path("outputs/sigma_variants")
SHARES = (0.0, 0.05, 0.1, 0.2, 0.3)
HISTORIES = (("random", 5), ("cycle", 6))


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
            for share in SHARES:
                bar = error_bar_fit.shape_of(model, parts, x_fit)
                bar.slope_low_dps, bar.slope_high_dps = error_bar_fit.edge_slopes(
                    model, x_fit, error_bar_fit.box_of(model, x_fit), share)
                spread, outside = bar.spread(features), bar.outside_dps(features)
                for rule in ("floor and scale", "floor, maximum likelihood", "floor, posterior mean", "held-out RMS"):
                    floor, scale = _floor(stats, rule)
                    sigma = np.sqrt(floor ** 2 + (scale * spread) ** 2 + outside ** 2)
                    score = block_coverage(recording.time_s, error, sigma, out.out_of_range)
                    results.setdefault(f"{rule}, share {share}", []).append(
                        [score["within_1_sigma"][a] for a in AXES])
            print(f"sensor {sensor} {profile} done", flush=True)
    print("rule, share: within 1 sigma per (sensor, history) x / y / z; mean")
    for key, values in results.items():
        values = np.array(values)
        print(f"{key}: {np.round(values, 2).tolist()} mean {values.mean():.2f}")


if __name__ == "__main__":
    main([int(a) for a in sys.argv[1:]] or list(range(10, 16)))
