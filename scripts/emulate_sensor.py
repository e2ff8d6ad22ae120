"""Play a recording into a pseudo-terminal as a sensor would: python scripts/emulate_sensor.py input=F.csv protocol=lpbus."""
import sys
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from gyronet.stream import FaultPlan, LpBusLayout
from gyronet.stream.pty_sensor import emulate_file

sys.path.insert(0, str(Path(__file__).resolve().parent))  # scripts/_cli.py, also when this file is run by path
from _cli import command  # noqa: E402


@command("emulate", schemas={"lpbus": "gyronet.stream.LpBusLayout", "faults": "gyronet.stream.FaultPlan"},
         required=("input",))
def main(cfg: DictConfig) -> None:
    options = OmegaConf.to_container(cfg, resolve=True)
    emulate_file(options["input"], options["protocol"], float(options["speed"]),
                 FaultPlan(**options["faults"]), LpBusLayout(**options["lpbus"]), options["csv_columns"],
                 options["link"], options["port_file"], options["log_file"], float(options["port_down_s"]),
                 float(options["reader_timeout_s"]))


if __name__ == "__main__":
    main()
