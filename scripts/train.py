"""Train a drift compensator: python scripts/train.py data.path=F.csv [model=rbf|poly3|lsq] [-m hydra/sweeper=ga]."""
import json
import logging
import math
import sys
from pathlib import Path

from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from gyronet.errors import ConfigError
from gyronet.training.axis_lag import with_axis_lags
from gyronet.training.pipeline import train_run
from gyronet.figures.tb import make_writer

sys.path.insert(0, str(Path(__file__).resolve().parent))  # scripts/_cli.py, also when this file is run by path
from _cli import command  # noqa: E402

log = logging.getLogger(__name__)


# a bad input is one line and exit 2; in a sweep it raises, and the sweeper scores the job inf
@command("train", schemas={"train": "gyronet.training.train.fit", "seed": int, "eval.paths": list, "eval.block_s": float})
def main(cfg: DictConfig) -> float:
    if not (cfg.eval.block_s > 0 and math.isfinite(cfg.eval.block_s)):  # -5 reported a "-5 s residual RMS"
        raise ConfigError(f"eval.block_s must be > 0 s (the held-out residual's averaging block), got {cfg.eval.block_s}")
    data = instantiate(cfg.data)
    model = instantiate(cfg.model, n_inputs=data.n_features)
    data, model = with_axis_lags(data, lambda n, columns: instantiate(cfg.model, n_inputs=n, axis_columns=columns),
                                 model)
    writer = make_writer(cfg.logger.log_dir, fresh=True)  # a run folder holds one run, as its report.json does
    hparams = {k: v for k, v in OmegaConf.to_container(cfg.model, resolve=True).items() if k != "_target_"}
    try:  # a failed job in a sweep (scored inf) must not leave its writer open
        metrics = train_run(data, model, instantiate(cfg.optim), HydraConfig.get().runtime.output_dir,
                            OmegaConf.to_container(cfg.train), seed=cfg.seed,
                            kalman_cfg=OmegaConf.to_container(cfg.kalman), eval_paths=list(cfg.eval.paths),
                            eval_block_s=cfg.eval.block_s, writer=writer,
                            hparams={"model": cfg.model._target_.rsplit(".", 1)[-1], **hparams,
                                     "lr": cfg.optim.get("lr", 0.0), "seed": cfg.seed,  # and what a sweep searches
                                     **{f"data.{k}": cfg.data.get(k) for k in ("rate_tau_s", "val_startup_s")},
                                     **{f"train.{k}": cfg.train.get(k) for k in ("weight_decay", "max_epochs")}})
    finally:
        writer.close()
    if HydraConfig.get().mode != RunMode.MULTIRUN:  # a newcomer's next step, with the start-up window the bar assumes
        bundle = Path(HydraConfig.get().runtime.output_dir) / "compensator"
        bar = json.loads((bundle / "meta.json").read_text()).get("error_bar") or {}
        still_s = (bar.get("calibration") or {}).get("startup_s") or 0
        log.info("next: python scripts/compensate.py model=%s input=F.csv output=G.csv%s (docs/reference/commands.md)",
                 bundle, f" startup.still_s={still_s:g}" if still_s else "")
    return metrics["val/rmse_dps"]


if __name__ == "__main__":
    main()
