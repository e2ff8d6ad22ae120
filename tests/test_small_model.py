"""The model on one row of floats (gyronet.model.small_model) equals the frozen TorchScript model, for every model kind."""
import numpy as np
import pytest
import torch

from gyronet.model.baselines import LinearFeatures, TempPolynomial
from gyronet.bundle.compensator import Compensator
from gyronet.model.rbf import RBFNet
from gyronet.model.px4 import Px4Cubic, Px4Onboard
from gyronet.model.small_model import row_model


def _features(n=400, seed=0):
    """Temperatures inside and far outside any trained box, rates both signs, T * dT/dt."""
    rng = np.random.default_rng(seed)
    temp_c = rng.uniform(-60.0, 120.0, n)
    rate = rng.normal(0.0, 0.05, n)
    return np.column_stack([temp_c, rate, temp_c * rate])


def _trained_rbf(**options):
    x = torch.from_numpy(_features(2000, seed=1)[:1000])
    x[:, 0] = x[:, 0].clamp(0.0, 50.0)  # a box narrower than the test inputs: the clamp is exercised
    y = torch.stack([0.01 * x[:, 0], -0.002 * x[:, 0] ** 2 / 50, x[:, 1]], 1)
    model = RBFNet(3, 3, **options)
    model.init_from_data(x, y, torch.Generator().manual_seed(0))
    with torch.no_grad():  # Adam would move the widths off their initial value: so does this
        model.raw_width.add_(torch.linspace(-0.3, 0.3, model.n_centers, dtype=torch.float64))
    return model


def _polynomial(cls, **options):
    model = cls(3, 3, **options)
    coef = np.array([[0.1, -0.2, 0.3], [1e-3, 2e-3, -3e-3], [1e-5, -2e-5, 3e-5], [1e-7, 2e-7, -1e-7],
                     [1e-9, -1e-9, 2e-9], [-1e-11, 1e-11, 3e-11]])[:model.degree + 1]
    if isinstance(model, (Px4Cubic, Px4Onboard)):
        model._set(5.0, 45.0, 25.0, coef)
    else:
        with torch.no_grad():
            model.coef.copy_(torch.from_numpy(coef))
            model.temp_ref_c.fill_(25.0), model.temp_min_c.fill_(5.0), model.temp_max_c.fill_(45.0)
    return model


def _linear():
    model = LinearFeatures(3, 3)
    with torch.no_grad():
        model.weight.copy_(torch.tensor([[1e-3, 2e-3, 3e-3], [0.5, -0.5, 0.2], [1e-2, 0.0, -1e-2]]))
        model.bias.copy_(torch.tensor([0.1, -0.1, 0.05]))
        model.x_mean.copy_(torch.tensor([25.0, 0.0, 0.0]))
    return model


KINDS = {
    "default": lambda: _trained_rbf(n_centers=12, rbf_inputs=[0], linear=True, temp_degree=3, clamp=True),
    "rbf": lambda: _trained_rbf(n_centers=32),
    "rbf_two_inputs_clamped": lambda: _trained_rbf(n_centers=6, rbf_inputs=[0, 1], linear=True, temp_degree=2,
                                                   clamp=True),
    "poly3": lambda: _polynomial(TempPolynomial, degree=3),
    "poly5": lambda: _polynomial(TempPolynomial, degree=5),
    "px4": lambda: _polynomial(Px4Cubic),
    "px4_onboard": lambda: _polynomial(Px4Onboard),
    "lsq": _linear,
}


@pytest.mark.parametrize("kind", sorted(KINDS))
def test_one_row_in_floats_equals_frozen_torchscript(kind):
    model = KINDS[kind]().eval()
    scripted = torch.jit.script(model)
    frozen = torch.jit.freeze(scripted)
    x = _features()
    with torch.no_grad():
        expected = frozen(torch.from_numpy(x)).numpy()
    for source in (scripted, model):  # the unfrozen TorchScript a bundle holds, and the eager module
        one = row_model(source)
        got = np.array([one(row) for row in x.tolist()])
        np.testing.assert_allclose(got, expected, rtol=1e-12, atol=1e-12 * np.abs(expected).max())
    assert row_model(frozen) is None  # its parameters are folded into constants: TorchScript it stays


def test_an_unknown_model_class_keeps_torchscript():
    assert row_model(torch.jit.script(torch.nn.Linear(3, 3, dtype=torch.float64))) is None


def test_compensate_keeps_torchscript_and_the_live_path_matches_it(bundle, cycle_csv):
    """Offline (no ``use_small_chunks``) is TorchScript's to the bit; live one-row calls agree to 1e-12."""
    from gyronet.recordings.data import load_recording

    recording = load_recording(cycle_csv).slice(slice(0, 300))
    offline, live, rows = Compensator.load(bundle), Compensator.load(bundle), Compensator.load(bundle)
    assert live.use_small_chunks() and rows.use_small_chunks()
    features = torch.from_numpy(offline.extractor.process(recording.columns))
    offline.extractor.reset()
    with torch.no_grad():
        torchscript = offline.model(features).numpy()
    np.testing.assert_array_equal(offline.process(recording.columns).drift_dps, torchscript)
    ones = [live.process({c: recording.columns[c][i:i + 1] for c in live.input_columns}) for i in range(300)]
    np.testing.assert_allclose(np.vstack([o.drift_dps for o in ones]), torchscript, rtol=0, atol=1e-12)
    by_row = [rows.process_row(float(recording.time_s[i]), {c: float(recording.columns[c][i])
                                                            for c in rows.input_columns}) for i in range(300)]
    np.testing.assert_array_equal(np.array([r.rate_dps for r in by_row]), np.vstack([o.rate_dps for o in ones]))
    assert rows.n_out_of_range == live.n_out_of_range and rows.n_bad_input == live.n_bad_input
