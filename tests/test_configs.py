"""Every config composes with Hydra's compose API, and every group instantiates."""

import pytest
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate
from omegaconf import OmegaConf

from conftest import ROOT

CONF = ROOT / "conf"


@pytest.mark.parametrize("model", sorted(p.stem for p in (CONF / "model").glob("*.yaml")))
def test_every_model_composes_and_instantiates(model):
    with initialize_config_dir(str(CONF), version_base="1.3"):
        cfg = compose("train", overrides=[f"model={model}", "data.path=x.csv"])
    net = instantiate(cfg.model, n_inputs=3)
    assert net(__import__("torch").zeros(2, 3, dtype=__import__("torch").float64)).shape == (2, 3)
    assert callable(instantiate(cfg.optim))


def _composed_and_resolved(folder, name: str) -> dict:
    """The command's settings as its run sees them: every interpolation resolved (a value it may not name is
    a failure here, not at run time); a mandatory ``???`` stays as it is."""
    from hydra.core.hydra_config import HydraConfig
    from omegaconf import open_dict

    with initialize_config_dir(str(folder), version_base="1.3"):
        cfg = compose(name, return_hydra_config=True)
    with open_dict(cfg):
        cfg.hydra.runtime.output_dir = "/tmp/run"  # what Hydra sets when the command starts
    HydraConfig.instance().set_config(cfg)
    return OmegaConf.to_container(OmegaConf.masked_copy(cfg, [k for k in cfg if k != "hydra"]), resolve=True)


@pytest.mark.parametrize("name", sorted(p.stem for p in CONF.glob("*.yaml")))
def test_every_top_level_config_composes_and_resolves(name, hydra_restore_singletons):
    assert _composed_and_resolved(CONF, name)


@pytest.mark.parametrize("name", sorted(p.stem for p in (CONF / "deploy").glob("*.yaml")))
def test_deploy_configs_compose_and_resolve(name, hydra_restore_singletons):
    assert _composed_and_resolved(CONF / "deploy", name)


# keys that name a file or folder a command writes
OUTPUT_KEYS = ("output", "log_dir", "tb_dir", "summary", "log_file")


def _top_level_and_deploy():
    return [(CONF, p.stem) for p in CONF.glob("*.yaml")] + [(CONF / "deploy", p.stem) for p in (CONF / "deploy").glob("*.yaml")]


@pytest.mark.parametrize("folder, name", _top_level_and_deploy(), ids=lambda v: getattr(v, "name", v))
def test_every_default_output_goes_under_the_run_folder(folder, name):
    """An output the user does not name is written under hydra.run.dir, never into the current folder."""
    with initialize_config_dir(str(folder), version_base="1.3"):
        cfg = compose(name)
    container = OmegaConf.to_container(cfg, resolve=False)
    found = []

    def walk(node, key=""):
        if isinstance(node, dict):
            for k, v in node.items():
                walk(v, f"{key}.{k}" if key else k)
        elif key.rsplit(".", 1)[-1] in OUTPUT_KEYS and node not in (None, "???"):
            found.append((key, node))

    walk(container)
    stray = [(k, v) for k, v in found if not str(v).startswith("${hydra:runtime.output_dir}/")]
    assert stray == []
