"""The paper's Table 1 on held-out recordings: python scripts/table.py input=F.csv '+bundles={name: D/compensator}'."""
import logging
import sys
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from gyronet.analysis.table import PAPER_TABLE_1, held_out_paths, runs_to_markdown, table_rows, table_runs, to_markdown
from gyronet.atomic import write_json, write_text
from gyronet.errors import ConfigError

sys.path.insert(0, str(Path(__file__).resolve().parent))  # scripts/_cli.py, also when this file is run by path
from _cli import command  # noqa: E402

log = logging.getLogger(__name__)


# a number that is text, or a path list given as one path, were a traceback or a misleading line (data.paths=F.csv
# was read letter by letter)
@command("table", "deploy", schemas={"px4.firmware_schedule": bool, "score_from_s": float, "startup": dict,
                                     "startup.still_s": float | None, "startup.motion_dps": float,
                                     "startup.static_rate_dps": list | None, "input": str | None,
                                     "data.path": str | None, "data.paths": list | None, "bundles": dict})
def main(cfg: DictConfig) -> None:
    paths = held_out_paths(cfg.get("input"), cfg.data.get("path"), cfg.data.get("paths"))
    bundles = OmegaConf.to_container(cfg.bundles)
    for name, folder in bundles.items():
        if not isinstance(folder, str):
            raise ConfigError(f"bundles.{name} must be a bundle folder, got {folder!r}")
    options = {"startup": OmegaConf.to_container(cfg.startup, resolve=True), "score_from_s": float(cfg.score_from_s),
               "px4_firmware_schedule": bool(cfg.px4.firmware_schedule)}
    if len(paths) == 1:
        rows = table_rows(paths[0], bundles, **options)
        markdown, figures = to_markdown(rows), {"input": paths[0], "rows": rows}
    else:
        per_run = table_runs(paths, bundles, **options)
        markdown, figures = runs_to_markdown(per_run), {"inputs": paths, "runs": per_run}
    output = Path(cfg.output)
    output.parent.mkdir(parents=True, exist_ok=True)
    write_text(output, markdown)
    write_json(output.with_suffix(".json"), {**figures, **options, "paper": PAPER_TABLE_1})
    log.info("Table 1 on %s:\n%s", ", ".join(paths), markdown)


if __name__ == "__main__":
    main()
