"""Recordings: round trip, auxiliary columns kept, every malformed file refused with one clear line."""
import gzip
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from gyronet.recordings.data import (GYRO_COLUMNS, REQUIRED_COLUMNS, Recording, block_means, load_recording,
                                     split_by_time, truth_path, warn_timing, write_recording)
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
    "nan": (f"{HEADER}\n0,20,1,2,3\n0.1,nan,1,2,3\n", "line 3: column 'temp_c': missing value"),
    "empty_cell": (f"{HEADER}\n0,20,1,2,3\n0.1,20,1,,3\n", "line 3: column 'gyro_y_dps': missing value"),
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
    with pytest.raises(RecordingError, match="a folder, not a recording"):
        load_recording(tmp_path)


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
    assert truth_path(tmp_path / "F.csv.gz").name == "F.truth.csv.gz"


def test_a_gz_output_name_is_gzip_compressed_by_every_whole_file_writer(tmp_path):
    from gyronet.bundle.offline import write_compensated
    from gyronet.recordings.fastcsv import write_csv

    cols = _columns()
    finite = {k: v for k, v in cols.items() if k != "vdd_v"}
    written = [write_recording(tmp_path / "r.csv.gz", cols, {"fs_hz": 10}),
               write_csv(tmp_path / "f.csv.gz", finite, {"fs_hz": 10}),
               write_compensated(tmp_path / "c.csv.gz", {**finite, "gyro_x_dps": np.r_[np.nan, cols["gyro_x_dps"][1:]]},
                                 tmp_path)]
    for path in written:
        with gzip.open(path) as handle:  # a gzip stream, not text under a .gz name
            back = pd.read_csv(handle, comment="#")
        np.testing.assert_allclose(back["time_s"], cols["time_s"])
    assert list(tmp_path.glob(".*")) == []  # no temporary file left behind
    np.testing.assert_allclose(load_recording(written[0]).columns["vdd_v"], cols["vdd_v"], rtol=1e-8)


def test_a_stream_refuses_a_gz_output_name_it_could_not_keep(tmp_path):
    from gyronet.deploy.stream.output import LiveWriter
    from gyronet.deploy.stream.record import _RecordingFile
    from gyronet.deploy.stream.summary import OutputError

    with pytest.raises(OutputError, match="line by line.*gzip the file afterwards"):
        LiveWriter(tmp_path / "live.csv.gz", tmp_path)
    with pytest.raises(OutputError, match="line by line"):
        _RecordingFile(tmp_path / "rec.CSV.GZ", ["time_s"], {})
    assert list(tmp_path.iterdir()) == []


def test_compensated_files_keep_twelve_significant_digits(tmp_path):
    from gyronet.bundle.offline import write_compensated

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
        assert (tmp_path / name).read_text().startswith("# compensated_by=")


# ------------------------------------------------------------------ hostile files (issue 10)

def _good_rows(n=20, aux=""):
    return [f"{i / 10!r},{20 + i / 8!r},{i * 0.25!r},{-i * 0.5!r},0.5{aux}" for i in range(n)]


def _load_error(path, **kwargs) -> str:
    with pytest.raises(RecordingError) as err:
        load_recording(path, **kwargs)
    message = str(err.value)
    assert str(path) in message and len(message.splitlines()) == 1 and "Traceback" not in message
    return message


def _check_good(rec, n=20):
    np.testing.assert_array_equal(rec.time_s, np.arange(n) / 10)
    np.testing.assert_array_equal(rec.temp_c, 20 + np.arange(n) / 8)
    np.testing.assert_array_equal(rec.gyro_dps, np.column_stack([np.arange(n) * 0.25, -np.arange(n) * 0.5,
                                                                 np.full(n, 0.5)]))


HUGE_LINES = {
    "distinct": lambda: ",".join(f"c{i}" for i in range(900_000)),  # 6 MB, no newline
    "same": lambda: "a," * 3_000_000,  # one name 3 M times
    "with_required": lambda: HEADER + "," + ",".join(f"aux{i}_v" for i in range(700_000)) + "\n0,1,2,3,4\n",
    "data_line": lambda: HEADER + "\n" + "1," * 3_000_000 + "\n",  # pandas made a column of every cell
    "empty_cells": lambda: HEADER + "\n0,1,2,3,4" + "," * 3_000_000 + "\n",
}


@pytest.mark.parametrize("kind", sorted(HUGE_LINES))
def test_a_huge_one_line_file_is_refused_at_once(tmp_path, kind):
    # the duplicate-column check was quadratic: a 6 MB line took minutes; run it apart so a
    # regression fails on the timeout instead of hanging the suite
    path = tmp_path / "line.csv"
    path.write_text(HUGE_LINES[kind]())
    code = ("import sys; from gyronet.recordings.data import load_recording; from gyronet.errors import RecordingError\n"
            f"try:\n    load_recording({str(path)!r})\nexcept RecordingError as e:\n    print(e)\n")
    proc = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=20,
                          env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert proc.returncode == 0 and proc.stdout.startswith(str(path)), proc.stderr[-500:]
    assert proc.stdout.count("\n") == 1 and len(proc.stdout) < 400


def test_the_header_checks_are_linear_in_the_number_of_columns(tmp_path):
    # 9,000 auxiliary columns (under the 10,000 cap) load; a duplicate among them is found
    names = [f"aux{i}_v" for i in range(9_000)]
    path = tmp_path / "wide.csv"
    path.write_text(",".join([HEADER, *names]) + "\n" + ",".join(["0,20,1,2,3", *["1"] * 9_000]) + "\n"
                    + ",".join(["0.1,21,1,2,3", *["2"] * 9_000]) + "\n")
    rec = load_recording(path)
    assert len(rec.columns) == 9_005 and rec.columns["aux8999_v"].tolist() == [1.0, 2.0]
    path.write_text(",".join([HEADER, *names, "aux17_v"]) + "\n")
    assert "duplicate column 'aux17_v'" in _load_error(path)


def test_a_header_cell_over_the_csv_field_limit_is_one_line(tmp_path):
    path = tmp_path / "cell.csv"
    path.write_text(f'{HEADER},"{"x" * 140_000}"\n' + "\n".join(r + ",1" for r in _good_rows()) + "\n")
    assert "column 6 of the header is 140000 characters long" in _load_error(path)


def test_gzip_files_good_truncated_corrupt_and_misnamed(tmp_path):
    text = (HEADER + "\n" + "\n".join(_good_rows()) + "\n").encode()
    good = tmp_path / "good.csv.gz"
    good.write_bytes(gzip.compress(text))
    _check_good(load_recording(good))
    cut = tmp_path / "cut.csv.gz"
    cut.write_bytes(gzip.compress(text)[:-12])
    assert "truncated gzip file" in _load_error(cut)
    corrupt = tmp_path / "corrupt.csv.gz"
    corrupt.write_bytes(gzip.compress(text)[:12] + b"\xff" * 40)
    assert "corrupt gzip file" in _load_error(corrupt)
    plain = tmp_path / "plain.csv.gz"  # not compressed at all: read as the text it is
    plain.write_bytes(text)
    _check_good(load_recording(plain))


def test_an_extra_cell_on_every_row_is_refused_not_shifted(tmp_path):
    path = tmp_path / "extra.csv"
    path.write_text(HEADER + "\n" + "\n".join(r + ",9" for r in _good_rows()) + "\n")
    message = _load_error(path)
    assert "line 2: malformed row: 6 cells where the header names 5 columns" in message


def test_trailing_commas_are_read_and_blame_lands_where_it_belongs(tmp_path):
    everywhere = tmp_path / "everywhere.csv"
    everywhere.write_text(HEADER + ",\n" + "\n".join(r + "," for r in _good_rows()) + "\n")
    _check_good(load_recording(everywhere))
    rows_only = tmp_path / "rows.csv"  # the header has none: the rows' last cell is empty, not acc_z_g
    rows_only.write_text(HEADER + ",acc_z_g\n" + "\n".join(r + ",1.0," for r in _good_rows()) + "\n")
    rec = load_recording(rows_only)
    _check_good(rec)
    assert rec.columns["acc_z_g"].tolist() == [1.0] * 20
    unnamed = tmp_path / "unnamed.csv"  # a trailing comma on the header, but values under it
    unnamed.write_text(HEADER + ",\n" + "\n".join(r + ",7" for r in _good_rows()) + "\n")
    assert "line 2: column 6 has a value but no name in the header" in _load_error(unnamed)


def test_a_missing_cell_is_refused_and_a_cut_last_line_is_ignored(tmp_path):
    rows = _good_rows()
    missing = tmp_path / "missing.csv"
    missing.write_text(HEADER + ",vdd_v\n" + "\n".join(r + ",3.3" for r in rows[:5]) + "\n" + rows[5] + "\n")
    assert "line 7: malformed row: 5 cells where the header names 6 columns (a missing cell)" in _load_error(missing)
    cut = tmp_path / "cut.csv"  # a logger stopped mid-line: no newline at the end
    cut.write_text(HEADER + "\n" + "\n".join(rows) + "\n" + "2.0,22.5,0.")
    _check_good(load_recording(cut))


def test_encodings_comments_and_line_ends_a_user_would_expect_read(tmp_path):
    text = "# place=bench 3\n# unit=°C\n" + HEADER + "\n" + "\n".join(_good_rows()) + "\n"
    variants = {
        "latin1": text.encode("latin-1"),
        "cp1252": text.replace("bench", "“bench”").encode("cp1252"),
        "utf16": text.encode("utf-16"),  # with its BOM
        "utf16be": b"\xfe\xff" + text.encode("utf-16-be"),
        "utf16_no_bom": text.encode("utf-16-le"),
        "utf8_bom": b"\xef\xbb\xbf" + text.encode(),
        "crlf": text.replace("\n", "\r\n").encode(),
        "cr": text.replace("\n", "\r").encode(),
        "blank_lines": text.replace("\n0.5,", "\n\n  \n0.5,").encode(),
    }
    for name, data in variants.items():
        path = tmp_path / f"{name}.csv"
        path.write_bytes(data)
        rec = load_recording(path)
        _check_good(rec)
        assert rec.meta["unit"] == "°C", name


def test_line_numbers_count_comment_and_blank_lines(tmp_path):
    path = tmp_path / "blank.csv"
    rows = _good_rows()
    rows[6] = rows[6].replace(",0.5", ",nan")
    path.write_text("# a=1\n\n" + HEADER + "\n" + "\n".join(rows[:3]) + "\n\n\n" + "\n".join(rows[3:]) + "\n")
    assert "line 12: column 'gyro_z_dps': missing value" in _load_error(path)


def test_auxiliary_columns_that_are_not_numbers_are_dropped_with_one_warning(tmp_path, caplog):
    rows = _good_rows()
    lines = [r + f",3.3,hello {i},{'' if i == 4 else '1.5'},{'inf' if i == 7 else '2'}" for i, r in enumerate(rows)]
    path = tmp_path / "aux.csv"
    path.write_text(HEADER + ",vdd_v,notes,spare_v,board_temp_c\n" + "\n".join(lines) + "\n")
    with caplog.at_level("WARNING", logger="gyronet"):
        rec = load_recording(path)
    _check_good(rec)
    assert rec.aux_columns == ["vdd_v"] and rec.columns["vdd_v"].tolist() == [3.3] * 20
    assert set(rec.dropped) == {"notes", "spare_v", "board_temp_c"}
    assert "line 6: missing value" in rec.dropped["spare_v"] and "line 9: infinite" in rec.dropped["board_temp_c"]
    warnings = [r for r in caplog.records if r.levelname == "WARNING"]
    assert len(warnings) == 1 and all(n in warnings[0].getMessage() for n in ("notes", "spare_v", "board_temp_c"))
    # what the caller requires stays strict
    assert "line 6: column 'spare_v': missing value" in _load_error(path, required=(*REQUIRED_COLUMNS, "spare_v"))
    assert "line 2: column 'notes': non-numeric value 'hello 0'" in _load_error(path, required=("time_s", "notes"))


def test_quoted_cells_are_read(tmp_path):
    path = tmp_path / "quoted.csv"
    lines = [",".join(f'"{c}"' for c in r.split(",")) + ',"a, b"' for r in _good_rows()]
    path.write_text(",".join(f'"{n}"' for n in HEADER.split(",")) + ',"notes"\n' + "\n".join(lines) + "\n")
    rec = load_recording(path)
    _check_good(rec)
    assert "notes" in rec.dropped


def test_a_repeated_header_is_named_as_such(tmp_path):
    path = tmp_path / "joined.csv"
    rows = _good_rows()
    path.write_text(HEADER + "\n" + "\n".join(rows[:4]) + "\n" + HEADER + "\n" + "\n".join(rows[4:]) + "\n")
    assert "line 6 repeats the header" in _load_error(path)


@pytest.mark.parametrize("declared, expected", [
    ("0", "not a positive number"), ("nan", "not a positive number"), ("abc", "not a positive number"),
    ("-5", "not a positive number"), ("inf", "not a positive number"),
    ("1e9", "fs_hz=1e9 disagrees with the samples (median interval 0.1 s, i.e. 10 Hz)"),
    ("11", "fs_hz=11 disagrees"),
])
def test_a_declared_sampling_rate_must_be_the_recordings(tmp_path, declared, expected):
    path = tmp_path / "fs.csv"
    path.write_text(f"# fs_hz={declared}\n{HEADER}\n" + "\n".join(_good_rows()) + "\n")
    assert expected in _load_error(path)


def test_a_declared_rate_within_the_clock_tolerance_is_kept(tmp_path):
    path = tmp_path / "fs.csv"
    path.write_text(f"# fs_hz=10.2\n{HEADER}\n" + "\n".join(_good_rows()) + "\n")
    assert load_recording(path).fs_hz == 10.2


def test_block_means_of_nothing_and_across_gaps():
    assert block_means(np.empty((0, 3)), np.empty(0), 10.0).shape == (0, 3)
    assert block_means(np.empty(0), np.empty(0), 10.0).shape == (0,)
    # 25 s, a one-hour gap, 25 s more at 1 Hz: the blocks after the gap start with it
    time_s = np.r_[np.arange(0.0, 25.0), np.arange(3625.0, 3650.0)]
    np.testing.assert_allclose(block_means(time_s, time_s, 10.0), [4.5, 14.5, 22.0, 3629.5, 3639.5, 3647.0])
    # a short gap inside a block: the block is the mean of the samples it has
    time_s = np.r_[np.arange(0.0, 4.0), np.arange(7.0, 20.0)]
    np.testing.assert_allclose(block_means(time_s, time_s, 10.0), [(0 + 1 + 2 + 3 + 7 + 8 + 9) / 7, 14.5])


def test_the_split_puts_validation_where_there_are_samples():
    # 20 min, a one-hour break, 20 min: spans of wall-clock time would all fall in the break
    time_s = np.r_[np.arange(0, 1200, 0.5), np.arange(4800, 6000, 0.5)]
    train, val = split_by_time(time_s, val_fraction=0.2, n_blocks=10)
    assert val.sum() == 0.2 * len(time_s) and train.sum() == 0.8 * len(time_s)
    # without a break the spans are those of time itself
    time_s = np.arange(0, 1000, 0.1)
    _, val = split_by_time(time_s)
    assert val[(time_s >= 200) & (time_s < 300)].all() and val.sum() == 2000


def test_stamps_that_look_wrong_for_training_are_named_once(caplog):
    def record(time_s, path):
        n = len(time_s)
        return Recording({"time_s": np.asarray(time_s, float), "temp_c": np.linspace(20, 30, n),
                          **{c: np.zeros(n) for c in GYRO_COLUMNS}}, {}, path)

    bursts = np.concatenate([np.arange(50.0) / 10.0 + 300.0 * k for k in range(20)])  # 5 s every 5 min
    with caplog.at_level("WARNING", logger="gyronet.recordings.data"):
        warn_timing(record(np.arange(5000.0) * 100.0, "ms.csv"))  # 10 Hz stamped in ms
        warn_timing(record(bursts, "bursts.csv"))
        warn_timing(record(bursts, "bursts.csv"))
        warn_timing(record(np.arange(5000.0) / 10.0, "fine.csv"))
    messages = [r.getMessage() for r in caplog.records]
    assert len(messages) == 2 and "ms.csv: 0.01 Hz" in messages[0] and "milliseconds" in messages[0]
    assert "bursts.csv: no stretch without a break reaches 60 s (the longest is 4.9 s)" in messages[1]


def test_another_logger_s_names_get_the_renames_to_make(tmp_path):
    path = tmp_path / "other.csv"
    path.write_text("t_s,temperature,gx,gy,gz\n0,20,1,2,3\n1,20,1,2,3\n")
    with pytest.raises(RecordingError, match=r"rename t_s -> time_s, temperature -> temp_c, gx -> gyro_x_dps, "
                                             r"gy -> gyro_y_dps, gz -> gyro_z_dps \(in s, degC and deg/s\)"):
        load_recording(path)


def test_a_bag_or_ulog_given_as_a_recording_is_sent_to_convert(tmp_path):
    for name in ("run.bag", "run.mcap", "flight.ulg"):
        (tmp_path / name).write_bytes(b"\x00\x01")
        with pytest.raises(RecordingError, match=rf"not a recording: convert it first \(python scripts/convert.py "
                                                 rf"input=.*{name} output=F.csv\)"):
            load_recording(tmp_path / name)


def test_a_text_column_that_starts_with_nan_is_dropped_not_a_traceback(tmp_path):
    """'nan' then 'ok' in a logger's status column was a ValueError from pandas (found by test_fuzz_loader)."""
    path = tmp_path / "notes.csv"
    path.write_text("time_s,temp_c,gyro_x_dps,gyro_y_dps,gyro_z_dps,vdd_v,notes\n0,20,0,0,0,3.3,nan\n"
                    "0.1,20,0,0,0,3.3,ok\n0.2,20,0,0,0,3.3,ok\n")
    recording = load_recording(path)
    assert "notes" in recording.dropped and "notes" not in recording.columns
    np.testing.assert_array_equal(recording.columns["vdd_v"], [3.3, 3.3, 3.3])
