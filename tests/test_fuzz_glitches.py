"""Fuzzing glitches through the file: damaged recordings on disk, loaded and compensated as the commands do.

Each example writes a small simulated recording, damages it with a random mix of what issue 26
found accepted with a wrong result (temperature glitches of any impossible value or a jump no
thermal mass allows, gyro values beyond any sensor's range, a file cut inside its last cell), and
checks what every command relies on: the loader returns exactly the written numbers (the cut last
row dropped and counted, or whole); every damaged row is flagged ``bad_input`` and nothing else
is; every other row's output equals the reference built from the undamaged file without the
damaged rows (the rows a temperature glitch hits are lost samples to the features; a gyro glitch
leaves the features whole and is lost to the start-up window and the Kalman stage); Allan equals
the undamaged file's without the impossible samples; live, one row at a time, equals the batch.
The default run tries a few dozen files; HYPOTHESIS_PROFILE=slow ten times more.
"""
import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from gyronet.allan import allan_report
from gyronet.bundle.compensator import Compensator
from gyronet.recordings.csvtable.tail import cell_shape
from gyronet.recordings.data import GYRO_COLUMNS, Recording, load_recording, write_recording
from gyronet.bundle.io import load_unfrozen
from gyronet.recordings.fastcsv import write_csv
from gyronet.recordings.guard import CONFIRM_SAMPLES
from gyronet.model.kalman import KalmanStage
from gyronet.bundle.offline import compensate_recording
from gyronet.bundle.startup import StartupOffset

from conftest import toy_kalman_dict

N_ROWS = 800  # 400 s at 2 Hz


@pytest.fixture(scope="module")
def clean(cycle_csv):
    return load_recording(cycle_csv).slice(slice(0, N_ROWS))


@pytest.fixture(scope="module")
def loaded(bundle):
    return Compensator.load(bundle)


@st.composite
def damages(draw):
    """Disjoint temperature-glitch rows (with values) and gyro-glitch rows (with axis and value), and a cut."""
    free = list(range(1, N_ROWS - 1))
    temp: dict[int, float] = {}
    for _ in range(draw(st.integers(0, 3))):
        start = draw(st.integers(1, N_ROWS - 80))
        if draw(st.booleans()):  # impossible: any length
            length = draw(st.integers(1, 60))
            value = draw(st.sampled_from([500.0, 1e6, -300.0, 250.0, 1e300, -1e300]))
            values = [value] * length
        else:  # a jump no thermal mass allows, shorter than the guard's confirmation
            length = draw(st.integers(1, CONFIRM_SAMPLES - 1))
            values = [draw(st.sampled_from([15.0, -15.0, 40.0, -60.0]))] * length
        if any(r in temp for r in range(start - 1, start + length + 1)):
            continue  # two runs side by side of one jump would be a step the guard confirms: a real one
        for row, value in zip(range(start, start + length), values):
            temp[row] = value
    gyro: dict[int, tuple[int, float]] = {}
    for row in draw(st.lists(st.sampled_from([r for r in free if r not in temp]), max_size=20, unique=True)):
        gyro[row] = (draw(st.integers(0, 2)), draw(st.sampled_from([2e4, -2e4, 1e300, -1e300, 1e5])))
    cut = draw(st.one_of(st.none(), st.integers(0, 12)))  # bytes cut from the end (0: the newline only)
    return temp, gyro, cut


def _damaged_columns(clean, temp, gyro):
    columns = {k: v.copy() for k, v in clean.columns.items()}
    for row, value in temp.items():
        columns["temp_c"][row] = value if abs(value) >= 200 else columns["temp_c"][row] + value
    for row, (axis, value) in gyro.items():
        columns[GYRO_COLUMNS[axis]][row] = value
    return columns


def _expected(loaded, clean, temp_rows, gyro_rows, kalman, startup):
    """The undamaged file's output without the temperature-glitch rows in the features and without any
    damaged row in the start-up window and the Kalman stage."""
    kept = np.ones(len(clean), dtype=bool)
    kept[temp_rows] = False
    plain = compensate_recording(Compensator(loaded.model, loaded.meta), clean.slice(kept)).rate_dps
    gyro_kept = np.ones(len(clean), dtype=bool)
    gyro_kept[gyro_rows] = False
    rate = plain[gyro_kept[kept]]
    if startup:
        rate = StartupOffset(60.0).process(clean.time_s[kept & gyro_kept], rate)
    if kalman:
        rate = KalmanStage.from_dict(toy_kalman_dict()).process(rate)
    return rate, kept & gyro_kept


@given(damage=damages(), kalman=st.booleans(), startup=st.booleans())
def test_damaged_files_flag_the_damaged_rows_and_leave_every_other_row(loaded, clean, tmp_path_factory, damage,
                                                                      kalman, startup):
    temp, gyro, cut = damage
    path = tmp_path_factory.mktemp("fuzz") / "damaged.csv"
    write_recording(path, _damaged_columns(clean, temp, gyro), clean.meta, float_format="%.17g")
    if cut is not None:
        raw = path.read_bytes()
        path.write_bytes(raw[:len(raw) - 1 - cut])
    recording = load_recording(path)
    n = len(recording)
    assert n in (N_ROWS, N_ROWS - 1) and recording.cut_rows == N_ROWS - n
    if cut is None or cut == 0:
        assert n == N_ROWS  # a complete file without its final newline reads whole
    # every row read is exactly what was written (a last row kept after a cut is checked below)
    written = _damaged_columns(clean, temp, gyro)
    whole = n - 1 if cut and n == N_ROWS else n
    for name, values in written.items():
        np.testing.assert_array_equal(recording.columns[name][:whole], values[:whole])
    clean_n = clean.slice(slice(0, whole))
    temp_rows = sorted(r for r in temp if r < whole)
    gyro_rows = sorted(r for r in gyro if r < whole)
    compensator = Compensator(loaded.model, loaded.meta, toy_kalman_dict() if kalman else None)
    if startup:
        compensator.use_startup(still_s=60.0)
    out = compensate_recording(compensator, recording.slice(slice(0, whole)))
    assert np.flatnonzero(out.bad_input).tolist() == sorted(temp_rows + gyro_rows)
    assert np.isfinite(out.rate_dps).all()
    expected, others = _expected(loaded, clean_n, temp_rows, gyro_rows, kalman, startup)
    np.testing.assert_array_equal(out.rate_dps[others], expected)
    report = allan_report(recording.time_s[:whole], recording.gyro_dps[:whole])
    keep = np.ones(whole, dtype=bool)
    keep[gyro_rows] = False
    reference = allan_report(clean_n.time_s[keep], clean_n.gyro_dps[keep])
    for axis in "xyz":
        np.testing.assert_equal(report[axis], reference[axis])


@given(seed=st.integers(0, 2**32 - 1), writer=st.sampled_from(["%.9g", "%.6f", "%.17g", "fast"]),
       cut=st.integers(0, 40))
def test_a_file_cut_inside_its_last_line_never_reads_a_shortened_number_unseen(tmp_path_factory, seed, writer,
                                                                                 cut):
    """Cut anywhere in the last line (0: only the final newline): the loader drops that row with a count,
    or reads it whole, or (a cut the rule cannot see) reads its last value within the column's coarsest
    rounding: at least as many significant digits as every cell of that column above it."""
    rng = np.random.default_rng(seed)
    n = 300
    columns = {"time_s": np.arange(n) * 0.5, "temp_c": 25 + np.cumsum(rng.normal(0, 0.01, n)).round(4),
               **{c: rng.normal(0, 0.1, n) for c in GYRO_COLUMNS}, "acc_z_g": 1 + rng.normal(0, 0.002, n)}
    path = tmp_path_factory.mktemp("cut") / "cut.csv"
    if writer == "fast":
        write_csv(path, columns, {"fs_hz": 2})
    else:
        write_recording(path, columns, {"fs_hz": 2}, float_format=writer)
    raw = path.read_bytes()
    last_line = raw[raw.rstrip(b"\n").rfind(b"\n") + 1:]
    cut = min(cut, len(last_line) - 1)
    path.write_bytes(raw[:len(raw) - 1 - cut])
    recording = load_recording(path)
    written = {k: np.array([float(c) for c in v]) for k, v in _cells(raw).items()}
    if cut == 0:
        assert len(recording) == n and recording.cut_rows == 0
    assert len(recording) in (n, n - 1) and recording.cut_rows == n - len(recording)
    for name in columns:
        np.testing.assert_array_equal(recording.columns[name][:n - 1], written[name][:n - 1])
    if len(recording) == n:
        last_cell = last_line.rstrip(b"\n")[:len(last_line) - 1 - cut].decode().split(",")[-1]
        above = _cells(raw)["acc_z_g"][:-1]
        digits = min(cell_shape(c)[1] for c in above)
        true = written["acc_z_g"][-1]
        assert cell_shape(last_cell)[1] >= digits
        assert math.isclose(recording.columns["acc_z_g"][-1], true, rel_tol=10.0 ** (1 - digits))


def _cells(raw: bytes) -> dict[str, list[str]]:
    lines = [line for line in raw.decode().split("\n") if line and not line.startswith("#")]
    names = lines[0].split(",")
    rows = [line.split(",") for line in lines[1:]]
    return {name: [row[i] for row in rows] for i, name in enumerate(names)}


@given(damage=damages())
def test_live_one_row_at_a_time_equals_the_batch_with_glitches(loaded, clean, bundle, damage):
    temp, gyro, _ = damage
    recording = Recording(_damaged_columns(clean, temp, gyro), dict(clean.meta), clean.path).slice(slice(0, 300))
    batch = Compensator(loaded.model, loaded.meta, toy_kalman_dict())
    expected = compensate_recording(batch, recording)
    live = Compensator(loaded.model, loaded.meta, toy_kalman_dict())
    assert live.use_small_chunks(load_unfrozen(bundle))  # the live path: process_row in plain floats
    rates, flags = [], []
    for i in range(len(recording)):
        values = {c: float(recording.columns[c][i]) for c in live.input_columns if c != "time_s"}
        row = live.process_row(float(recording.time_s[i]), values)
        if row is None:  # a gyro value out of range: the array path takes it
            one = live.process({c: recording.columns[c][i:i + 1] for c in live.input_columns})
            rates.append(one.rate_dps[0]), flags.append(bool(one.bad_input[0]))
        else:
            rates.append(row.rate_dps), flags.append(row.bad_input)
    # the model in plain floats rounds differently from TorchScript (test_small_model: 1e-9)
    np.testing.assert_allclose(np.array(rates), expected.rate_dps, rtol=0, atol=1e-9)
    assert flags == expected.bad_input.tolist() and live.n_bad_input == batch.n_bad_input
