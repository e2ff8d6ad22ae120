"""Apply a compensator bundle to a recording: python scripts/compensate.py model=D/compensator input=F.csv output=O.csv."""
import sys
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from gyronet.bundle.offline import compensate_file

sys.path.insert(0, str(Path(__file__).resolve().parent))  # scripts/_cli.py, also when this file is run by path
from _cli import command  # noqa: E402


# a path that is null or a list, startup=5 or resample=maybe (read as true) were a traceback or taken silently
@command("compensate", "deploy", schemas={"model": str, "input": str, "output": str, "resample": bool, "startup": dict})
def main(cfg: DictConfig) -> None:
    compensate_file(cfg.model, cfg.input, cfg.output, resample=bool(cfg.get("resample", False)),
                    startup=OmegaConf.to_container(cfg.startup, resolve=True))


if __name__ == "__main__":
    main()
