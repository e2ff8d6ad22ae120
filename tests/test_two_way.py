"""The record's thermal history decides the starts' widths: narrower only where it heats and cools through."""
from types import SimpleNamespace

import numpy as np
import pytest

from gyronet.model.rbf import RBFNet
from gyronet.training import two_way
from gyronet.training.two_way import two_way_share

FS_HZ = 0.1  # 10 s blocks, as training sees the record


def ramp(*knots_c: float, rate_c_per_min: float = 1.0, dwell_s: float = 1800.0) -> tuple[np.ndarray, np.ndarray]:
    """Time and temperature through ``knots_c`` at ``rate_c_per_min``, a dwell at each knot."""
    temps = [np.full(int(dwell_s * FS_HZ), knots_c[0])]
    for start, stop in zip(knots_c[:-1], knots_c[1:]):
        n = int(abs(stop - start) / rate_c_per_min * 60 * FS_HZ)
        temps += [np.linspace(start, stop, n), np.full(int(dwell_s * FS_HZ), stop)]
    temp_c = np.concatenate(temps)
    return np.arange(len(temp_c)) / FS_HZ, temp_c


def test_a_cooling_staircase_is_one_way_and_a_cycle_two_way():
    assert two_way_share(*ramp(60, 40, 20, 0, -20, -40)) < 0.05
    assert two_way_share(*ramp(25, -40, 60, 25)) > 0.95
    # heating over the top half only: about half the degC bins both ways
    assert two_way_share(*ramp(60, -40, 10)) == pytest.approx(0.5, abs=0.05)


def test_a_campaign_counts_rates_within_runs_and_degrees_across_them():
    cooling, heating = ramp(60, -40), ramp(-40, 60)  # both runs start at time 0
    time_s, temp_c = (np.concatenate(pair) for pair in zip(cooling, heating))
    run = np.repeat([0, 1], [len(cooling[0]), len(heating[0])])
    assert two_way_share(time_s, temp_c, run) > 0.95
    assert two_way_share(*cooling) < 0.05 and two_way_share(*heating) < 0.05
    assert two_way_share(time_s, temp_c) < 0.5  # as one record the runs' samples would share time blocks


def test_dwells_and_gaps_are_neither_heating_nor_cooling():
    time_s, temp_c = ramp(20, 20.5, rate_c_per_min=0.05)  # slower than a ramp: a drifting dwell
    assert two_way_share(time_s, temp_c) == 0.0
    # a held-out span cut out of a cycle: no rate is taken across the gap
    time_s, temp_c = ramp(25, -40, 60, 25)
    keep = (time_s < 20_000) | (time_s > 30_000)
    assert two_way_share(time_s[keep], temp_c[keep]) > 0.5
    assert two_way_share(time_s[:1], temp_c[:1]) == 0.0
    nan_c = temp_c.copy()
    nan_c[::7] = np.nan
    assert two_way_share(time_s, nan_c) == pytest.approx(two_way_share(time_s, temp_c), abs=0.05)


@pytest.mark.parametrize("knots, expected", [((25, -40, 60, 25), 0.5), ((60, 20, -40), 1.0)])
def test_apply_sets_the_width_of_the_starts(knots, expected):
    time_s, temp_c = ramp(*knots)
    data = SimpleNamespace(train=SimpleNamespace(time_s=time_s, x=np.column_stack([temp_c, np.zeros_like(temp_c)])))
    model = RBFNet(2, n_centers=4, width_init=1.0, two_way_width_init=0.5)
    two_way.apply(model, data)
    assert model.width_init == expected
    plain = RBFNet(2, n_centers=4, width_init=1.0)  # no two_way_width_init: the record does not matter
    two_way.apply(plain, data)
    assert plain.width_init == 1.0
