"""Convert another tool's recording to a CONTRACT.md CSV: python scripts/convert.py input=IN output=F.csv [format=psim|lpms|ulog|rosbag|csv].

``format=csv`` (or auto) also reads a spreadsheet's export of the contract's columns: ``;`` or tab
between cells, decimal commas, UTF-16, trailing commas; the output is the plain comma CSV.
A ROS bag (``.bag``, ``.db3``, ``.mcap`` or a ROS 2 bag folder) is read with ``rosbag.*`` options.
``bad_lines=drop`` recovers a contract CSV that has malformed lines: they are left out, counted.
"""
import sys
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from gyronet.recordings.importers import FORMATS, convert_with_options

sys.path.insert(0, str(Path(__file__).resolve().parent))  # scripts/_cli.py, also when this file is run by path
from _cli import command  # noqa: E402


@command("convert")
def main(cfg: DictConfig) -> None:
    options = {name: OmegaConf.to_container(cfg[name], resolve=True) for name in FORMATS if name in cfg}
    convert_with_options(cfg.input, cfg.output, cfg.format, cfg.sensor, options, cfg.bad_lines)


if __name__ == "__main__":
    main()
