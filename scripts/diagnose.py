"""Close the loop: python scripts/diagnose.py data.path=F.csv hydra.run.dir=D [data.val_path=G.csv].

Writes D/diagnosis.json, D/baseline/compensator/, D/compensator/ and D/report.md; see conf/diagnose.yaml.
"""
import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from gyronet.diagnose import diagnose
from gyronet.errors import exit_on_error


@hydra.main(version_base="1.3", config_path="../conf", config_name="diagnose")
@exit_on_error
def main(cfg: DictConfig) -> None:
    data = {k: v for k, v in OmegaConf.to_container(cfg.data, resolve=True).items() if not k.startswith("_")}
    diagnose(data, lambda n_inputs: instantiate(cfg.model, n_inputs=n_inputs), HydraConfig.get().runtime.output_dir,
             optim=instantiate(cfg.optim), train_cfg=OmegaConf.to_container(cfg.train),
             options=OmegaConf.to_container(cfg.diagnose), seed=cfg.seed)


if __name__ == "__main__":
    main()
