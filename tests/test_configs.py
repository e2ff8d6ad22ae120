"""Every config composes with Hydra's compose API, and every group instantiates."""

import pytest
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate

from conftest import ROOT

CONF = ROOT / "conf"


@pytest.mark.parametrize("model", sorted(p.stem for p in (CONF / "model").glob("*.yaml")))
def test_every_model_composes_and_instantiates(model):
    with initialize_config_dir(str(CONF), version_base="1.3"):
        cfg = compose("train", overrides=[f"model={model}", "data.path=x.csv"])
    net = instantiate(cfg.model, n_inputs=3)
    assert net(__import__("torch").zeros(2, 3, dtype=__import__("torch").float64)).shape == (2, 3)
    assert callable(instantiate(cfg.optim))


@pytest.mark.parametrize("name", sorted(p.stem for p in CONF.glob("*.yaml")))
def test_every_top_level_config_composes(name):
    with initialize_config_dir(str(CONF), version_base="1.3"):
        assert compose(name) is not None


@pytest.mark.parametrize("name", sorted(p.stem for p in (CONF / "deploy").glob("*.yaml")))
def test_deploy_configs_compose(name):
    with initialize_config_dir(str(CONF / "deploy"), version_base="1.3"):
        assert compose(name) is not None
