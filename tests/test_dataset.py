"""Training data: records too short, too flat or physically impossible are refused in one line before
any work; a record with a long break still trains; a diverging fit says so in one line."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from gyronet.training import dataset
from gyronet.recordings.data import write_recording
from gyronet.training.dataset import MIN_TEMP_SPAN_C, DriftData
from gyronet.errors import GyronetError, RecordingError

FS_HZ = 1.0


def _record(duration_s: float = 3600.0, fs_hz: float = FS_HZ, temp=lambda t: 20 + 20 * t / t[-1], keep=None):
    """A static record whose drift follows temperature, at ``fs_hz``; ``keep`` masks samples out."""
    time_s = np.arange(0.0, duration_s, 1.0 / fs_hz)
    time_s = time_s if keep is None else time_s[keep(time_s)]
    temp_c = temp(time_s) if len(time_s) > 1 else np.full(len(time_s), 20.0)
    rng = np.random.default_rng(0)
    columns = {"time_s": time_s, "temp_c": temp_c}
    for axis, slope in zip("xyz", (0.01, -0.02, 0.005)):
        columns[f"gyro_{axis}_dps"] = slope * (temp_c - 25) + rng.normal(0, 0.01, len(time_s))
    columns["vdd_v"] = np.full(len(time_s), 3.3)
    return columns


def _write(tmp_path, name, columns, meta=None):
    return str(write_recording(tmp_path / name, columns, meta or {}, float_format="%.12g"))


def _error(path, cls=GyronetError, **options) -> str:
    with pytest.raises(cls) as err:
        DriftData(path, **options)
    message = str(err.value)
    assert len(message.splitlines()) == 1 and path in message
    return message


@pytest.fixture
def no_feature_work(monkeypatch):
    """Fail the test if the causal features are computed: a refusal must come before that."""
    def refuse(*args, **kwargs):
        raise AssertionError("features were computed before the record was refused")

    monkeypatch.setattr(dataset, "featurize", refuse)
    dataset._features_by_key.cache_clear()
    yield
    dataset._features_by_key.cache_clear()


def test_a_six_sample_record_is_refused_as_too_short(tmp_path, no_feature_work):
    # six samples at 100 Hz, as in a short ULog: the held-out span was empty and block_means crashed
    path = _write(tmp_path, "six.csv", _record(duration_s=0.06, fs_hz=100.0))
    message = _error(path)
    assert "too short to train on (6 samples over 0.05 s" in message


def test_a_constant_temperature_is_refused(tmp_path, no_feature_work):
    path = _write(tmp_path, "flat.csv", _record(temp=lambda t: np.zeros(len(t))))
    message = _error(path)
    assert "temperature spans 0 degC (0 .. 0)" in message and f"at least {MIN_TEMP_SPAN_C:g} degC" in message
    path = _write(tmp_path, "nearly.csv", _record(temp=lambda t: 20 + 0.5 * t / t[-1]))
    assert "temperature spans 0.5 degC" in _error(path)


@pytest.mark.parametrize("column, value, rows, expected", [
    ("gyro_x_dps", 1e300, [100], "gyro_x_dps = 1e+300 deg/s is outside any sensor's range"),
    ("gyro_z_dps", -2e4, [100], "gyro_z_dps = -20000 deg/s is outside"),
    ("temp_c", 1e6, slice(100, None), "temp_c = 1e+06 degC is outside any sensor's range (-80 .. 200)"),
    ("temp_c", -273.0, slice(100, None), "temp_c = -273 degC"),
])
def test_a_physically_impossible_sample_is_refused_naming_its_line(tmp_path, no_feature_work, column, value, rows,
                                                                    expected):
    columns = _record()
    columns[column][rows] = value  # a temperature so on more than 1 % of the rows: a unit or a column wrong
    path = _write(tmp_path, "glitch.csv", columns, {"sensor": "bench"})
    message = _error(path, RecordingError)
    # line 1 is the metadata, 2 the header: row 100 is line 103
    assert f"line 103: {expected}" in message and "such sample(s)" in message


def test_a_few_impossible_temperatures_are_glitches_left_out_of_training(tmp_path, caplog):
    columns = _record()
    columns["temp_c"][100] = 500.0  # one sensor-read glitch in a long chamber log
    path = _write(tmp_path, "glitch.csv", columns)
    with caplog.at_level("WARNING", logger="gyronet.training.dataset"):
        data = DriftData(path)
    assert data.n_rejected == 1 and data.temp_range_c[1] < 100.0
    assert "1 of " in caplog.text and "left out of training and of the trained range" in caplog.text


def test_the_validation_recording_is_checked_too(tmp_path, no_feature_work):
    train = _write(tmp_path, "train.csv", _record())
    columns = _record()
    columns["temp_c"][7:] = 500.0
    val = _write(tmp_path, "val.csv", columns)
    with pytest.raises(RecordingError, match=r"val.csv: line 9: temp_c = 500 degC"):
        DriftData(train, val_path=val)
    short = _write(tmp_path, "short_val.csv", _record(duration_s=11.0))
    with pytest.raises(GyronetError, match=r"short_val.csv: too short to validate on \(1 blocks"):
        DriftData(train, val_path=short)


def test_a_feature_column_the_loader_dropped_is_named_with_its_reason(tmp_path, no_feature_work):
    columns = _record()
    path = tmp_path / "aux.csv"
    _write(tmp_path, "aux.csv", columns)
    lines = path.read_text().splitlines()
    lines[5] = lines[5].rsplit(",", 1)[0] + ","  # one empty vdd_v cell, line 6
    path.write_text("\n".join(lines) + "\n")
    features = [{"kind": "temp"}, {"kind": "column", "source": "vdd_v"}]
    message = _error(str(path), features=features)
    assert "the features need column 'vdd_v', which is not usable (line 6: missing value" in message


def test_a_record_with_a_one_hour_break_trains(tmp_path):
    # 20 min, an hour with no samples, 20 min: wall-clock spans put every held-out span in the break
    keep = lambda t: (t < 1200) | (t >= 4800)  # noqa: E731
    path = _write(tmp_path, "gap.csv", _record(duration_s=6000.0, keep=keep))
    data = DriftData(path)
    assert len(data.train) == 192 and len(data.val) == 48
    assert np.isfinite(data.train.x).all() and np.isfinite(data.val.y).all()


def test_a_fit_that_diverges_says_so_in_one_line(tmp_path):
    from gyronet.model.rbf import RBFNet
    from gyronet.training.train import fit

    data = DriftData(_write(tmp_path, "ok.csv", _record()))
    model = RBFNet(data.n_features, 3, 8, rbf_inputs=[0], linear=True, temp_degree=3, clamp=True)
    with pytest.raises(GyronetError) as err:
        fit(model, data, optim=lambda p: torch.optim.SGD(p, lr=1e200), max_epochs=60, progress=False)
    message = str(err.value)
    assert message.startswith("training diverged at step ") and len(message.splitlines()) == 1


def test_a_flickering_mask_leaves_no_blocks_of_a_few_samples():
    """A temperature read in 0.01 degC steps flickers across the box's edge: its pieces are no 60 s means."""
    rng = np.random.default_rng(0)
    time_s = np.arange(0.0, 36000.0, 1.0)
    noise = rng.normal(0.0, 0.1, (len(time_s), 1))  # 0.1 deg/s a 1 Hz sample: 13 mdps a full 60 s mean
    flicker = rng.random(len(time_s)) < 0.5  # the first half: in and out of the box, sample by sample
    inside = np.where(time_s < 18000.0, flicker, True)
    rms = dataset.block_rmse(time_s[inside], noise[inside], 60.0)[0]
    assert rms == pytest.approx(0.1 / np.sqrt(60.0), rel=0.1)  # the whole blocks of the second half only
    means = dataset.residual_block_means(time_s[inside], noise[inside], 60.0)
    assert len(means) == 300


def test_a_record_in_bursts_keeps_a_block_per_burst():
    """Bursts of 1 s at 50 Hz every 30 s (a logger that wakes): a full block is what the bursts hold."""
    time_s = (np.arange(100)[:, None] * 30.0 + np.arange(50)[None] / 50.0).ravel()
    residual = np.ones((len(time_s), 3))
    assert len(dataset.residual_block_means(time_s, residual, 60.0)) == 100
    np.testing.assert_allclose(dataset.block_rmse(time_s, residual, 60.0), 1.0)
