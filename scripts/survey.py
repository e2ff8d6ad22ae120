"""The survey: python scripts/survey.py [n_sensors=100 jobs=2] [hydra.run.dir=D] (see conf/survey.yaml).

Per sensor: D/sensors/sensor_<seed>/ (records, one bundle per method, result.json); then D/survey.md,
D/survey.json, D/survey_sensors.csv and D/survey.png. Run again with the same hydra.run.dir to resume.
"""
import logging
import sys
from pathlib import Path

from hydra import compose
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf

from gyronet.errors import GyronetError
from gyronet.sim.survey_sensor import check_distribution
from gyronet.analysis.survey.bound import BOUND
from gyronet.analysis.survey import TRAIN_PATH, History, SurveySpec, summarize, survey, to_markdown, write_outputs

sys.path.insert(0, str(Path(__file__).resolve().parent))  # scripts/_cli.py, also when this file is run by path
from _cli import CONF_DIR, command  # noqa: E402

log = logging.getLogger(__name__)


def _method(model: str, overrides: list) -> dict:
    """What ``train.py model=<model> <overrides>`` trains, as plain settings (data.path stands for each sensor's record)."""
    known = sorted(p.stem for p in (CONF_DIR / "model").glob("*.yaml"))
    if model not in known:
        raise GyronetError(f"methods: no conf/model/{model}.yaml (known: {', '.join(known)})")
    cfg = compose("train", overrides=[f"model={model}", f"data.path={TRAIN_PATH}", *overrides])
    return {**{key: OmegaConf.to_container(cfg[key], resolve=True) for key in ("model", "data", "optim", "train")},
            "seed": int(cfg.seed)}


@command("survey", schemas={"n_sensors": int, "first_seed": int, "jobs": int, "fs_hz": float, "startup_s": float,
                            "reuse": bool, "keep_records": bool, "bound": bool, "train_overrides": list,
                            "more_train_histories": list,
                            "train_history": "gyronet.analysis.survey.History", "check_history": "gyronet.analysis.survey.History",
                            "goals": "gyronet.analysis.survey.table.goal_keys"})
def main(cfg: DictConfig) -> None:
    if cfg.n_sensors < 1:
        raise GyronetError(f"n_sensors must be at least 1, got {cfg.n_sensors}")
    if cfg.jobs < 1:
        raise GyronetError(f"jobs must be a whole number >= 1, got {cfg.jobs}")
    check_distribution(cfg.distribution)
    chosen = cfg.methods or {}  # methods=null: form-bound alone
    methods = {str(name): _method(str(model), list(cfg.train_overrides)) for name, model in chosen.items()}
    scored = [*methods, *([BOUND] if cfg.bound else [])]
    if not scored:
        raise GyronetError("nothing to score: no methods and bound=false")
    for key in ("ours", "reference"):
        if cfg[key] not in scored and not (key == "reference" and cfg[key] is None):
            raise GyronetError(f"{key}={cfg[key]} is not one of the methods ({', '.join(scored)})")
    histories = {k: History(**OmegaConf.to_container(cfg[k], resolve=True)) for k in ("train_history", "check_history")}
    more = tuple(_history(item) for item in cfg.more_train_histories)
    spec = SurveySpec(methods=methods, distribution=cfg.distribution, fs_hz=cfg.fs_hz, startup_s=cfg.startup_s,
                      simulate=OmegaConf.to_container(cfg.simulate, resolve=True), keep_records=cfg.keep_records,
                      bound=cfg.bound, more_train_histories=more, **histories)
    out_dir = Path(HydraConfig.get().runtime.output_dir)
    seeds = range(cfg.first_seed, cfg.first_seed + cfg.n_sensors)
    results = survey(seeds, spec, out_dir, jobs=cfg.jobs, reuse=cfg.reuse, progress=cfg.progress)
    summary = summarize(results, cfg.ours, cfg.reference, OmegaConf.to_container(cfg.goals))
    settings = {"distribution": cfg.distribution, "startup_s": cfg.startup_s, "fs_hz": cfg.fs_hz,
                "train": " + ".join(_history_text(h) for h in (histories["train_history"], *more)),
                "check": _history_text(histories["check_history"]),
                "methods": dict(chosen), "train_overrides": list(cfg.train_overrides),
                "first_seed": cfg.first_seed}
    output = write_outputs(results, summary, settings, cfg.output)
    log.info("survey table %s (and .json, _sensors.csv, .png), %.0f s a sensor (median):\n%s", output,
             summary["seconds_per_sensor"], to_markdown(summary, settings))


def _history(item) -> History:
    """One of ``more_train_histories``, or a one-line error naming the settings a history takes."""
    known = ", ".join(History.__dataclass_fields__)
    if not isinstance(item, DictConfig):
        raise GyronetError(f"more_train_histories: each item is a history {{{known}}}, got {item!r}")
    try:
        return History(**OmegaConf.to_container(item, resolve=True))
    except TypeError as err:
        raise GyronetError(f"more_train_histories: {err} (a history takes {known})") from None


def _history_text(history: History) -> str:
    extra = f", {history.duration_s:g} s" if history.duration_s else ""
    options = "".join(f", {k}={v}" for k, v in dict(history.profile_options).items())
    simulate = f", simulate={dict(history.simulate)}" if history.simulate else ""
    return f"profile={history.profile} seed={history.seed}{extra}{options}{simulate}"


if __name__ == "__main__":
    main()
