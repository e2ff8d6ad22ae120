"""Play a recording into a pseudo-terminal as a sensor would: python scripts/emulate_sensor.py input=F.csv protocol=lpbus."""
import signal
import sys
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from gyronet.deploy.stream import FaultPlan, LpBusLayout
from gyronet.errors import ConfigError
from gyronet.deploy.stream.lpbus_device import EmulatedLpms
from gyronet.deploy.stream.pty_sensor import emulate_file

sys.path.insert(0, str(Path(__file__).resolve().parent))  # scripts/_cli.py, also when this file is run by path
from _cli import command  # noqa: E402


def built(key: str, make):
    """``make()``, with the ValueError a bad setting raises as one line naming its key."""
    try:
        return make()
    except ValueError as err:
        raise ConfigError(f"{key}: {err}") from None


@command("emulate", schemas={"lpbus": "gyronet.deploy.stream.LpBusLayout", "faults": "gyronet.deploy.stream.FaultPlan",
                             "sensor": "gyronet.deploy.stream.lpbus_device.EmulatedLpms", "speed": float,
                             "port_down_s": float, "reader_timeout_s": float, "command_wait_s": float},
         required=("input",))
def main(cfg: DictConfig) -> None:
    signal.signal(signal.SIGTERM, signal.default_int_handler)  # stopped as by Ctrl-C: the port's link is removed
    options = OmegaConf.to_container(cfg, resolve=True)
    if not options["speed"] >= 0:  # a negative speed played as fast as possible, silently
        raise ConfigError(f"speed must be 0 (as fast as the reader takes it) or more, got {options['speed']}")
    if options["protocol"] not in ("lpbus", "csv"):  # was refused after the recording loaded, under its file name
        raise ConfigError(f"protocol must be lpbus or csv, got {options['protocol']!r}")
    sensor = options.get("sensor") or {}
    device = built("sensor", lambda: EmulatedLpms(**{**sensor, "firmware": tuple(sensor["firmware"]),
                                                     "fields": tuple(sensor["fields"])})) if sensor.get("model") else None
    emulate_file(options["input"], options["protocol"], float(options["speed"]),
                 built("faults", lambda: FaultPlan(**options["faults"])), built("lpbus", lambda: LpBusLayout(**options["lpbus"])),
                 options["csv_columns"],
                 options["link"], options["port_file"], options["log_file"], float(options["port_down_s"]),
                 float(options["reader_timeout_s"]), device, float(options.get("command_wait_s", 2.0)))


if __name__ == "__main__":
    main()
