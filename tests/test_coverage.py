"""The record's seconds per degC: what train.py says about where a record is too thin."""
from types import SimpleNamespace

import numpy as np
import pytest

from gyronet.training import coverage


def test_seconds_per_degc_adds_the_passes_and_the_runs_and_skips_nan():
    # 0 -> 10 degC at 1 degC/min, back at 0.5 degC/min: 60 + 120 s in every degC, sampled at 10 Hz
    up = np.linspace(0.0, 10.0, 6000, endpoint=False)
    down = np.linspace(10.0, 0.0, 12000, endpoint=False)
    temp_c = np.concatenate([up, down])
    time_s = np.arange(len(temp_c)) * 0.1
    edges, seconds = coverage.seconds_per_degc([(time_s, temp_c)], 0.0, 10.0)
    np.testing.assert_array_equal(edges, np.arange(10.0))
    np.testing.assert_allclose(seconds, 180.0, atol=0.2)
    with_nan = temp_c.copy()
    with_nan[:600] = np.nan  # the first degC of the way up lost
    _, seconds = coverage.seconds_per_degc([(time_s, with_nan), (time_s, temp_c)], 0.0, 10.0)
    np.testing.assert_allclose(seconds, [300.0] + [360.0] * 9, atol=0.4)


def test_only_whole_bins_inside_the_trained_range_count():
    time_s = np.arange(1000.0)
    edges, _ = coverage.seconds_per_degc([(time_s, np.linspace(4.3, 9.8, 1000))], 4.3, 9.8)
    np.testing.assert_array_equal(edges, [5.0, 6.0, 7.0, 8.0])


@pytest.mark.parametrize("seconds, warns", [(128.0, True), (900.0, False)])
def test_the_thinnest_degc_is_named_and_a_thin_record_is_told_what_helps(seconds, warns):
    temp_c = np.concatenate([np.full(int(seconds), 20.5), np.full(5000, 21.5), np.full(5000, 22.5)])
    data = SimpleNamespace(recording=SimpleNamespace(time_s=np.arange(len(temp_c), dtype=float), temp_c=temp_c),
                           temp_range_c=(20.0, 23.0))
    figures = coverage.thinnest(data)
    assert figures == {"data/min_s_per_degc": seconds, "data/thinnest_c": 20.0}
    line = coverage.describe({**figures, "val/rmse_dps": 0.01})
    assert line.startswith(f"record: {seconds:.0f} s per degC at the least (20..21 degC)")
    assert ("a second cycle helps" in line) == warns
    assert coverage.describe({"val/rmse_dps": 0.01}) is None
