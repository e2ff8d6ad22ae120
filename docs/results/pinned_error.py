"""What the start-up offset pins on the survey's sensors: the model's error over the power-up window.

python docs/results/pinned_error.py RUN_DIR   # a survey run with keep_records=true (run by hand, not by the build)

Per sensor and axis, from each sensor's records and gyronet bundle, against the simulator's truth:

- pinned: the model's mean error over the check history's first 600 s, less its mean error after
  them (what the offset carries into every later sample beyond the noise);
- in-sample: the same over the training record's own first 600 s (in sample: it was trained on);
- noise: the training record's mean noise over those 600 s.

Then the correlations and the RMS of each, in mdps.
"""
import sys
from pathlib import Path

import numpy as np

from gyronet.bundle.compensator import Compensator
from gyronet.bundle.offline import compensate_as_deployed
from gyronet.recordings.data import AXES, load_recording, load_truth

WINDOW_S = 600.0


def window_figures(compensator: Compensator, csv: Path) -> tuple[np.ndarray, np.ndarray]:
    """The model's mean error (3,) over the record's first WINDOW_S less after them, and the window's mean noise (3,), deg/s."""
    recording, truth = load_recording(csv), load_truth(csv).columns
    plain = compensate_as_deployed(compensator, recording).rate_dps  # no start-up offset
    true = np.stack([truth[f"true_rate_{a}_dps"] for a in AXES], 1)
    noise = np.stack([truth[f"noise_{a}_dps"] for a in AXES], 1)
    error = plain - true - noise  # the drift the model missed (its turn-on bias cancels below)
    window = recording.time_s < recording.time_s[0] + WINDOW_S
    return error[window].mean(0) - error[~window].mean(0), noise[window].mean(0)


def rms(values: np.ndarray) -> float:
    """Root mean square: the scale of a signed error over the sensor-axes."""
    return float(np.sqrt(np.mean(values ** 2)))


def main(run_dir: str) -> None:
    rows = []  # pinned, in-sample, noise (mdps) per sensor-axis
    for folder in sorted(Path(run_dir, "sensors").glob("sensor_*")):
        if not (folder / "train.csv").is_file() or not (folder / "result.json").is_file():
            continue
        compensator = Compensator.load(folder / "gyronet" / "compensator")
        compensator.use_startup(0.0)
        in_sample, noise = window_figures(compensator, folder / "train.csv")
        pinned, _ = window_figures(compensator, folder / "check.csv")
        rows += [[p, i, n] for p, i, n in zip(1e3 * pinned, 1e3 * in_sample, 1e3 * noise)]
    if len(rows) < 3:
        sys.exit(f"{run_dir}: fewer than 3 sensor-axes with records (run the survey with keep_records=true)")
    pinned, in_sample, noise = np.array(rows).T
    print(f"{len(rows)} sensor-axes; RMS pinned {rms(pinned):.2f}, in-sample {rms(in_sample):.2f}, "
          f"training window noise {rms(noise):.2f} mdps")
    print(f"pinned vs in-sample: r = {np.corrcoef(pinned, in_sample)[0, 1]:.2f}")
    print(f"pinned vs training window noise: r = {np.corrcoef(pinned, noise)[0, 1]:.2f}, "
          f"slope {np.polyfit(noise, pinned, 1)[0]:.2f}")


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit(__doc__.splitlines()[2])
    main(sys.argv[1])
