"""Capacity per axis chosen on held-out data, and the refit on every block of one recording."""
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from gyronet.training import capacity
from gyronet.recordings.data import load_truth
from gyronet.training.dataset import Blocks, DriftData
from gyronet.model.rbf import RBFNet
from gyronet.sim import simulate, write_simulation
from gyronet.training.train import fit


def _run(temp_c, bump_c, rng):
    """Blocks of one synthetic run: x a bump that is this run's own, y a shared line, z a shared sharp knee."""
    n = len(temp_c)
    x = np.column_stack([temp_c, rng.normal(0, 1e-3, n), rng.normal(0, 1e-2, n)])
    drift = np.column_stack([0.05 * np.exp(-0.5 * ((temp_c - bump_c) / 2.0) ** 2),
                             0.003 * temp_c,
                             0.05 * np.tanh((temp_c - 5.0) / 1.5) + 1e-4 * temp_c**2])
    return x, drift + rng.normal(0, 2e-3, (n, 3))


def _fold(bump_train_c, bump_val_c, seed=0):
    """A fold of leave-one-run-out as ``fit`` sees it: train on one run, the other held out."""
    rng = np.random.default_rng(seed)
    temp = np.concatenate([np.linspace(20, -10, 600), np.linspace(-10, 20, 600)])
    time_s = np.arange(len(temp)) * 10.0
    xt, yt = _run(temp, bump_train_c, rng)
    xv, yv = _run(temp, bump_val_c, rng)
    return SimpleNamespace(train=Blocks(xt, yt, time_s), val=Blocks(xv, yv, time_s), val_full=(time_s, xv, yv),
                           held_out=1, temp_range_c=(-10.0, 20.0), offsets=None)


def test_choose_keeps_the_lowest_level_within_the_tolerance():
    errors = np.array([[5.0, 9.0, 9.0], [2.0, 1.005, 9.0], [1.5, 1.0, 9.0], [1.0, 1.2, 1.0]])
    assert capacity.choose(errors, tolerance=0.01) == [3, 1, 3]
    assert capacity.choose(errors, tolerance=0.6) == [2, 1, 3]


def test_refit_head_at_a_level_writes_only_the_given_axes():
    x = torch.rand(300, 3, dtype=torch.float64) * torch.tensor([40.0, 0.02, 1.0])
    y = torch.stack([torch.sin(x[:, 0] / 5), x[:, 0] / 40, torch.cos(x[:, 0] / 7)], 1)
    model = RBFNet(3, 3, 6, rbf_inputs=[0], linear=True, temp_degree=3, clamp=True)
    model.init_from_data(x, y, torch.Generator().manual_seed(0))
    before = {k: v.clone() for k, v in model.state_dict().items()}
    model.refit_head(x, y, level=1, axes=[1])
    assert torch.all(model.head.weight[1] == 0) and torch.all(model.poly.weight[1] == 0)
    assert torch.any(model.linear.weight[1] != 0)
    for name in ("head.weight", "linear.weight", "poly.weight"):
        assert torch.equal(model.state_dict()[name][[0, 2]], before[name][[0, 2]])
    model.refit_head(x, y, level=0, axes=[0])
    with torch.no_grad():
        assert torch.allclose(model(x)[:, 0], y[:, 0].mean().expand(len(x)))


def test_a_capacity_without_gaussians_says_which_settings_it_makes_inert(monkeypatch, caplog):
    """A GA sweep over n_centers, width_init, lr and seed on a record that keeps no Gaussians searches nothing."""
    monkeypatch.setattr(capacity, "refit", lambda *args: None)
    with caplog.at_level("INFO", logger="gyronet.training.capacity"):
        capacity.apply(None, None, [2, 1, 1])
        capacity.apply(None, None, [3, 1, 1])
    said = [r.getMessage() for r in caplog.records]
    assert said[0].endswith(f"z=linear (no axis keeps its Gaussians: {capacity.INERT})") and "optim.lr" in said[0]
    assert said[1].endswith("z=linear")


def test_held_out_runs_choose_each_axis_its_capacity():
    """x: a bump each run has at its own temperature (nothing to learn); y: a shared line; z: a shared knee."""
    data = _fold(bump_train_c=0.0, bump_val_c=12.0)
    model = RBFNet(3, 3, 12, rbf_inputs=[0], linear=True, temp_degree=3, clamp=True, select_capacity=True)
    metrics = fit(model, data, max_epochs=600, progress=False)
    errors = np.array([[metrics[f"val/capacity_{lv}_{a}_dps"] for a in "xyz"] for lv in capacity.LEVELS])
    levels = capacity.choose(errors)
    assert levels[0] <= 1, errors  # the first run's bump, learnt, is an error on the other run
    assert levels[1] == 1, errors
    assert levels[2] == 3, errors  # a knee 1.5 degC wide needs the Gaussians
    assert errors[levels[0], 0] < 0.8 * errors[3, 0]
    assert "model/level_x" not in metrics  # a fold reports; fit_by_run chooses over every fold


@pytest.mark.slow
def test_one_recording_is_refitted_on_every_block(tmp_path):
    """Sensor 4 on the paper profile: its x knee (-9.9 degC, 5 degC wide) lies in a validation span."""
    path = tmp_path / "paper4.csv"
    write_simulation(simulate("paper", fs_hz=0.5, seed=1, sensor_seed=4), path)
    data = DriftData(str(path), block_s=30.0)
    time_s, x, _ = data.val_full
    truth = load_truth(str(path))
    true_x = np.interp(time_s, truth.time_s, truth.columns["drift_x_dps"])
    knee = (x[:, 0] < -7.0) & (x[:, 0] > -13.0)
    assert knee.sum() > 100  # the knee is inside the held-out span
    error_dps = {}
    for refit_all in (False, True):
        model = RBFNet(3, 3, 12, rbf_inputs=[0], linear=True, temp_degree=3, clamp=True, select_capacity=True,
                       refit_all=refit_all)
        metrics = fit(model, data, max_epochs=1500, progress=False, for_bundle=True)
        assert [metrics[f"model/level_{a}"] for a in "xyz"] == [3, 3, 3]  # one run: full capacity where needed
        with torch.no_grad():
            predicted = model(torch.tensor(x[knee])).numpy()[:, 0]
        error_dps[refit_all] = float(np.sqrt(np.mean((predicted - true_x[knee]) ** 2)))
    assert error_dps[True] < 0.6 * error_dps[False], error_dps  # never seen without the refit: bridged
