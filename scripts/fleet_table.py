"""The fleet table of a fleet sweep folder: python scripts/fleet_table.py sweep=S ['spec_range_c=[-40,85]'] [output=T.md].

scripts/fleet.py writes it when its sweep ends; this writes it again (a unit re-run, another spec range).
"""
import logging
import sys
from pathlib import Path

from omegaconf import DictConfig, ListConfig, OmegaConf

from gyronet.training.fleet import check_spec_range, fleet_table, to_markdown, write_table

sys.path.insert(0, str(Path(__file__).resolve().parent))  # scripts/_cli.py, also when this file is run by path
from _cli import command  # noqa: E402

log = logging.getLogger(__name__)


@command("fleet_table", schemas={"sweep": str}, required=("sweep",))
def main(cfg: DictConfig) -> None:
    spec = cfg.spec_range_c
    table = fleet_table(cfg.sweep, check_spec_range(OmegaConf.to_container(spec) if isinstance(spec, ListConfig) else spec))
    output = write_table(table, cfg.output)
    log.info("fleet table %s (and .json):\n%s", output, to_markdown(table))


if __name__ == "__main__":
    main()
