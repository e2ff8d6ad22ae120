"""The README's table on the simulator's effects: python scripts/effects_table.py [hydra.run.dir=D] ['effects=[aux]'].

Per effect: D/<effect>/train.csv and check.csv (scripts/simulate.py), D/<effect>/diagnose/ (scripts/diagnose.py),
both bundles checked on check.csv against its truth. Writes D/effects_table.md and .json; see conf/effects_table.yaml.
"""
import json
import logging
import sys
from pathlib import Path

from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from gyronet.analysis.diagnose.effects import check_bundle, effect_row, to_markdown, write_table
from gyronet.errors import GyronetError

sys.path.insert(0, str(Path(__file__).resolve().parent))  # scripts/_cli.py, also when this file is run by path
from _cli import command, run_script  # noqa: E402

log = logging.getLogger(__name__)
SCRIPTS = Path(__file__).resolve().parent
EFFECTS_CONF = SCRIPTS.parent / "conf" / "sim" / "effects"


@command("effects_table", schemas={"sensor_seed": int, "reuse": bool})
def main(cfg: DictConfig) -> None:
    known = sorted(p.stem for p in EFFECTS_CONF.glob("*.yaml"))
    unknown = [effect for effect in cfg.effects if effect not in known]
    if unknown:
        raise GyronetError(f"effects: no conf/sim/effects/{unknown[0]}.yaml (known: {', '.join(known)})")
    rows = []
    for effect in cfg.effects:
        folder = Path(HydraConfig.get().runtime.output_dir) / effect
        diagnosis = _diagnose(cfg, effect, folder)
        checks = [check_bundle(folder / "diagnose" / bundle, folder / "check.csv")
                  for bundle in ("baseline/compensator", "compensator")]
        rows.append(effect_row(effect, diagnosis, *checks))
        log.info("%s done:\n%s", effect, to_markdown(rows[-1:]))
    output = write_table(rows, cfg.output, OmegaConf.to_container(cfg, resolve=True))
    log.info("effects table %s (and .json):\n%s", output, to_markdown(rows))


def _diagnose(cfg: DictConfig, effect: str, folder: Path) -> dict:
    """The two records of one effect and its diagnosis (kept with ``reuse``): diagnosis.json."""
    for name, history in (("train", cfg.train_history), ("check", cfg.check_history)):
        if not (cfg.reuse and (folder / f"{name}.csv").is_file()):
            run_script("simulate.py", f"output={folder / name}.csv", f"sim/effects={effect}", f"profile={history.profile}",
                 f"seed={history.seed}", f"sensor_seed={cfg.sensor_seed}", *cfg.simulate)
    if not (cfg.reuse and (folder / "diagnose" / "diagnosis.json").is_file()):
        run_script("diagnose.py", f"data.path={folder / 'train.csv'}", f"hydra.run.dir={folder / 'diagnose'}",
             *cfg.diagnose)
    return json.loads((folder / "diagnose" / "diagnosis.json").read_text())



if __name__ == "__main__":
    main()
