"""A thermal lag per axis (gyronet.training.axis_lag): lagged features, the network reading them per axis, the screen."""
import logging

import numpy as np
import pytest
import torch

from gyronet.model.features import PAPER_FEATURES, FeatureExtractor
from gyronet.model.filters import LaggedRate
from gyronet.model.rbf import RBFNet
from gyronet.model.small_model import row_model
from gyronet.sim.sensor import first_order_lag
from gyronet.training.axis_lag import choose_inputs, choose_lags, lagged_specs, screen_errors, with_axis_lags

from conftest import CATS_RUNS, needs_cats

SPECS = [*PAPER_FEATURES, *lagged_specs(20.0, 5.0)]


def _temperature(n: int = 30000, fs_hz: float = 10.0):
    """Quantised ramps and holds, as a die sensor reports them."""
    time_s = np.arange(n) / fs_hz
    temp_c = 25.0 + 8.0 * np.sin(time_s / 400.0) + np.where(time_s > 1500.0, 3.0, 0.0) * np.tanh((time_s - 1500) / 60)
    return time_s, np.round(temp_c * 16.0) / 16.0


def _lossy_temperature():
    """``_temperature`` with a bridged gap, a restarting one and a rate that doubles."""
    time_s, temp_c = _temperature(12000)
    keep = np.ones(len(time_s), dtype=bool)
    keep[3000:3004] = keep[5000:5400] = False  # bridged, and restarted
    time_s, temp_c = time_s[keep], temp_c[keep]
    time_s[time_s > 900.0] = 900.0 + (time_s[time_s > 900.0] - 900.0) * 0.5  # the rate doubles
    return time_s, temp_c


def test_lagged_rate_is_the_rate_of_the_lagged_temperature():
    time_s, temp_c = _temperature()
    got = FeatureExtractor(SPECS, 10.0).process({"time_s": time_s, "temp_c": temp_c})
    lagged = first_order_lag(temp_c, 10.0, 20.0)
    want = FeatureExtractor(PAPER_FEATURES, 10.0).process({"time_s": time_s, "temp_c": lagged})
    settled = time_s > 200.0  # both start settled, at different states
    np.testing.assert_allclose(got[settled, 3], lagged[settled], atol=1e-9)
    np.testing.assert_allclose(got[settled, 4], want[settled, 1], atol=1e-9)
    np.testing.assert_allclose(got[settled, 5], lagged[settled] * want[settled, 1], atol=1e-7)


def test_lagged_features_are_the_same_in_one_block_in_chunks_and_row_by_row_across_gaps_and_a_rate_change():
    time_s, temp_c = _lossy_temperature()
    columns = {"time_s": time_s, "temp_c": temp_c}
    whole = FeatureExtractor(SPECS, 10.0).process(columns)
    extractor = FeatureExtractor(SPECS, 10.0)
    chunks = np.concatenate([extractor.process({k: v[i:i + 997] for k, v in columns.items()})
                             for i in range(0, len(time_s), 997)])
    extractor.reset()
    rows = np.array([extractor.process_row(t, {"temp_c": v})[0] for t, v in zip(time_s, temp_c)])
    assert np.isfinite(whole).all() and extractor.rate_changes
    np.testing.assert_allclose(chunks, whole, rtol=0, atol=1e-12)
    np.testing.assert_allclose(rows, whole, rtol=0, atol=1e-12)


def test_a_lagged_rate_reads_the_unlagged_tracker_and_gives_the_numbers_of_its_own():
    time_s, temp_c = _lossy_temperature()
    temp_c[7000] = 150.0  # a glitch, rejected
    columns = {"time_s": time_s, "temp_c": temp_c}
    shared = FeatureExtractor(SPECS, 10.0)
    trackers = {id(f.tracker if isinstance(f, LaggedRate) else f) for i, f in shared._filters.items()
                if SPECS[i]["kind"] == "rate"}
    assert len(trackers) == 1
    own = FeatureExtractor([SPECS[4]], 10.0)  # the lagged rate alone runs its own tracker
    assert not own._filters[0].shared
    whole = shared.process(columns)
    assert shared.rate_changes and shared.n_rejected
    np.testing.assert_array_equal(whole[:, 4], own.process(columns)[:, 0])
    shared.reset()
    own.reset()
    rows = [shared.process_row(t, {"temp_c": v})[0][4] for t, v in zip(time_s, temp_c)]
    np.testing.assert_array_equal(rows, [own.process_row(t, {"temp_c": v})[0][0] for t, v in zip(time_s, temp_c)])


def _grouped(n_inputs: int = 6):
    """A default-like network whose y reads columns 3-5 in its first three slots."""
    rng = np.random.default_rng(0)
    x = torch.from_numpy(np.column_stack([rng.uniform(-20, 50, 800), rng.normal(0, 0.02, (800, n_inputs - 1))]))
    x[:, 3] = x[:, 0] + torch.from_numpy(rng.normal(0, 0.5, 800))
    y = torch.stack([0.01 * x[:, 0], torch.tanh(x[:, 3] / 5.0), x[:, 1]], 1)
    columns = [list(range(n_inputs)), [3, 4, 5, 3, 4, 5], list(range(n_inputs))]
    net = RBFNet(n_inputs, 3, 6, rbf_inputs=[0], linear=True, temp_degree=3, clamp=True, axis_columns=columns)
    net.init_from_data(x, y, torch.Generator().manual_seed(0))
    return net, x, y, columns


def _in_box(net, x):
    """Rows whose column 3 (y's temperature) lies within slot 0's box (column 0's range)."""
    low, high = (net.x_mean[0] + net.x_std[0] * bound for bound in (net.z_low[0], net.z_high[0]))
    return (x[:, 3] >= low) & (x[:, 3] <= high)


def test_each_axis_is_the_network_on_its_own_columns():
    net, x, y, columns = _grouped()
    plain = RBFNet(6, 3, 6, rbf_inputs=[0], linear=True, temp_degree=3, clamp=True)
    plain.load_state_dict({k: v for k, v in net.state_dict().items() if k not in ("group_columns", "axis_group")},
                          strict=False)
    with torch.no_grad():
        out = net(x)
        inside = _in_box(net, x)  # y's temperature (column 3) within its slot's box: its copy not clamped
        for a, cols in enumerate(columns):
            torch.testing.assert_close(out[inside, a], plain(x[:, cols])[inside, a], rtol=0, atol=0)
        torch.testing.assert_close(net.on_fixed_input(x)(), out, rtol=0, atol=0)
        scripted = torch.jit.script(net.eval())
        torch.testing.assert_close(torch.jit.freeze(scripted)(x), out, rtol=0, atol=0)
    one = row_model(scripted)
    got = np.array([one(row) for row in x.numpy().tolist()])
    np.testing.assert_allclose(got, out.numpy(), rtol=1e-12, atol=1e-12)
    # the head's least squares is each group's own: y's row is what a refit on y's columns gives
    x, y = x[inside], y[inside]
    net.refit_head(x, y)
    plain.refit_head(x[:, columns[1]], y)
    with torch.no_grad():
        torch.testing.assert_close(net(x)[:, 1], plain(x[:, columns[1]])[:, 1], rtol=1e-9, atol=1e-12)


def test_a_slot_holding_a_copy_of_the_temperature_holds_its_edge_value_too():
    """y reads column 3 in slot 0 (clamped) and again in slot 3: beyond the box both hold, in every implementation."""
    net, x, y, columns = _grouped()
    with torch.no_grad():
        net.linear.weight.normal_(generator=torch.Generator().manual_seed(1))  # weight on both copies
    edge_c = float(net.x_mean[0] + net.z_high[0] * net.x_std[0])  # slot 0's box: column 0's range
    steady = torch.zeros(4, 6, dtype=torch.float64)
    steady[:, 3] = torch.tensor([edge_c, edge_c + 5.0, edge_c + 50.0, edge_c + 500.0])
    scripted = torch.jit.script(net.eval())
    one = row_model(scripted)
    with torch.no_grad():
        for drift in (net(steady)[:, 1], scripted(steady)[:, 1], torch.tensor([one(r)[1] for r in steady.tolist()])):
            torch.testing.assert_close(drift, drift[:1].expand(4), rtol=0, atol=1e-12)
        inside = x[_in_box(net, x)]  # inside the box nothing moves: the copies' shift is exactly zero
        plain = RBFNet(6, 3, 6, rbf_inputs=[0], linear=True, temp_degree=3, clamp=True)
        plain.load_state_dict({k: v for k, v in net.state_dict().items() if k not in ("group_columns", "axis_group")},
                              strict=False)
        torch.testing.assert_close(net(inside)[:, 1], plain(inside[:, columns[1]])[:, 1], rtol=0, atol=0)
        assert net.to("meta")(steady.to("meta")).shape == (4, 3)  # the mask is made where the inputs are


def test_axis_columns_are_checked():
    with pytest.raises(ValueError, match="axis_columns"):
        RBFNet(3, 3, 4, axis_columns=[[0, 1, 2], [0, 1]])


@pytest.fixture(scope="module")
def lagged_sensor_csv(tmp_path_factory):
    """A simulated sensor whose y axis sees the die 25 s late, x and z at once (no cross-axis coupling)."""
    from gyronet.sim.core import simulate, write_simulation

    sim = simulate(profile="cycle", fs_hz=2.0, seed=1, sensor_seed=3,
                   sensor={"axis_lag_s": [0.0, 25.0, 0.0]})
    path = tmp_path_factory.mktemp("axis_lag") / "cycle.csv"
    write_simulation(sim, path)
    return path


def test_the_screen_finds_the_lagged_axis_and_leaves_the_others(lagged_sensor_csv):
    from gyronet.training.dataset import DriftData

    data = DriftData(str(lagged_sensor_csv))
    lags = [5.0, 10.0, 20.0, 30.0, 60.0]
    errors = screen_errors(data, lags)
    chosen = choose_lags(errors, lags)
    assert chosen[0] == 0.0 and chosen[2] == 0.0, (chosen, errors)
    assert chosen[1] in (20.0, 30.0), (chosen, errors)
    # 10 s means hold the noise too: the lag's share of them is a few per cent
    assert errors[0, 1] > 1.04 * errors[1:, 1].min() and errors[0, [0, 2]].min() > 0

    made = []
    model = RBFNet(data.n_features, 3, 4, rbf_inputs=[0], linear=True, temp_degree=3, clamp=True, axis_lags_s=lags)
    lagged_data, lagged_model = with_axis_lags(data, lambda n, cols: made.append(cols) or RBFNet(
        n, 3, 4, rbf_inputs=[0], linear=True, temp_degree=3, clamp=True, axis_columns=cols), model)
    assert [s.get("lag_s", s.get("tau_s")) for s in lagged_data.features[3:]] == [chosen[1]] * 3
    assert made == [[[0, 1, 2, 0, 1, 2], [3, 4, 5, 3, 4, 5], [0, 1, 2, 0, 1, 2]]]
    assert lagged_model.lag_by_axis_s == chosen
    plain = RBFNet(data.n_features, 3, 4)  # without candidates nothing changes
    assert with_axis_lags(data, None, plain) == (data, plain)


def test_the_lagged_copy_of_the_data_does_not_say_the_data_s_lines_again(lagged_sensor_csv, caplog):
    from gyronet.training.axis_lag import with_features
    from gyronet.training.dataset import DriftData

    with caplog.at_level("DEBUG", logger="gyronet.training.dataset"):  # a child with its own level (hydra.verbose)
        data = DriftData(str(lagged_sensor_csv))
        wide = with_features(data, SPECS)
    assert wide.n_features == len(SPECS) and len(wide.train) == len(data.train)
    assert sum("training data" in r.getMessage() for r in caplog.records) == 1
    assert logging.root.manager.disable == logging.NOTSET  # put back


def test_the_rate_only_control_tells_a_thermal_lag_from_a_smoother_rate(lagged_sensor_csv):
    """y's drawn lag shifts its bias curve: lagging the temperature too must beat lagging dT/dt alone."""
    from gyronet.training.dataset import DriftData

    data = DriftData(str(lagged_sensor_csv))
    lags = [5.0, 10.0, 20.0, 30.0, 60.0]
    errors = screen_errors(data, lags, rate_only=True)
    assert errors.shape == (1 + 2 * len(lags), 3)
    assert np.array_equal(errors[:1 + len(lags)], screen_errors(data, lags))  # the choice's rows are the same
    best = 1 + int(np.argmin(errors[1:1 + len(lags), 1]))
    full_gain, rate_only_gain = errors[0, 1] - errors[best, 1], errors[0, 1] - errors[best + len(lags), 1]
    # at 2 Hz a smoother dT/dt earns part of the gain too (the real tag's 60 s is all of that kind)
    assert full_gain > 1.3 * rate_only_gain > 0, errors[:, 1]


def test_several_runs_are_screened_together_with_a_constant_per_run(lagged_sensor_csv, tmp_path):
    from gyronet.sim.core import simulate, write_simulation
    from gyronet.training.runs import RunsData, training_data

    second = tmp_path / "random.csv"
    write_simulation(simulate(profile="random", fs_hz=2.0, seed=2, sensor_seed=3, duration_s=6 * 3600.0,
                              sensor={"axis_lag_s": [0.0, 25.0, 0.0]}), second)
    data = training_data(paths=[str(lagged_sensor_csv), str(second)], run_offsets=True)
    lags = [5.0, 10.0, 20.0, 30.0, 60.0]
    chosen = choose_lags(screen_errors(data, lags), lags)
    assert chosen[0] == 0.0 and chosen[2] == 0.0 and chosen[1] in (20.0, 30.0), chosen
    model = RBFNet(data.n_features, 3, 4, rbf_inputs=[0], linear=True, temp_degree=3, clamp=True, axis_lags_s=lags)
    lagged, _ = with_axis_lags(data, lambda n, cols: RBFNet(n, 3, 4, axis_columns=cols), model)
    assert isinstance(lagged, RunsData) and lagged.n_runs == 2 and lagged.run_offsets
    assert lagged.n_features == 6 and lagged.train.x.shape[1] == 6 and len(lagged.train) == len(data.train)


def test_an_axis_gets_only_its_rate_lagged_where_the_temperature_lag_earns_nothing_more():
    lags = [10.0, 60.0]
    # rows: none, full 10 s, full 60 s, rate-only 10 s, rate-only 60 s; columns x, y, z
    errors = np.array([[1.00, 1.00, 1.00],
                       [0.97, 0.90, 0.99],
                       [0.95, 0.80, 0.995],
                       [0.99, 0.95, 0.985],
                       [0.93, 0.85, 0.99]])
    assert choose_inputs(errors, lags) == [(60.0, True), (60.0, False), (0.0, False)]
    assert choose_lags(errors[:3], lags) == [60.0, 60.0, 0.0]  # the temperature-lag-only choice as before


def test_a_rate_only_axis_reads_the_reported_temperature_and_the_lagged_rate(lagged_sensor_csv, monkeypatch):
    from gyronet.training import axis_lag
    from gyronet.training.dataset import DriftData

    data = DriftData(str(lagged_sensor_csv))
    lags = [20.0, 30.0]
    monkeypatch.setattr(axis_lag, "choose_inputs", lambda errors, lags_s: [(30.0, True), (20.0, False), (0.0, False)])
    made = []
    model = RBFNet(data.n_features, 3, 4, rbf_inputs=[0], linear=True, axis_lags_s=lags)
    lagged_data, lagged_model = with_axis_lags(data, lambda n, cols: made.append(cols) or RBFNet(
        n, 3, 4, rbf_inputs=[0], linear=True, axis_columns=cols), model)
    # features: paper 0-2, 20 s lag 3-5, 30 s lag 6-8; x keeps temperature 0 with the 30 s rate and product
    assert made == [[[0, 7, 8, 0, 7, 8, 0, 7, 8], [3, 4, 5, 3, 4, 5, 3, 4, 5], [0, 1, 2, 0, 1, 2, 0, 1, 2]]]
    assert lagged_model.lag_by_axis_s == [30.0, 20.0, 0.0] and lagged_model.rate_lag_only_by_axis == [True, False, False]
    assert lagged_data.n_features == 9


def test_a_campaign_deployed_with_a_start_up_offset_is_screened_run_by_run(lagged_sensor_csv, tmp_path):
    """data.val_startup_s: each run held out whole and scored as the offset leaves it; a real lag still shows."""
    from gyronet.sim.core import simulate, write_simulation
    from gyronet.training.runs import training_data

    second = tmp_path / "random.csv"
    write_simulation(simulate(profile="random", fs_hz=2.0, seed=2, sensor_seed=3, duration_s=6 * 3600.0,
                              sensor={"axis_lag_s": [0.0, 25.0, 0.0]}), second)
    paths = [str(lagged_sensor_csv), str(second)]
    lags = [5.0, 10.0, 20.0, 30.0, 60.0]
    deployed = screen_errors(training_data(paths=paths, run_offsets=True, val_startup_s=600.0), lags)
    assert not np.allclose(deployed, screen_errors(training_data(paths=paths, run_offsets=True), lags))
    chosen = choose_lags(deployed, lags)
    assert chosen[0] == 0.0 and chosen[2] == 0.0 and chosen[1] in (20.0, 30.0), (chosen, deployed)


@needs_cats
def test_the_real_tags_y_lag_does_not_survive_the_start_up_window():
    """Within its runs the tag's y prefers dT/dt a minute late; held out as deployed, the lag costs it."""
    from gyronet.training.runs import training_data

    lags = [5.0, 10.0, 20.0, 30.0, 60.0]
    paths = [str(p) for p in CATS_RUNS]
    within = choose_inputs(screen_errors(training_data(paths=paths, run_offsets=True), lags, rate_only=True), lags)
    deployed = screen_errors(training_data(paths=paths, run_offsets=True, val_startup_s=600.0), lags, rate_only=True)
    assert within[1][0] == 60.0, within
    assert choose_inputs(deployed, lags)[1] == (0.0, False), deployed[:, 1]
    assert deployed[0, 1] < 0.95 * deployed[1:, 1].min()  # every lag of y is worse on the next run, by 5 % or more
