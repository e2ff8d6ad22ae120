"""Close the loop: python scripts/diagnose.py data.path=F.csv hydra.run.dir=D [data.val_path=G.csv], or 'data.paths=[A.csv,B.csv]'.

Writes D/diagnosis.json, D/baseline/compensator/, D/compensator/ and D/report.md; see conf/diagnose.yaml.
"""
import sys
from pathlib import Path

from hydra.core.hydra_config import HydraConfig
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from gyronet.analysis.diagnose import diagnose

sys.path.insert(0, str(Path(__file__).resolve().parent))  # scripts/_cli.py, also when this file is run by path
from _cli import command  # noqa: E402


@command("diagnose", schemas={"train": "gyronet.training.train.fit", "diagnose": "gyronet.analysis.diagnose.DiagnoseOptions",
                              "diagnose.candidates": "gyronet.analysis.diagnose.CandidateGrid", "seed": int})
def main(cfg: DictConfig) -> None:
    data = {k: v for k, v in OmegaConf.to_container(cfg.data, resolve=True, throw_on_missing=True).items() if not k.startswith("_")}
    diagnose(data, lambda n_inputs: instantiate(cfg.model, n_inputs=n_inputs), HydraConfig.get().runtime.output_dir,
             optim=instantiate(cfg.optim), train_cfg=OmegaConf.to_container(cfg.train),
             options=OmegaConf.to_container(cfg.diagnose), seed=cfg.seed)


if __name__ == "__main__":
    main()
