"""Close the loop: python scripts/diagnose.py data.path=F.csv hydra.run.dir=D [data.val_path=G.csv], or 'data.paths=[A.csv,B.csv]'.

Writes D/diagnosis.json, D/baseline/compensator/, D/compensator/ and D/report.md; see conf/diagnose.yaml.
"""
import sys
from pathlib import Path

from hydra.core.hydra_config import HydraConfig
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from gyronet.analysis.diagnose import diagnose
from gyronet.errors import fail

sys.path.insert(0, str(Path(__file__).resolve().parent))  # scripts/_cli.py, also when this file is run by path
from _cli import command  # noqa: E402


@command("diagnose", schemas={"train": "gyronet.training.train.fit", "diagnose": "gyronet.analysis.diagnose.DiagnoseOptions",
                              "diagnose.candidates": "gyronet.analysis.diagnose.CandidateGrid", "seed": int})
def main(cfg: DictConfig) -> None:
    data = {k: v for k, v in OmegaConf.to_container(cfg.data, resolve=True, throw_on_missing=True).items() if not k.startswith("_")}
    diagnose(data, lambda n_inputs: instantiate(cfg.model, n_inputs=n_inputs), HydraConfig.get().runtime.output_dir,
             optim=instantiate(cfg.optim), train_cfg=OmegaConf.to_container(cfg.train),
             options=OmegaConf.to_container(cfg.diagnose), seed=cfg.seed)


def refuse_train_only_options(overrides: list[str]) -> None:
    """``model=``, ``kalman=``, ``search=`` and ``eval.*`` are train.py's: Hydra ran ``model=rbf``, ignored
    ``+kalman=ar`` (what its own message for ``kalman=ar`` advises) and refused ``model=poly3`` with a setting of
    the default model (``model.validate_init``): one line that says so instead."""
    for override in overrides:
        key, _, value = override.partition("=")
        key = key.lstrip("+~")
        if (key == "model" and value != "default") or key.split(".")[0] in ("kalman", "search", "eval"):
            fail(f"{override}: diagnose.py trains gyronet's default model and takes train.py's data.* options, "
                 "not model=, kalman=, search= or eval.* (docs/reference/commands.md)")


if __name__ == "__main__":
    refuse_train_only_options(sys.argv[1:])
    main()
