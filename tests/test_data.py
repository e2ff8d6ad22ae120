"""Recordings: round trip, auxiliary columns kept, every malformed file refused with one clear line."""
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from gyronet.data import (GYRO_COLUMNS, block_means, load_recording, split_by_time, truth_path,
                          write_recording)
from gyronet.errors import RecordingError

ROOT = Path(__file__).resolve().parents[1]
HEADER = "time_s,temp_c,gyro_x_dps,gyro_y_dps,gyro_z_dps"


def _columns(n=50):
    rng = np.random.default_rng(0)
    cols = {"time_s": np.arange(n) / 10, "temp_c": 20 + rng.normal(size=n)}
    cols.update({c: rng.normal(size=n) for c in GYRO_COLUMNS})
    cols["vdd_v"] = 3.3 + 0.01 * rng.normal(size=n)
    return cols


def test_round_trip_keeps_aux_columns_and_metadata(tmp_path):
    cols = _columns()
    path = write_recording(tmp_path / "r.csv", cols, {"fs_hz": 10, "sensor": "LPMS-USBAL2"})
    rec = load_recording(path)
    assert rec.meta == {"fs_hz": "10", "sensor": "LPMS-USBAL2"}
    assert rec.aux_columns == ["vdd_v"]
    assert rec.fs_hz == 10.0
    for name, values in cols.items():
        np.testing.assert_allclose(rec.columns[name], values, rtol=1e-8)
    assert rec.gyro_dps.shape == (50, 3)


def test_column_order_is_free(tmp_path):
    path = tmp_path / "r.csv"
    path.write_text("gyro_z_dps,temp_c,time_s,gyro_y_dps,gyro_x_dps\n1,20,0,2,3\n4,21,0.1,5,6\n")
    rec = load_recording(path)
    np.testing.assert_array_equal(rec.gyro_dps, [[3, 2, 1], [6, 5, 4]])


BAD_FILES = {
    "missing_column": ("time_s,temp_c,gyro_x_dps,gyro_y_dps\n0,1,2,3\n", "missing required column(s) gyro_z_dps"),
    "non_numeric": (f"{HEADER}\n0,20,1,2,3\n0.1,20,abc,2,3\n", "line 3: column 'gyro_x_dps': non-numeric value 'abc'"),
    "nan": (f"{HEADER}\n0,20,1,2,3\n0.1,nan,1,2,3\n", "line 3: column 'temp_c': empty cell or NaN"),
    "empty_cell": (f"{HEADER}\n0,20,1,2,3\n0.1,20,1,,3\n", "line 3: column 'gyro_y_dps': empty cell or NaN"),
    "inf": (f"{HEADER}\n0,20,1,2,3\n0.1,20,1,2,inf\n", "line 3: column 'gyro_z_dps': infinite value"),
    "time_backwards": (f"{HEADER}\n0,20,1,2,3\n0.2,20,1,2,3\n0.1,20,1,2,3\n", "line 4: time_s 0.1 does not increase"),
    "time_repeated": (f"# fs_hz=10\n{HEADER}\n0,20,1,2,3\n0,20,1,2,3\n", "line 4: time_s 0.0 does not increase"),
    "empty": ("", "empty file"),
    "header_only": (f"{HEADER}\n", "no samples after the header"),
    "too_many_fields": (f"{HEADER}\n0,20,1,2,3\n0.1,20,1,2,3,4\n", "malformed row"),
    "not_csv": ("\x89PNG\r\n\x1a\n\x00\x00\x00\rIHDR", "not a CSV"),
    "not_text": (b"\xff\xfe\xfa\xfb garbage".decode("latin-1"), "not a CSV"),
    "duplicate": ("time_s,temp_c,gyro_x_dps,gyro_y_dps,gyro_z_dps,temp_c\n0,1,2,3,4,5\n", "duplicate column 'temp_c'"),
}


@pytest.mark.parametrize("name", sorted(BAD_FILES))
def test_malformed_files_get_one_clear_line(tmp_path, name):
    text, expected = BAD_FILES[name]
    path = tmp_path / f"{name}.csv"
    path.write_bytes(text.encode("latin-1") if name == "not_text" else text.encode())
    with pytest.raises(RecordingError) as err:
        load_recording(path)
    message = str(err.value)
    assert str(path) in message and expected in message
    assert "\n" not in message


def test_missing_file(tmp_path):
    with pytest.raises(RecordingError, match="no such file"):
        load_recording(tmp_path / "nope.csv")


def test_script_refuses_bad_file_without_traceback(tmp_path):
    path = tmp_path / "bad.csv"
    path.write_text(f"{HEADER}\n0,20,1,2,3\n0.1,20,x,2,3\n")
    proc = subprocess.run([sys.executable, "scripts/compensate.py", f"model={tmp_path}", f"input={path}",
                           f"output={tmp_path / 'o.csv'}", f"hydra.run.dir={tmp_path / 'hydra'}"], cwd=ROOT,
                          capture_output=True, text=True)
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
    assert proc.stderr.strip().count("\n") == 0 and proc.stderr.startswith("error: ")


def test_split_is_by_time_block():
    time_s = np.arange(0, 1000, 0.1)
    train, val = split_by_time(time_s, val_fraction=0.2, n_blocks=10)
    assert abs(val.mean() - 0.2) < 0.01
    edges = np.flatnonzero(np.diff(val.astype(int)))
    assert len(edges) <= 4  # two contiguous held-out spans, not scattered samples


def test_block_means_and_truth_path(tmp_path):
    time_s = np.arange(0, 120, 0.1)
    means = block_means(np.column_stack([time_s, -time_s]), time_s, 60.0)
    np.testing.assert_allclose(means[:, 0], [29.95, 89.95])
    assert truth_path(tmp_path / "F.csv").name == "F.truth.csv"


def test_compensated_files_keep_twelve_significant_digits(tmp_path):
    from gyronet.offline import write_compensated

    rng = np.random.default_rng(0)
    columns = {"time_s": np.arange(5000) / 10.0, "gyro_x_dps": rng.normal(0, 0.3, 5000),
               "gyro_y_dps": rng.normal(0, 10.0, 5000), "out_of_range": (rng.random(5000) > 0.9).astype(np.int8)}
    with_nan = {**columns, "gyro_x_dps": np.r_[np.nan, columns["gyro_x_dps"][1:]]}  # the pandas fallback
    for name, values in (("fast.csv", columns), ("nan.csv", with_nan)):
        back = pd.read_csv(write_compensated(tmp_path / name, values, tmp_path), comment="#")
        assert list(back.columns) == list(columns)
        for key, value in values.items():
            scale = np.nanmax(np.abs(value))
            np.testing.assert_allclose(back[key].to_numpy(), value, rtol=0, atol=1e-11 * scale)
        assert open(tmp_path / name).readline().startswith("# compensated_by=")
