"""Train a drift compensator: python scripts/train.py data.path=F.csv [model=rbf|poly3|lsq] [-m hydra/sweeper=ga]."""
import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from gyronet.errors import exit_on_error
from gyronet.pipeline import train_run
from gyronet.tb import make_writer


@hydra.main(version_base="1.3", config_path="../conf", config_name="train")
def main(cfg: DictConfig) -> float:
    # a sweep needs failures as exceptions (the sweeper scores them inf); a single run, as one line
    if HydraConfig.get().mode == RunMode.MULTIRUN:
        return run(cfg)
    return exit_on_error(run)(cfg)


def run(cfg: DictConfig) -> float:
    data = instantiate(cfg.data)
    model = instantiate(cfg.model, n_inputs=data.n_features)
    writer = make_writer(cfg.logger.log_dir)
    hparams = {k: v for k, v in OmegaConf.to_container(cfg.model, resolve=True).items() if k != "_target_"}
    metrics = train_run(data, model, instantiate(cfg.optim), HydraConfig.get().runtime.output_dir,
                        OmegaConf.to_container(cfg.train), seed=cfg.seed,
                        kalman_cfg=OmegaConf.to_container(cfg.kalman), eval_paths=list(cfg.eval.paths),
                        eval_block_s=cfg.eval.block_s, writer=writer,
                        hparams={"model": cfg.model._target_.rsplit(".", 1)[-1], **hparams,
                                 "lr": cfg.optim.get("lr", 0.0), "seed": cfg.seed})
    writer.close()
    return metrics["val/rmse_dps"]


if __name__ == "__main__":
    main()
