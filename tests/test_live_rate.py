"""The live path checks the stream's rate against the bundle's, as compensate.py checks a file's (issue 10 item 8)."""
import numpy as np
import pandas as pd
import pytest

from gyronet.bundle.compensator import Compensator
from gyronet.recordings.data import GYRO_COLUMNS, load_recording
from gyronet.errors import BundleError
from gyronet.bundle.offline import compensate_recording
from gyronet.sim import simulate, write_simulation


@pytest.fixture(scope="module")
def ten_hz(tmp_path_factory):
    """Ten minutes of the paper profile at 10 Hz: five times the conftest bundle's 2 Hz."""
    path = tmp_path_factory.mktemp("rate") / "ten_hz.csv"
    write_simulation(simulate("paper", fs_hz=10.0, seed=5, sensor_seed=0, duration_s=600.0), path)
    return load_recording(path)


def _stream(monkeypatch, recording):
    import gyronet.deploy.stream.live as live
    from gyronet.deploy.stream import Sample

    def scripted(*args, **kwargs):
        samples = [Sample(float(recording.time_s[row]), {c: float(recording.columns[c][row])
                                                         for c in ("temp_c", *GYRO_COLUMNS)})
                   for row in range(len(recording))]
        for start in range(0, len(samples), 13):  # reads of 13 samples: the rate gate opens inside one
            yield samples[start:start + 13]

    monkeypatch.setattr(live, "read_chunks", scripted)
    return live


def test_a_stream_at_another_rate_is_refused_before_any_sample_is_written(bundle, ten_hz, tmp_path, monkeypatch):
    live = _stream(monkeypatch, ten_hz)
    with pytest.raises(BundleError, match=r"10 Hz.*2 Hz.*resample=true"):
        live.run_stream(bundle, "/dev/null", tmp_path / "live.csv", allan_every_s=0, reconnect={"wait_at_start": True})
    assert len(pd.read_csv(tmp_path / "live.csv", comment="#")) == 0


def test_resample_live_equals_resample_offline(bundle, ten_hz, tmp_path, monkeypatch):
    live = _stream(monkeypatch, ten_hz)
    summary = live.run_stream(bundle, "/dev/null", tmp_path / "live.csv", allan_every_s=0,
                              reconnect={"wait_at_start": True}, resample=True)
    assert summary["n_samples"] == len(ten_hz)  # the samples held for the rate check are all written
    offline = Compensator.load(bundle)
    offline.use_input_rate(ten_hz.fs_hz, resample=True, source="ten_hz")
    expected = compensate_recording(offline, ten_hz).rate_dps
    got = pd.read_csv(tmp_path / "live.csv", comment="#")[list(GYRO_COLUMNS)].to_numpy()
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-9)
