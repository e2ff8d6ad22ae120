"""The real-data table, each run held out in turn: python scripts/campaign_table.py 'runs=[A.csv,B.csv]' output=T.md."""
import json
import logging
import sys
from pathlib import Path

from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from gyronet.atomic import atomic_output
from gyronet.campaign import held_out_table, to_markdown

sys.path.insert(0, str(Path(__file__).resolve().parent))  # scripts/_cli.py, also when this file is run by path
from _cli import command  # noqa: E402

log = logging.getLogger(__name__)
MODEL_CONF = Path(__file__).resolve().parents[1] / "conf" / "model"


@command("campaign", schemas={"train": "gyronet.train.fit", "seed": int}, required=("runs",))
def main(cfg: DictConfig) -> None:
    models = {}
    for name in cfg.models:
        variant = dict(cfg.variants.get(name) or {"model": name})
        spec = None if name == "raw" else OmegaConf.merge(OmegaConf.load(MODEL_CONF / f"{variant.pop('model')}.yaml"),
                                                         variant)
        models[name] = None if spec is None else (lambda n_inputs, spec=spec: instantiate(spec, n_inputs=n_inputs))
    table = held_out_table(list(cfg.runs), models, float(cfg.startup_s), float(cfg.score_from_s), bool(cfg.run_offsets),
                           OmegaConf.to_container(cfg.train), int(cfg.seed))
    markdown = to_markdown(table)
    output = Path(cfg.output)
    output.parent.mkdir(parents=True, exist_ok=True)
    with atomic_output(output) as tmp:
        tmp.write_text(markdown)
    with atomic_output(output.with_suffix(".json")) as tmp:
        tmp.write_text(json.dumps(table, indent=2) + "\n")
    log.info("held-out runs:\n%s", markdown)


if __name__ == "__main__":
    main()
