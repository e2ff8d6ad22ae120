"""The paper's Table 1 on a held-out recording: python scripts/table.py input=F.csv '+bundles={name: D/compensator}'."""
import json
import logging
import sys
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from gyronet.table import PAPER_TABLE_1, table_rows, to_markdown

sys.path.insert(0, str(Path(__file__).resolve().parent))  # scripts/_cli.py, also when this file is run by path
from _cli import command  # noqa: E402

log = logging.getLogger(__name__)


@command("table", "deploy")
def main(cfg: DictConfig) -> None:
    rows = table_rows(cfg.input, OmegaConf.to_container(cfg.bundles))
    markdown = to_markdown(rows)
    output = Path(cfg.output)
    output.parent.mkdir(parents=True, exist_ok=True)
    output.write_text(markdown)
    output.with_suffix(".json").write_text(json.dumps({"input": cfg.input, "rows": rows, "paper": PAPER_TABLE_1}, indent=2))
    log.info("Table 1 on %s:\n%s", cfg.input, markdown)


if __name__ == "__main__":
    main()
