"""RBFNet and the baselines: gradients, TorchScript round trip, PX4 clamping, extrapolation."""
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from torch.testing import assert_close

from gyronet.model.baselines import LinearFeatures, TempPolynomial
from gyronet.training.dataset import Blocks
from gyronet.bundle.io import load_bundle, save_bundle
from gyronet.model.rbf import CENTER_INITS, OLS_NARROW_WIDTHS_C, OLS_WIDTHS_C, RBFNet, forward_select
from gyronet.training.starts import held_out_residuals, member_seeds, mix_into, stack_weights
from gyronet.training.train import fit, validation_metrics


def _data(n=400, seed=0):
    g = torch.Generator().manual_seed(seed)
    x = torch.rand(n, 3, generator=g, dtype=torch.float64) * torch.tensor([100.0, 0.03, 3.0]) - torch.tensor([40.0, 0.015, 1.5])
    y = torch.stack([torch.sin(x[:, 0] / 20), 0.01 * x[:, 0] + 5 * x[:, 1], x[:, 2]], 1)
    return x, y


def test_gradcheck_on_a_tiny_float64_net():
    model = RBFNet(3, 2, n_centers=4, linear=True, temp_degree=3)
    x, y = _data(20)
    model.init_from_data(x, y[:, :2], torch.Generator().manual_seed(0))
    names = ("centers", "raw_width", "head.weight")

    def fn(*tensors):
        return torch.func.functional_call(model, dict(zip(names, tensors)), (x[:5],))

    inputs = tuple(dict(model.named_parameters())[n].detach().clone().requires_grad_(True) for n in names)
    assert torch.autograd.gradcheck(fn, inputs)


@pytest.mark.parametrize("options", [dict(rbf_inputs=[0], linear=True, temp_degree=3, clamp=True), dict()],
                         ids=["default", "paper"])
def test_a_fit_on_a_fixed_input_computes_forward_and_its_gradients(options):
    model = RBFNet(3, 3, n_centers=6, **options)
    x, y = _data(300)
    model.init_from_data(x, y, torch.Generator().manual_seed(0))
    x_out = x * 1.5  # outside the box on every side: the clamp is part of what is precomputed
    gradients = []
    for output in (model(x_out), model.on_fixed_input(x_out)()):
        model.zero_grad()
        output.pow(2).sum().backward()
        gradients.append([p.grad.clone() for p in model.parameters() if p.requires_grad])
    assert torch.equal(model(x_out), model.on_fixed_input(x_out)())
    for by_autograd, by_hand in zip(*gradients):  # one input: the Gaussians' gradient by hand, to rounding
        assert_close(by_hand, by_autograd, rtol=1e-12, atol=1e-12 * float(by_autograd.abs().max()))


def test_widths_stay_positive():
    model = RBFNet(3, 3, n_centers=5)
    model.raw_width.data.fill_(-50.0)
    assert torch.all(model.widths() > 0)


def test_script_save_load_round_trip(tmp_path):
    x, y = _data()
    for model in (RBFNet(3, 3, 8, rbf_inputs=[0], linear=True, temp_degree=3, clamp=True), RBFNet(3, 3, 8),
                  TempPolynomial(3), LinearFeatures(3)):
        if hasattr(model, "fit_closed_form"):
            model.fit_closed_form(x, y)
        else:
            model.init_from_data(x, y, torch.Generator().manual_seed(1))
        save_bundle(model, {"features": [], "fs_hz": 10.0, "temp_range_c": [-40, 60]}, tmp_path / "b")
        loaded, meta, kalman = load_bundle(tmp_path / "b")
        assert meta["fs_hz"] == 10.0 and kalman is None
        with torch.no_grad():
            assert_close(loaded(x), model(x), rtol=0, atol=1e-12)


def test_head_least_squares_fits_a_linear_target_exactly():
    x, _ = _data()
    y = x @ torch.tensor([[0.01, 0.0, 1.0], [3.0, -2.0, 0.0], [0.0, 0.5, 0.2]], dtype=torch.float64) + 0.3
    model = RBFNet(3, 3, 4, linear=True)
    model.init_from_data(x, y, torch.Generator().manual_seed(0))
    model.refit_head(x, y, ridge=1e-14)
    with torch.no_grad():
        assert_close(model(x), y, rtol=0, atol=1e-6)


def test_hybrid_extrapolates_the_rate_linearly_but_the_plain_rbf_does_not():
    x, _ = _data()
    x[:, 1] = -x[:, 1].abs()  # trained on cooling only
    x[:, 2] = x[:, 0] * x[:, 1]
    y = (8.0 * x[:, 1:2]).repeat(1, 3)
    heating = x.clone()
    heating[:, 1] = -heating[:, 1]
    heating[:, 2] = heating[:, 0] * heating[:, 1]
    hybrid = RBFNet(3, 3, 8, rbf_inputs=[0], linear=True, temp_degree=3, clamp=True)
    plain = RBFNet(3, 3, 8)
    for model in (hybrid, plain):
        model.init_from_data(x, y, torch.Generator().manual_seed(0))
    with torch.no_grad():
        err_hybrid = (hybrid(heating) - 8.0 * heating[:, 1:2]).abs().max()
        err_plain = (plain(heating) - 8.0 * heating[:, 1:2]).abs().max()
    assert err_hybrid < 1e-3 < err_plain


def test_px4_polynomial_clamps_to_the_calibrated_range():
    temp = torch.linspace(-20, 40, 200, dtype=torch.float64)
    x = torch.stack([temp, torch.zeros_like(temp), torch.zeros_like(temp)], 1)
    y = torch.stack([1e-4 * temp**3, 0.01 * temp, -0.02 * temp + 1], 1)
    model = TempPolynomial(3)
    model.fit_closed_form(x, y)
    assert float(model.temp_ref_c) == 10.0
    hot = torch.tensor([[80.0, 0.0, 0.0], [40.0, 0.0, 0.0]], dtype=torch.float64)
    out = model(hot)
    assert_close(out[0], out[1])
    assert_close(out[1], torch.tensor([6.4, 0.4, 0.2], dtype=torch.float64), rtol=0, atol=1e-9)


def _hybrid_on_drift_with_a_temperature_slope():
    """The default model's shape, trained on drift with a linear and a cubic part in temperature."""
    x, _ = _data()
    x[:, 2] = x[:, 0] * x[:, 1]
    y = torch.stack([0.02 * x[:, 0] + 1e-5 * x[:, 0] ** 3 + 8.0 * x[:, 1], 0.01 * x[:, 0], torch.sin(x[:, 0] / 20)], 1)
    model = RBFNet(3, 3, 8, rbf_inputs=[0], linear=True, temp_degree=3, clamp=True)
    model.init_from_data(x, y, torch.Generator().manual_seed(0))
    return model, x


def _unclamped_linear_output(model, x):
    """The output with the linear term on unclamped inputs (the formula before the fix)."""
    phi, _, powers = model.parts(x)
    z = (x - model.x_mean) / model.x_std
    return (model.head(phi) + model.linear(z) + model.poly(powers)) * model.y_std + model.y_mean


def test_every_part_holds_its_edge_value_above_and_below_the_trained_range():
    model, x = _hybrid_on_drift_with_a_temperature_slope()
    low, high = float(x[:, 0].min()), float(x[:, 0].max())
    for edge, beyond in ((high, high + 40.0), (low, low - 40.0)):
        steady = torch.tensor([[edge, 0.0, 0.0], [beyond, 0.0, 0.0]], dtype=torch.float64)
        with torch.no_grad():
            out = model(steady)
            moved_before = (_unclamped_linear_output(model, steady)[1] - out[0]).abs().max()
        assert moved_before > 0.1  # the linear temperature term alone used to move this far
        assert_close(out[1], out[0], rtol=0, atol=1e-12)


def test_clamping_the_linear_temperature_term_changes_nothing_inside_the_box():
    model, x = _hybrid_on_drift_with_a_temperature_slope()
    with torch.no_grad():
        assert_close(model(x), _unclamped_linear_output(model, x), rtol=0, atol=1e-12)
        # the rate terms stay linear outside the box: twice the fastest trained rate, twice the effect
        fast = x[:5].clone()
        fast[:, 1] = 2 * x[:, 1].abs().max()
        fast[:, 2] = fast[:, 0] * fast[:, 1]
        faster = fast.clone()
        faster[:, 1] *= 2
        faster[:, 2] = faster[:, 0] * faster[:, 1]
        slow = fast.clone()
        slow[:, 1:] = 0.0
        assert_close(model(faster) - model(slow), 2 * (model(fast) - model(slow)), rtol=1e-9, atol=1e-12)
        # the scripted model does the same
        scripted = torch.jit.script(model)
        beyond = x[:3].clone()
        beyond[:, 0] += 200.0
        assert_close(scripted(beyond), model(beyond), rtol=0, atol=1e-12)


def _knee_data(width_c=4.0, knee_c=17.0, n=2000, seed=0):
    """One slow pass through -40..60 degC: a cubic bias plus a tanh knee a few degC wide, and noise."""
    g = torch.Generator().manual_seed(seed)
    temp = torch.linspace(60.0, -40.0, n, dtype=torch.float64)
    rate = torch.full_like(temp, -1.0 / 60)
    x = torch.stack([temp, rate, temp * rate], 1)
    u = (temp - 10.0) / 50.0
    knee = 0.3 * torch.tanh((temp - knee_c) / width_c)
    y = torch.stack([0.8 * u + 0.3 * u**3 + knee, -0.5 * u**2 - 0.5 * knee, 0.4 * u], 1)
    return x, y + 1e-3 * torch.randn(y.shape, generator=g, dtype=torch.float64), knee


def test_forward_selection_finds_the_columns_a_target_is_made_of():
    g = torch.Generator().manual_seed(0)
    t = torch.linspace(-1, 1, 300, dtype=torch.float64)[:, None]
    candidates = torch.exp(-0.5 * ((t - torch.linspace(-1, 1, 41, dtype=torch.float64)) / 0.1) ** 2)
    base = torch.cat([torch.ones_like(t), t], 1)
    target = base @ torch.randn(2, 2, generator=g, dtype=torch.float64) + candidates[:, [7, 30]] @ torch.tensor(
        [[1.0, 0.0], [0.5, -2.0]], dtype=torch.float64)
    assert sorted(forward_select(candidates, base, target, 2).tolist()) == [7, 30]


def test_ols_initialisation_fits_a_sharp_knee_that_kmeans_centres_miss():
    x, y, _ = _knee_data()
    misfit = {}
    for init in ("kmeans", "ols"):
        model = RBFNet(3, 3, 6, rbf_inputs=[0], linear=True, temp_degree=3, clamp=True, center_init=init)
        model.init_from_data(x, y, torch.Generator().manual_seed(0))
        with torch.no_grad():
            misfit[init] = float((model(x) - y)[:, :2].pow(2).mean().sqrt())
    assert misfit["ols"] < 0.5 * misfit["kmeans"], misfit
    with torch.no_grad():
        widths_c = model.widths() * model.x_std[0]
    assert float(widths_c.min()) >= OLS_WIDTHS_C[0] - 1e-9  # the candidates' widths, in degC


def test_the_narrow_start_follows_a_knee_2_5_degC_wide_that_the_ols_candidates_cannot():
    x, y, _ = _knee_data(width_c=2.5)
    misfit, floor_c = {}, {}
    for init in ("ols", "ols_narrow"):
        model = RBFNet(3, 3, 6, rbf_inputs=[0], linear=True, temp_degree=3, clamp=True, center_init=init)
        model.init_from_data(x, y, torch.Generator().manual_seed(0))
        with torch.no_grad():
            misfit[init] = float((model(x) - y)[:, :2].pow(2).mean().sqrt())
        floor_c[init] = model.train_min_width * float(model.x_std[0])  # training's width floor, degC
    assert misfit["ols_narrow"] < 0.8 * misfit["ols"], misfit  # 0.66 here
    assert floor_c == pytest.approx({"ols": OLS_WIDTHS_C[0], "ols_narrow": OLS_NARROW_WIDTHS_C[0]})


def test_ols_centres_stay_out_of_a_gap_in_the_training_temperatures():
    """A held-out span leaves a gap; a Gaussian centred there would be fitted by its tails alone."""
    x, y, _ = _knee_data(knee_c=-5.0)
    kept = (x[:, 0] < -10.0) | (x[:, 0] > 0.0)
    model = RBFNet(3, 3, 12, rbf_inputs=[0], linear=True, temp_degree=3, clamp=True, center_init="ols")
    model.init_from_data(x[kept], y[kept], torch.Generator().manual_seed(0))
    with torch.no_grad():
        centres_c = (model.centers[:, 0] * model.x_std[0] + model.x_mean[0]).tolist()
    assert not any(-8.5 < c < -1.5 for c in centres_c), centres_c


def test_ols_initialisation_refuses_gaussians_on_several_inputs_and_unknown_inits():
    with pytest.raises(ValueError, match="temperature only"):
        RBFNet(3, 3, 4, center_init="ols")
    with pytest.raises(ValueError, match="center_init"):
        RBFNet(3, 3, 4, center_init="grid")


def _blocks(x, y):
    """Every fifth block held out, as ``fit`` reads a recording's blocks."""
    time_s = np.arange(len(x)) * 10.0
    held_out = np.arange(len(x)) % 5 == 0
    blocks = [Blocks(x[m].numpy(), y[m].numpy(), time_s[m]) for m in (~held_out, held_out)]
    return SimpleNamespace(train=blocks[0], val=blocks[1], val_full=(blocks[1].time_s, blocks[1].x, blocks[1].y))


def test_stack_weights_minimise_the_held_out_error_of_the_mixture_per_axis():
    rng = np.random.default_rng(0)
    first = rng.normal(size=(50, 3)) + np.array([0.0, 2.0, -1.0])
    second = rng.normal(size=(50, 3)) + np.array([0.0, -1.0, -3.0])
    second[:, 2] = 2 * first[:, 2]  # twice the error everywhere on z: the weight stops at 0
    weights = stack_weights(first, second)[1]
    grid = np.linspace(0.0, 1.0, 2001)
    error = [(((1 - w) * first + w * second) ** 2).sum(0) for w in grid]
    assert_close(torch.tensor(weights), torch.tensor(grid[np.argmin(error, axis=0)]), atol=1e-3, rtol=0)
    assert 0.0 < weights[0] < 1.0 and weights[2] == 0.0
    assert stack_weights(first, first).tolist() == [[1.0, 1.0, 1.0], [0.0, 0.0, 0.0]]


def test_stack_weights_of_three_models_are_the_best_point_of_the_simplex():
    rng = np.random.default_rng(1)
    parts = [rng.normal(size=(40, 3)) + shift for shift in (np.array([1.0, 0.0, 2.0]), np.array([-1.0, 0.5, 2.5]),
                                                              np.array([0.2, -0.5, 3.0]))]
    weights = stack_weights(*parts)
    assert (weights >= 0).all() and np.allclose(weights.sum(0), 1.0)
    step = np.linspace(0.0, 1.0, 201)
    grid = np.array([(a, b, 1 - a - b) for a in step for b in step if a + b <= 1 + 1e-12])  # (points, 3)
    error = ((np.einsum("pk,kma->pma", grid, np.stack(parts))) ** 2).sum(1)  # (points, axes)
    best = (np.einsum("ka,kma->ma", weights, np.stack(parts)) ** 2).sum(0)
    assert (best <= error.min(0) + 1e-9).all()


def test_validate_init_mixes_the_starts_per_axis_by_their_held_out_residuals(tmp_path):
    """The bundle is one network: sum_k w_k start_k per axis, the w stacked on the held-out blocks."""
    x, y, _ = _knee_data()
    data = _blocks(x, y)
    alone = {}
    for init in CENTER_INITS:
        alone[init] = RBFNet(3, 3, 6, rbf_inputs=[0], linear=True, temp_degree=3, clamp=True, center_init=init)
        fit(alone[init], data, max_epochs=100, progress=False)
    model = RBFNet(3, 3, 6, rbf_inputs=[0], linear=True, temp_degree=3, clamp=True, validate_init=True)
    metrics = fit(model, data, max_epochs=100, progress=False)
    weights = stack_weights(*(held_out_residuals(alone[i], data) for i in CENTER_INITS))
    assert [[metrics[f"model/{i}_weight_{a}"] for a in "xyz"] for i in CENTER_INITS] == weights.tolist()
    assert weights[:, 0].max() < 1.0  # no start alone: the x knee
    with torch.no_grad():
        mixture = sum(torch.tensor(w) * alone[i](x) for i, w in zip(CENTER_INITS, weights))
        assert_close(model(x), mixture, rtol=0, atol=1e-12)
    assert metrics["val/rmse_dps"] <= min(validation_metrics(m, data)["val/rmse_dps"] for m in alone.values())
    assert model.n_centers == 6 * weights.any(axis=1).sum()  # a start with no weight is left out
    meta = {"features": [], "fs_hz": 10.0, "temp_range_c": [-40, 60]}
    loaded = load_bundle(save_bundle(model, meta, tmp_path / "b"))[0]
    assert_close(loaded(x), model(x).detach())


class _PowerUp(torch.nn.Module):
    """A drift of ``window_dps`` on every axis over the first 600 s (feature 0 is the time), 0 after."""

    def __init__(self, window_dps):
        super().__init__()
        self.window_dps = window_dps

    def forward(self, x):
        return torch.where(x[:, :1] < 600.0, x.new_tensor(self.window_dps), x.new_zeros(())).expand(len(x), 3)


def test_mixing_as_deployed_charges_a_start_its_error_over_the_records_power_up():
    """With data.val_startup_s each start's held-out blocks are scored less its mean residual over the
    record's first val_startup_s s: a start-up offset carries that error into every later sample."""
    rng = np.random.default_rng(0)
    time_s = np.arange(0.0, 6000.0, 10.0)
    y = np.where(time_s[:, None] < 600.0, 0.01, 0.0) + np.zeros((len(time_s), 3))
    held = (time_s >= 3000) & (time_s < 4200)
    y[held] += rng.normal(0.0, 1e-3, (held.sum(), 3))
    x = np.column_stack([time_s, np.zeros((len(time_s), 2))])
    temp_c = np.full(len(time_s), 25.0)  # it powers up at 25 degC, inside its -40..60 degC
    data = SimpleNamespace(train=Blocks(x[~held], y[~held], time_s[~held]), val=Blocks(x[held], y[held], time_s[held]),
                           val_full=(time_s[held], x[held], y[held]), val_path=None, val_startup_s=0.0,
                           recording=SimpleNamespace(time_s=time_s, temp_c=temp_c), temp_range_c=(-40.0, 60.0))
    misses, follows = _PowerUp(0.0), _PowerUp(0.01)  # alike on the held-out blocks; one misses the power-up
    as_is = held_out_residuals(misses, data)
    assert_close(held_out_residuals(follows, data), as_is, rtol=0, atol=0)
    assert stack_weights(as_is, held_out_residuals(follows, data))[:, 0].tolist() == [1.0, 0.0]  # a tie: the first
    data.val_startup_s = 600.0
    assert_close(held_out_residuals(misses, data), as_is - 0.01, rtol=0, atol=1e-15)
    temp_c[3] = np.nan  # a glitch row in the window does not turn the rule off
    assert_close(held_out_residuals(misses, data), as_is - 0.01, rtol=0, atol=1e-15)
    deployed = [held_out_residuals(m, data) for m in (misses, follows)]
    assert stack_weights(*deployed)[:, 0].tolist() == [0.0, 1.0]
    temp_c[:60] = 58.0  # a hot soak: its first 600 s at the edge of the range stand for no deployment
    assert_close(held_out_residuals(misses, data), as_is, rtol=0, atol=0)
    temp_c[:60] = 25.0
    # a validation recording of its own: its residual less its own first 600 s (a held-out power-up), scored
    # after them (the offset makes the window's own blocks alike for every start)
    data.val_path, data.val_full = "other.csv", (time_s, x, y)
    missed, followed = (held_out_residuals(m, data) for m in (misses, follows))
    assert len(missed) == len(followed) == 90  # 6000 s of 60 s blocks, the first ten (the window) left out
    assert_close(missed, followed - 0.01, rtol=0, atol=1e-15)


def test_kmeans_members_average_fits_from_disjoint_seeds_and_report_the_spread():
    """``kmeans_members``: the k-means start is the mean of fits from other seeds; the spread is reported."""
    x, y, _ = _knee_data()
    data = _blocks(x, y)
    assert member_seeds(0, 3)[0] == 0 and not set(member_seeds(0, 3)) & set(member_seeds(1, 3))
    members = []
    for seed in member_seeds(5, 2):
        members.append(RBFNet(3, 3, 6, rbf_inputs=[0], linear=True, temp_degree=3, clamp=True))
        fit(members[-1], data, max_epochs=100, progress=False, seed=seed)
    ols = {i: RBFNet(3, 3, 6, rbf_inputs=[0], linear=True, temp_degree=3, clamp=True, center_init=i)
           for i in CENTER_INITS[1:]}
    for part in ols.values():
        fit(part, data, max_epochs=100, progress=False, seed=5)
    model = RBFNet(3, 3, 6, rbf_inputs=[0], linear=True, temp_degree=3, clamp=True, validate_init=True,
                   kmeans_members=2)
    metrics = fit(model, data, max_epochs=100, progress=False, seed=5)
    with torch.no_grad():
        average = 0.5 * (members[0](x) + members[1](x))
        parts = [average] + [ols[i](x) for i in CENTER_INITS[1:]]
        weights = np.array([[metrics[f"model/{i}_weight_{a}"] for a in "xyz"] for i in CENTER_INITS])
        assert_close(model(x), sum(torch.tensor(w) * p for w, p in zip(weights, parts)), rtol=0, atol=1e-12)
    assert metrics["val/fits_tried"] == 4
    tried = [validation_metrics(m, data) for m in members + list(ols.values())]
    for a in "xyz":
        values = [t[f"val/rmse_{a}_dps"] for t in tried]
        assert metrics[f"val/lowest_{a}_dps"] == pytest.approx(min(values))
        assert metrics[f"val/spread_{a}_pct"] == pytest.approx(100 * (max(values) / min(values) - 1))
    with pytest.raises(ValueError, match="kmeans_members"):
        RBFNet(3, 3, 6, kmeans_members=0)


def test_mix_into_refuses_fits_normalised_on_different_data():
    x, y, _ = _knee_data()
    parts = [RBFNet(3, 3, 4, rbf_inputs=[0], linear=True, temp_degree=3, clamp=True) for _ in range(2)]
    parts[0].init_from_data(x, y, torch.Generator().manual_seed(0))
    parts[1].init_from_data(x[::2], y[::2], torch.Generator().manual_seed(0))
    with pytest.raises(ValueError, match="normalise differently"):
        mix_into(RBFNet(3, 3, 4, rbf_inputs=[0]), parts, np.full((2, 3), 0.5))


def test_mix_into_is_exact_for_fits_with_different_output_scales():
    """A campaign's starts each subtract their own run offsets, so their output scales differ."""
    x, y, _ = _knee_data()
    parts = [RBFNet(3, 3, 4, rbf_inputs=[0], linear=True, temp_degree=3, clamp=True) for _ in range(2)]
    parts[0].init_from_data(x, y, torch.Generator().manual_seed(0))
    parts[1].init_from_data(x, 2 * y + 0.3, torch.Generator().manual_seed(1))
    weights = np.array([[0.25, 1.0, 0.0], [0.75, 0.0, 1.0]])
    model = RBFNet(3, 3, 4, rbf_inputs=[0], linear=True, temp_degree=3, clamp=True)
    mix_into(model, parts, weights)
    with torch.no_grad():
        expected = sum(torch.tensor(w) * p(x) for w, p in zip(weights, parts))
        assert_close(model(x), expected, rtol=0, atol=1e-12)


def test_training_keeps_ols_widths_at_or_above_the_narrowest_candidate():
    """``fit`` holds the floor: without it Adam narrows a Gaussian onto a step far sharper than any candidate."""
    x, y, _ = _knee_data(width_c=0.5)
    data = _blocks(x, y)
    narrowest = {}
    for floor in (False, True):
        model = RBFNet(3, 3, 6, rbf_inputs=[0], linear=True, temp_degree=3, clamp=True, center_init="ols")
        if not floor:
            model.keep_widths_ = lambda: None
        fit(model, data, max_epochs=300, patience=10_000, progress=False)
        with torch.no_grad():
            narrowest[floor] = float((model.widths() * model.x_std[0]).min())
    assert narrowest[False] < 0.9 * OLS_WIDTHS_C[0] <= narrowest[True] + 1e-9, narrowest
