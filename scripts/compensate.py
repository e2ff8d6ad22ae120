"""Apply a compensator bundle to a recording: python scripts/compensate.py model=D/compensator input=F.csv output=O.csv."""
import hydra
from omegaconf import DictConfig, OmegaConf

from gyronet.errors import exit_on_error
from gyronet.offline import compensate_file


@hydra.main(version_base="1.3", config_path="../conf/deploy", config_name="compensate")
@exit_on_error
def main(cfg: DictConfig) -> None:
    compensate_file(cfg.model, cfg.input, cfg.output, resample=bool(cfg.get("resample", False)),
                    startup=OmegaConf.to_container(cfg.startup, resolve=True))


if __name__ == "__main__":
    main()
