"""Play a recording into a pseudo-terminal as a sensor would: python scripts/emulate_sensor.py input=F.csv protocol=lpbus."""
import hydra
from omegaconf import DictConfig, OmegaConf

from gyronet.errors import exit_on_error
from gyronet.stream import FaultPlan, LpBusLayout
from gyronet.stream.pty_sensor import emulate_file


@hydra.main(version_base="1.3", config_path="../conf", config_name="emulate")
@exit_on_error
def main(cfg: DictConfig) -> None:
    options = OmegaConf.to_container(cfg, resolve=True)
    emulate_file(options["input"], options["protocol"], float(options["speed"]),
                 FaultPlan(**options["faults"]), LpBusLayout(**options["lpbus"]), options["csv_columns"],
                 options["link"], options["port_file"], options["log_file"], float(options["port_down_s"]),
                 float(options["reader_timeout_s"]))


if __name__ == "__main__":
    main()
