"""The real-data table, each run held out in turn: python scripts/campaign_table.py 'runs=[A.csv,B.csv]' output=T.md."""
import json
import logging
from pathlib import Path

import hydra
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from gyronet.campaign import held_out_table, to_markdown
from gyronet.errors import exit_on_error

log = logging.getLogger(__name__)
MODEL_CONF = Path(__file__).resolve().parents[1] / "conf" / "model"


@hydra.main(version_base="1.3", config_path="../conf", config_name="campaign")
@exit_on_error
def main(cfg: DictConfig) -> None:
    models = {}
    for name in cfg.models:
        spec = None if name == "raw" else OmegaConf.load(MODEL_CONF / f"{name}.yaml")
        models[name] = None if spec is None else (lambda n_inputs, spec=spec: instantiate(spec, n_inputs=n_inputs))
    table = held_out_table(list(cfg.runs), models, float(cfg.startup_s), float(cfg.score_from_s), bool(cfg.run_offsets),
                           OmegaConf.to_container(cfg.train), int(cfg.seed))
    markdown = to_markdown(table)
    output = Path(cfg.output)
    output.parent.mkdir(parents=True, exist_ok=True)
    output.write_text(markdown)
    output.with_suffix(".json").write_text(json.dumps(table, indent=2) + "\n")
    log.info("held-out runs:\n%s", markdown)


if __name__ == "__main__":
    main()
