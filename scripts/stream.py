"""Compensate a live sensor stream: python scripts/stream.py model=D/compensator port=P baud=B protocol=lpbus output=O.csv."""
import sys
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from gyronet.deploy.stream.live import run_stream, stop_on_signals
from gyronet.deploy.stream.lpbus_setup import LpBusSetup

sys.path.insert(0, str(Path(__file__).resolve().parent))  # scripts/_cli.py, also when this file is run by path
from _cli import command  # noqa: E402


@command("stream", "deploy", schemas={"lpbus": "gyronet.deploy.stream.lpbus_setup.LpBusSetup", "baud": int,
                                      "max_samples": int | None, "duration_s": float | None, "read_timeout_s": float,
                                      "allan_every_s": float, "resample": bool}, required=("model", "port", "output"))
def main(cfg: DictConfig) -> None:
    options = OmegaConf.to_container(cfg, resolve=True)
    with stop_on_signals() as stop:  # SIGINT and SIGTERM alike, whatever the parent left them as
        run_stream(options["model"], options["port"], options["output"], options["protocol"], options["baud"],
                   None, options["max_samples"], options["duration_s"],
                   float(options["allan_every_s"]), options["tb_dir"], options["summary"],
                   options["read_timeout_s"], options["reconnect"], options["clock"], stop=stop,
                   startup=options.get("startup"), resample=bool(options.get("resample", False)),
                   lpbus=LpBusSetup(**options["lpbus"]), realtime_priority=options.get("realtime_priority"))


if __name__ == "__main__":
    main()
