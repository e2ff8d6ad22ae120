"""The vectorised CSV writer: every finite float64 comes back to 1e-12 relative; atomic output."""
import errno
import os
import sys

import numpy as np
import pytest
from hypothesis import given, strategies as st

from gyronet.atomic import OutputError, atomic_output
from gyronet.errors import GyronetError
from gyronet.recordings.fastcsv import format_rows, write_csv

# any finite float64: zeros, subnormals, 1e-300 .. 1e300, negatives
FINITE = st.floats(allow_nan=False, allow_infinity=False, allow_subnormal=True, width=64)
MIXED = st.one_of(FINITE, st.floats(-1e3, 1e3), st.sampled_from([0.0, -0.0, 5e-324, -2.2250738585072014e-308,
                                                                  1.7976931348623157e308, 0.0418, 1.5e6, 2e19]),
                  st.builds(lambda m, e: m * 10.0**e, st.floats(-10, 10), st.integers(-300, 300)))


def _parse(rows: bytes, n_columns: int) -> np.ndarray:
    lines = rows.decode("ascii").splitlines()
    cells = [line.split(",") for line in lines]
    assert all(len(c) == n_columns for c in cells)
    return np.array([[float(x) for x in c] for c in cells]).reshape(len(lines), n_columns)


def _assert_round_trip(columns: dict, significant: int, rel: float) -> None:
    values = np.column_stack(list(columns.values()))
    back = _parse(format_rows(columns, significant), len(columns))
    assert np.isfinite(back).all()
    # above the largest float64 rounded down to `significant` digits, rounding up would read back as inf:
    # the writer rounds down there (less than one unit of the last digit, not half a unit)
    unit = 10 ** (sys.float_info.max_10_exp - significant + 1)
    near_max = np.abs(values) > float(int(sys.float_info.max) // unit * unit)
    relative = np.abs(back - values) / np.maximum(np.abs(values), 5e-324)
    bad = relative > rel * np.where(near_max, 2.0, 1.0)
    assert not bad.any(), (values[bad], back[bad])


@given(st.lists(st.tuples(MIXED, MIXED, MIXED), min_size=1, max_size=60))
def test_any_finite_float64_round_trips_to_1e12_relative(rows):
    columns = {name: np.array([r[i] for r in rows]) for i, name in enumerate("abc")}
    _assert_round_trip(columns, 13, 1e-12)


@given(st.lists(MIXED, min_size=1, max_size=60), st.integers(1, 15))
def test_every_value_keeps_its_significant_digits(values, significant):
    _assert_round_trip({"a": np.array(values)}, significant, 0.5 * 10.0**(1 - significant) * (1 + 1e-9) + 1e-15)


def test_one_large_value_does_not_round_its_column():
    """Issue 10 item 3: 1.5e6 made 0.0418 a 0, and 2e19 overflowed int64."""
    column = np.array([0.0418, 1.5e6, -0.0418, 2e19, 1e-7])
    back = _parse(format_rows({"a": column}, 12), 1)[:, 0]
    np.testing.assert_allclose(back, column, rtol=5e-12, atol=0)
    assert b"90776627963145224192" not in format_rows({"a": column}, 12)


def test_ordinary_columns_stay_fixed_point():
    rows = format_rows({"time_s": np.arange(4) / 10.0, "temp_c": np.array([20.0, 20.5, 21.25, 12.0])}, 9)
    assert rows == b"0,20\n0.1,20.5\n0.2,21.25\n0.3,12\n"


def test_values_off_the_column_layout_are_written_as_g():
    column = np.array([2e19, 0.0418, -1.5e6, 1e-5, -1.2345e-6, 1.7976931348623157e308, 5e-324, 0.0])
    expected = [f"{v:.3g}".replace("e+0", "e+").replace("e-0", "e-") for v in column]
    expected[5] = "1.79e+308"  # %.3g gives 1.8e+308, which reads back as inf
    assert format_rows({"a": column}, 3).decode().splitlines() == expected


def test_write_csv_leaves_no_half_file_on_a_full_disk(tmp_path, monkeypatch):
    path = tmp_path / "out.csv"
    path.write_text("old\n")
    real_open = open

    class FullDisk:
        def __init__(self, handle):
            self.handle, self.written = handle, 0

        def write(self, data):
            if self.written:
                raise OSError(errno.ENOSPC, "No space left on device")
            self.written += self.handle.write(data[: len(data) // 2] if len(data) > 100 else data)
            return len(data)

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.handle.close()

    monkeypatch.setattr("builtins.open", lambda *a, **k: FullDisk(real_open(*a, **k)))
    with pytest.raises(OutputError) as info:
        write_csv(path, {"a": np.arange(1000.0)})
    monkeypatch.undo()
    message = str(info.value)
    assert isinstance(info.value, GyronetError) and "\n" not in message
    assert str(path) in message and "no space left" in message
    assert path.read_text() == "old\n"  # the previous file is untouched
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.csv"]  # and no temporary file is left


def test_atomic_output_keeps_other_errors_and_cleans_up(tmp_path):
    with pytest.raises(ZeroDivisionError):
        with atomic_output(tmp_path / "x.csv") as tmp:
            tmp.write_text("half")
            1 / 0
    assert list(tmp_path.iterdir()) == []
    with atomic_output(tmp_path / "sub" / "y.csv") as tmp:
        tmp.write_text("whole\n")
    assert (tmp_path / "sub" / "y.csv").read_text() == "whole\n"
    assert [p.name for p in (tmp_path / "sub").iterdir()] == ["y.csv"]
    umask = os.umask(0)
    os.umask(umask)
    assert (tmp_path / "sub" / "y.csv").stat().st_mode & 0o777 == 0o666 & ~umask  # not mkstemp's 0600


def test_output_onto_a_folder_or_under_a_file_is_one_line(tmp_path):
    (tmp_path / "folder").mkdir()
    (tmp_path / "file").write_text("x")
    for target, reason in ((tmp_path / "folder", "it is a folder"), (tmp_path / "file" / "o.csv", "is a file")):
        with pytest.raises(OutputError, match=reason) as info:
            write_csv(target, {"a": np.arange(3.0)})
        assert "\n" not in str(info.value) and str(target) in str(info.value)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file", "folder"] and not any((tmp_path / "folder").iterdir())
