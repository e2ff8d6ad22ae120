"""Record a calibration run from an LPMS sensor, set up first: python scripts/record.py port=P output=F.csv."""
import sys
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from gyronet.deploy.stream.signals import stop_on_signals
from gyronet.deploy.stream.lpbus_setup import LpBusSetup
from gyronet.deploy.stream.record import record_stream

sys.path.insert(0, str(Path(__file__).resolve().parent))  # scripts/_cli.py, also when this file is run by path
from _cli import command  # noqa: E402


@command("record", "deploy", schemas={"lpbus": "gyronet.deploy.stream.lpbus_setup.LpBusSetup", "overwrite": bool,
                                      "baud": int, "max_samples": int | None, "duration_s": float | None,
                                      "read_timeout_s": float}, required=("port", "output"))
def main(cfg: DictConfig) -> None:
    options = OmegaConf.to_container(cfg, resolve=True)
    with stop_on_signals() as stop:  # Ctrl-C and SIGTERM end the recording with whole lines
        record_stream(options["port"], options["output"], options["baud"], LpBusSetup(**options["lpbus"]),
                      options["max_samples"], options["duration_s"], options["read_timeout_s"],
                      options["reconnect"], options["clock"], options["summary"], stop=stop,
                      overwrite=options["overwrite"])


if __name__ == "__main__":
    main()
