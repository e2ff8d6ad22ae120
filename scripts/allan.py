"""Allan analysis of a recording or a ROS bag: python scripts/allan.py input=F.csv|B.bag|BAG_FOLDER output=A.json.

Writes A.json (CONTRACT.md section 3: per axis ``taus_s``, ``adev_dps``, N, B, K) and A.png. A bag
is read in memory (its sensor_msgs/Imu topic, ``rosbag.imu_topic``); it needs no temperature.
"""
import logging
import sys
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from gyronet.allan import allan_report, format_table, plot_allan, report_to_json
from gyronet.data import ALLAN_COLUMNS, load_recording
from gyronet.errors import GyronetError
from gyronet.importers.rosbag import is_rosbag, read_rates

sys.path.insert(0, str(Path(__file__).resolve().parent))  # scripts/_cli.py, also when this file is run by path
from _cli import command  # noqa: E402

log = logging.getLogger(__name__)


@command("allan", schemas={"per_decade": int})
def main(cfg: DictConfig) -> None:
    if OmegaConf.is_missing(cfg, "input"):
        raise GyronetError("no recording given: add input=F.csv")
    if is_rosbag(cfg.input):
        recording = read_rates(cfg.input, cfg.rosbag.imu_topic, cfg.rosbag.stamp)
    else:
        recording = load_recording(cfg.input, required=ALLAN_COLUMNS)
    report = allan_report(recording.time_s, recording.gyro_dps, per_decade=int(cfg.per_decade))
    output = Path(cfg.output)
    output.parent.mkdir(parents=True, exist_ok=True)
    output.write_text(report_to_json(report), encoding="utf-8")
    plot_allan(report, path=output.with_suffix(".png"), title=f"Allan deviation: {Path(cfg.input).name}")
    for line in format_table(report).splitlines():
        log.info(line)
    log.info("wrote %s and %s", output, output.with_suffix(".png"))


if __name__ == "__main__":
    main()
