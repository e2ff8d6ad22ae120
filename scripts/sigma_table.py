"""The README's error-bar calibration table: python scripts/sigma_table.py [hydra.run.dir=D] ['sensors=[0]'].

Simulated sensors trained on the paper's staircase and compensated on other histories, scored against
their truth; the real cats-tag runs each held out in turn (truth: zero rate). Writes D/sigma_table.md and
.json; see conf/sigma_table.yaml and gyronet/training/sigma_table.py.
"""
import logging
import sys
from pathlib import Path

from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from gyronet.training.runs import run_name
from gyronet.training.sigma_table import score_simulated, score_still, to_markdown, write_table

sys.path.insert(0, str(Path(__file__).resolve().parent))  # scripts/_cli.py, also when this file is run by path
from _cli import command, run_script  # noqa: E402

log = logging.getLogger(__name__)


@command("sigma_table", schemas={"fs_hz": float, "reuse": bool, "real_still_s": float})
def main(cfg: DictConfig) -> None:
    root = Path(HydraConfig.get().runtime.output_dir)
    rows = []
    for sensor in cfg.sensors:
        rows += _simulated(cfg, root / f"s{sensor}", int(sensor), {}, list(cfg.held_out), "paper")
    if cfg.narrow:
        options = dict(cfg.narrow.profile_options)
        label = f"paper {options.get('start_c', 60):g} to {options.get('stop_c', -40):g} degC"
        rows += _simulated(cfg, root / "narrow", int(cfg.narrow.sensor), options, [cfg.narrow.held_out], label)
    runs = [str(Path(p)) for p in cfg.real_runs]
    if runs and all(Path(p).is_file() for p in runs):
        for train, held in ((runs[0], runs[1]), (runs[1], runs[0])):
            folder = root / f"real_{run_name(train)}"
            bundle = _train(cfg, folder, train)
            out = folder / f"{run_name(held)}_out.csv"
            _step(cfg, out, "compensate.py", f"model={bundle}", f"input={held}", f"output={out}",
                  f"startup.still_s={cfg.real_still_s}")
            rows.append({"kind": "real", "trained_on": run_name(train), "held_out": f"{run_name(held)} (still, "
                         f"from {cfg.real_still_s:g} s)", "score": score_still(out, cfg.real_still_s)})
    elif runs:
        log.warning("real runs not found (%s): the table has simulated rows only", ", ".join(runs))
    output = write_table(rows, cfg.output, OmegaConf.to_container(cfg, resolve=True))
    log.info("error-bar table %s (and .json):\n%s", output, to_markdown(rows))


def _simulated(cfg: DictConfig, folder: Path, sensor: int, options: dict, held_out: list, label: str) -> list:
    """One sensor: its training record and bundle, then each held-out history compensated and scored."""
    train = folder / "train.csv"
    history = cfg.train_history
    _step(cfg, train, "simulate.py", f"output={train}", f"profile={history.profile}", f"seed={history.seed}",
          f"sensor_seed={sensor}", f"fs_hz={cfg.fs_hz}",
          *[f"+profile_options.{k}={v}" for k, v in options.items()])
    bundle = _train(cfg, folder, train)
    rows = []
    for held in held_out:
        name = f"{held.profile}{held.seed}"
        record, out = folder / f"{name}.csv", folder / f"{name}_out.csv"
        _step(cfg, record, "simulate.py", f"output={record}", f"profile={held.profile}", f"seed={held.seed}",
              f"sensor_seed={sensor}", f"fs_hz={cfg.fs_hz}")
        _step(cfg, out, "compensate.py", f"model={bundle}", f"input={record}", f"output={out}")
        rows.append({"kind": "simulated", "trained_on": f"sensor {sensor}, {label}",
                     "held_out": f"{held.profile} seed {held.seed}", "score": score_simulated(out, record)})
    return rows


def _train(cfg: DictConfig, folder: Path, path: str | Path) -> Path:
    bundle = folder / "run" / "compensator"
    _step(cfg, bundle / "meta.json", "train.py", f"data.path={path}", f"hydra.run.dir={folder / 'run'}",
          "train.progress=false", *cfg.train)
    return bundle


def _step(cfg: DictConfig, made: Path, script: str, *overrides: str) -> None:
    """One README command in its own interpreter, unless ``reuse`` and what it makes is there."""
    if cfg.reuse and Path(made).is_file():
        return
    run_script(script, *overrides)


if __name__ == "__main__":
    main()
