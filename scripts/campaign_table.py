"""The real-data table, each run held out in turn: python scripts/campaign_table.py 'data.paths=[A.csv,B.csv]' output=T.md.

``runs=[...]`` is the older spelling of ``data.paths``."""
import logging
import sys
from pathlib import Path

from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from gyronet.atomic import write_json, write_text
from gyronet.errors import GyronetError
from gyronet.analysis.campaign import held_out_table, to_markdown

sys.path.insert(0, str(Path(__file__).resolve().parent))  # scripts/_cli.py, also when this file is run by path
from _cli import command  # noqa: E402

log = logging.getLogger(__name__)
MODEL_CONF = Path(__file__).resolve().parents[1] / "conf" / "model"
DATA_CONF = MODEL_CONF.parent / "data" / "default.yaml"


@command("campaign", schemas={"train": "gyronet.training.train.fit", "seed": int})
def main(cfg: DictConfig) -> None:
    if cfg.data.paths is not None and cfg.runs is not None:
        raise GyronetError("give the runs once: data.paths=[...] (runs=[...] is its older spelling)")
    runs = cfg.data.paths if cfg.data.paths is not None else cfg.runs
    if runs is None:
        raise GyronetError("no runs given: add 'data.paths=[A.csv,B.csv]' (two or more runs of one unit)")
    models, data_options = {}, {}
    for name in cfg.models:
        if name == "raw":
            models[name] = None
            continue
        spec, data_options[name] = _variant(name, cfg.get("variants") or {})  # '~variants' leaves none
        models[name] = lambda n_inputs, spec=spec, **more: instantiate(spec, n_inputs=n_inputs, **more)
    table = held_out_table(list(runs), models, float(cfg.startup_s), float(cfg.score_from_s), bool(cfg.run_offsets),
                           OmegaConf.to_container(cfg.train), int(cfg.seed), data_options)
    markdown = to_markdown(table)
    output = Path(cfg.output)
    output.parent.mkdir(parents=True, exist_ok=True)
    write_text(output, markdown)
    write_json(output.with_suffix(".json"), table)
    log.info("held-out runs:\n%s", markdown)


def _variant(name: str, variants: DictConfig | dict) -> tuple[DictConfig, dict]:
    """A model name's spec and data settings: ``conf/model/<name>.yaml``, or a variant's yaml, overrides and ``data``."""
    variant = dict(variants.get(name) or {"model": name})
    data = OmegaConf.to_container(variant.pop("data", None) or OmegaConf.create({}))
    spec, options = _model_yaml(variant.pop("model"))
    return OmegaConf.merge(spec, variant), {**options, **data}


def _model_yaml(name: str) -> tuple[DictConfig, dict]:
    """``conf/model/<name>.yaml``: the model's spec, and the data settings a ``_global_`` one (px4) makes
    (dT/dt's time constant and the start-up window from ``conf/data/default.yaml``, as ``train.py`` takes them)."""
    path = MODEL_CONF / f"{name}.yaml"
    if not path.is_file():
        known = ", ".join(sorted(p.stem for p in MODEL_CONF.glob("*.yaml")))
        raise GyronetError(f"models: no conf/model/{name}.yaml (known: {known}, raw)")
    conf = OmegaConf.load(path)
    defaults = OmegaConf.load(DATA_CONF)
    taken = {"rate_tau_s": float(defaults.rate_tau_s), "val_startup_s": float(defaults.val_startup_s)}
    if "model" not in conf:  # a bare model spec, trained on conf/data's defaults
        return conf, taken
    data = conf.get("data") or {}
    options = {k: OmegaConf.to_container(data[k]) if k == "features" else data[k]
               for k in ("features", "block_s", "run_offsets") if k in data}
    options["in_sample"] = "val_path" in data  # validated on its own recording (PX4 holds nothing out)
    return conf.model, {**taken, **options}


if __name__ == "__main__":
    main()
