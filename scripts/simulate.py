"""Simulate a gyro in a chamber: python scripts/simulate.py output=F.csv [profile=cycle seed=1 ...].

Writes F.csv (the recording) and F.truth.csv (its ground truth); see conf/simulate.yaml.
"""
import hydra
from omegaconf import DictConfig, OmegaConf

from gyronet.errors import GyronetError, exit_on_error
from gyronet.sim import simulate, write_simulation


@hydra.main(version_base="1.3", config_path="../conf", config_name="simulate")
@exit_on_error
def main(cfg: DictConfig) -> None:
    if OmegaConf.is_missing(cfg, "output"):
        raise GyronetError("no output file: add output=F.csv")
    params = OmegaConf.to_container(cfg, resolve=True)
    output, fast = params.pop("output"), params.pop("fast_writer")
    write_simulation(simulate(**params), output, fast=fast)


if __name__ == "__main__":
    main()
