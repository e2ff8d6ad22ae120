"""Simulate a gyro in a chamber: python scripts/simulate.py output=F.csv [profile=cycle seed=1 ...].

Writes F.csv (the recording) and F.truth.csv (its ground truth); see conf/simulate.yaml.
"""
import sys
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from gyronet.errors import GyronetError
from gyronet.sim import simulate, write_simulation

sys.path.insert(0, str(Path(__file__).resolve().parent))  # scripts/_cli.py, also when this file is run by path
from _cli import command  # noqa: E402


@command("simulate", schemas={"fs_hz": float, "seed": int, "sensor_seed": int, "duration_s": float | None})
def main(cfg: DictConfig) -> None:
    if OmegaConf.is_missing(cfg, "output"):
        raise GyronetError("no output file: add output=F.csv")
    params = OmegaConf.to_container(cfg, resolve=True)
    output, fast = params.pop("output"), params.pop("fast_writer")
    write_simulation(simulate(**params), output, fast=fast)


if __name__ == "__main__":
    main()
