"""Allan analysis of a recording or a ROS bag: python scripts/allan.py input=F.csv|B.bag|BAG_FOLDER output=A.json.

Writes A.json (CONTRACT.md section 3: per axis ``taus_s``, ``adev_dps``, N, B, K, from ``still_s`` on; for a
compensated file with ``drift_sigma_*_dps`` columns also the error bar's median, 95 % and maximum, and whether
to recalibrate: ``gyronet.model.recalibration``, on a still record from ``still_s`` on, against its
``# static_rate_dps``) and A.png. A bag
is read in memory (its sensor_msgs/Imu topic, ``rosbag.imu_topic``); it needs no temperature.
"""
import logging
import sys
from pathlib import Path

import numpy as np
from omegaconf import DictConfig, OmegaConf

from gyronet.atomic import write_json
from gyronet.allan import allan_report, format_table, plot_allan
from gyronet.model import recalibration
from gyronet.recordings.data import ALLAN_COLUMNS, load_recording
from gyronet.errors import GyronetError
from gyronet.recordings.importers.rosbag import is_rosbag, read_rates
from gyronet.recordings.rate_watch import first_rate_change
from gyronet.bundle.offline import SIGMA_COLUMNS, STILL_S_KEY
from gyronet.training.dataset import static_rate_dps
from gyronet.training.sigma_table import allan_sigma_summary

sys.path.insert(0, str(Path(__file__).resolve().parent))  # scripts/_cli.py, also when this file is run by path
from _cli import command  # noqa: E402

log = logging.getLogger(__name__)


def _still_s(given, meta) -> float:
    """``still_s`` as given, else the compensated file's own start-up window (``# startup_still_s=``), else 0."""
    if given is not None:
        return float(given)
    text = meta.get(STILL_S_KEY)
    try:
        still_s = float(text) if text is not None else 0.0
    except ValueError:
        raise GyronetError(f"# {STILL_S_KEY}={text} is not a number of seconds: pass still_s=S") from None
    if still_s:
        log.info("still_s=%g from the file's # %s (the start-up window it was compensated with)", still_s, STILL_S_KEY)
    return still_s


def _refuse_rate_change(recording, source) -> None:
    """An Allan curve needs one rate: a record whose rate changes (10 Hz, then 50) read N 22 % high, silently."""
    if len(recording) < 3:
        return
    fs_hz = 1.0 / float(np.median(np.diff(recording.time_s[:201])))  # the rate it starts at
    change = first_rate_change(recording.time_s, fs_hz)
    if change is not None:
        raise GyronetError(f"{source}: near time_s={change.since_time_s:.6g} the sampling rate changes from "
                           f"{change.old_hz:.4g} Hz to {change.new_hz:.4g} Hz; an Allan curve needs one rate: split "
                           "the file there and analyse each part")


@command("allan", schemas={"per_decade": int, "still_s": float | None, "input": str, "output": str})
def main(cfg: DictConfig) -> None:
    if OmegaConf.is_missing(cfg, "input"):
        raise GyronetError("no recording given: add input=F.csv")
    if Path(str(cfg.output)).suffix.lower() == ".png":  # the JSON was written there, then replaced by its own plot
        raise GyronetError(f"output={cfg.output}: output names the JSON report, and its plot goes beside it with the "
                           "suffix .png, which would replace it: name the report A.json (the plot is then A.png)")
    if is_rosbag(cfg.input):
        recording = read_rates(cfg.input, cfg.rosbag.imu_topic, cfg.rosbag.stamp)
    else:
        recording = load_recording(cfg.input, required=ALLAN_COLUMNS)
    _refuse_rate_change(recording, cfg.input)
    still_s = _still_s(cfg.still_s, recording.meta)
    analysed = recording
    if still_s:  # the start-up window's rows carry no offset yet: a step the Allan curve would read as drift
        analysed = recording.slice(recording.time_s >= recording.time_s[0] + still_s)
        if len(analysed) < 3:
            raise GyronetError(f"{cfg.input}: nothing after still_s={still_s:g} s to analyse")
        log.info("Allan deviation from %g s on (still_s: the start-up window is left out)", still_s)
    report = allan_report(analysed.time_s, analysed.gyro_dps, per_decade=int(cfg.per_decade))
    if all(c in recording.columns for c in SIGMA_COLUMNS):  # a compensated file: its error bar beside N, B, K
        sigma = np.column_stack([recording.columns[c] for c in SIGMA_COLUMNS])
        for axis, values in allan_sigma_summary(sigma).items():
            report[axis].update(values)
            log.info("%s: drift sigma median %.4g deg/s (95 %% %.4g, max %.4g)", axis, values["drift_sigma_median_dps"],
                     values["drift_sigma_p95_dps"], values["drift_sigma_max_dps"])
        outside = recording.columns.get("out_of_range")
        true_dps = static_rate_dps(recording)  # a still test's true rate (the Earth's) stays in the output
        verdicts = recalibration.check(recording.time_s, recording.gyro_dps - true_dps, sigma,
                                       None if outside is None else np.asarray(outside) > 0, still_s)
        if not verdicts:
            log.info("no recalibration check: fewer than two 60 s blocks with a drift_sigma after still_s=%g s",
                     still_s)
        for axis, verdict in verdicts.items():  # a still record: does the bar still describe the sensor?
            report[axis]["recalibration"] = verdict
            (log.warning if verdict["recalibrate"] else log.info)(recalibration.summary_line(axis, verdict))
    output = Path(cfg.output)
    output.parent.mkdir(parents=True, exist_ok=True)
    write_json(output, report, indent=1)
    plot_allan(report, path=output.with_suffix(".png"), title=f"Allan deviation: {Path(cfg.input).name}")
    for line in format_table(report).splitlines():
        log.info(line)
    log.info("wrote %s and %s", output, output.with_suffix(".png"))


if __name__ == "__main__":
    main()
