"""``bad_lines=drop``: a recording with malformed lines gives up those lines, counted, and nothing else.

The default refuses such a file in one line that names the line and this remedy; with ``drop`` the loader and
``convert.py`` return exactly what the same file with those lines deleted gives (numpy equality), count them by
reason in one warning and in the ``# dropped_rows`` metadata, and still refuse what is not about one line.
"""
from __future__ import annotations

import logging
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gyronet.errors import GyronetError, RecordingError
from gyronet.recordings.data import REQUIRED_COLUMNS, load_recording
from gyronet.recordings.importers import convert, convert_with_options

ROOT = Path(__file__).resolve().parents[1]
NAMES = ["time_s", "temp_c", "gyro_x_dps", "gyro_y_dps", "gyro_z_dps", "vdd_v"]
# each damage to one line, and the reason it is counted under
REASONS = {"non_numeric": "non_numeric", "missing": "missing_value", "infinite": "infinite", "extra_cell": "cell_count",
           "missing_cell": "cell_count", "cut_short": "cell_count", "repeated_header": "repeated_header",
           "time": "time_not_increasing"}


def good_lines(n_rows: int, seed: int = 0) -> list[str]:
    """A valid recording's data lines, 10 Hz, with an auxiliary column."""
    rng = np.random.default_rng(seed)
    return [",".join([repr(i / 10), *(f"{v:.9g}" for v in rng.normal(size=len(NAMES) - 1))]) for i in range(n_rows)]


def write(path: Path, lines: list[str], meta: str = "# fs_hz=10\n") -> Path:
    path.write_text(meta + ",".join(NAMES) + "\n" + "".join(f"{line}\n" for line in lines))
    return path


def damage(line: str, kind: str, column: int, first_time: str) -> str:
    """``line`` made malformed in one way; ``column`` is a required column's index."""
    cells = line.split(",")
    if kind in ("non_numeric", "missing", "infinite"):
        cells[column] = {"non_numeric": "abc25", "missing": ("", "nan", "NaN", "NA")[column % 4],
                         "infinite": ("inf", "-inf", "1e999")[column % 3]}[kind]
    elif kind == "extra_cell":
        cells.insert(column, "7")
    elif kind == "missing_cell":
        del cells[column]
    elif kind == "cut_short":  # a write cut off inside the line: fewer cells than the header
        return line[:line.rfind(",") - column]
    elif kind == "time":  # as early as the first line, which is kept: never later than the previous kept one
        cells[0] = first_time
    return ",".join(cells)


def assert_same(got, want) -> None:
    assert list(got.columns) == list(want.columns)
    for name in want.columns:
        np.testing.assert_array_equal(got.columns[name], want.columns[name], err_msg=name)


@st.composite
def damaged_files(draw) -> tuple[list[str], list[str], list[str]]:
    """(the lines as written, the same without the damaged ones, the kinds of damage)."""
    clean = good_lines(draw(st.integers(3, 15)), draw(st.integers(0, 1000)))
    entries: list[tuple[str, str | None]] = [(line, None) for line in clean]  # the first line stays good
    for row in sorted(draw(st.lists(st.integers(1, len(clean) - 1), min_size=1, max_size=4, unique=True)),
                      reverse=True):  # from the end, so that an inserted header moves no other damage
        kind = draw(st.sampled_from(sorted(REASONS)))
        if kind == "repeated_header":
            entries.insert(row, (",".join(NAMES), kind))
        else:
            column = draw(st.integers(0, len(REQUIRED_COLUMNS) - 1))
            entries[row] = (damage(clean[row], kind, column, clean[0].split(",")[0]), kind)
    return ([line for line, _ in entries], [line for line, kind in entries if kind is None],
            [kind for _, kind in entries if kind is not None])


@settings(suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(case=damaged_files())
def test_drop_gives_the_file_without_the_damaged_lines(tmp_path, case):
    written, kept, kinds = case
    damaged = write(tmp_path / "damaged.csv", written, meta="")  # removing lines may change the rate
    with pytest.raises(RecordingError, match="bad_lines=drop leaves out such lines, counted"):
        load_recording(damaged)
    recovered = load_recording(damaged, bad_lines="drop")
    assert_same(recovered, load_recording(write(tmp_path / "kept.csv", kept, meta="")))
    expected: dict[str, int] = {}
    for kind in kinds:
        expected[REASONS[kind]] = expected.get(REASONS[kind], 0) + 1
    assert recovered.dropped_lines == expected


def _case_with_every_reason(tmp_path: Path) -> tuple[Path, Path]:
    lines = good_lines(20)
    written = list(lines)
    written[3] = damage(lines[3], "non_numeric", 2, "")
    written[5] = damage(lines[5], "extra_cell", 1, "")
    written[6] = damage(lines[6], "cut_short", 0, "")
    written[8] = damage(lines[8], "missing", 4, "")
    written[9] = damage(lines[9], "infinite", 1, "")
    written[11] = damage(lines[11], "time", 0, lines[10].split(",")[0])
    written.insert(14, ",".join(NAMES))
    kept = [line for i, line in enumerate(lines) if i not in (3, 5, 6, 8, 9, 11)]
    return write(tmp_path / "damaged.csv", written), write(tmp_path / "kept.csv", kept)


def test_convert_drop_writes_every_other_row_and_counts_the_lines(tmp_path, caplog):
    damaged, kept = _case_with_every_reason(tmp_path)
    with caplog.at_level(logging.WARNING):
        convert(damaged, tmp_path / "out.csv", "csv", bad_lines="drop")
    convert(kept, tmp_path / "want.csv", "csv")
    out, want = load_recording(tmp_path / "out.csv"), load_recording(tmp_path / "want.csv")
    assert_same(out, want)
    assert out.meta["dropped_rows"] == "7" and "dropped_rows" not in want.meta
    assert out.meta["dropped_detail"] == ("non_numeric:1;cell_count:2;missing_value:1;infinite:1;"
                                          "time_not_increasing:1;repeated_header:1")
    warnings = [r.getMessage() for r in caplog.records if "bad_lines=drop" in r.getMessage()]
    assert len(warnings) == 1 and "\n" not in warnings[0]
    assert ("7 malformed line(s) left out" in warnings[0] and "line 6: column 'gyro_x_dps': non-numeric value "
            "'abc25'; line 8: 7 cells where the header names 6 columns; line 9: " in warnings[0])
    assert warnings[0].endswith("; ...")  # five named, of seven


def test_a_second_conversion_adds_to_the_earlier_count(tmp_path):
    lines = good_lines(6)
    lines[2] = damage(lines[2], "non_numeric", 3, "")
    path = tmp_path / "old.csv"
    path.write_text("# dropped_rows=3\n# dropped_detail=nan:2;duplicate_time:1\n" + ",".join(NAMES) + "\n"
                    + "".join(f"{line}\n" for line in lines))
    out = convert(path, tmp_path / "out.csv", "csv", bad_lines="drop")
    assert out.meta["dropped_rows"] == "4"
    assert out.meta["dropped_detail"] == "nan:2;duplicate_time:1;non_numeric:1"


def test_a_clean_file_reads_the_same_either_way(tmp_path):
    path = write(tmp_path / "clean.csv", good_lines(10))
    recovered = load_recording(path, bad_lines="drop")
    assert_same(recovered, load_recording(path))
    assert recovered.dropped_lines == {}
    assert convert(path, tmp_path / "out.csv", "csv", bad_lines="drop").meta["dropped_rows"] == "0"


@pytest.mark.parametrize("text, reason", [
    ("", "empty file"),
    ("# fs_hz=10\n", "empty file"),
    ("time_s,temp_c,gyro_x_dps,gyro_y_dps\n0,20,1,2\n", r"missing required column\(s\) gyro_z_dps"),
    ("\x00\x01\x02\x03\n", "binary content"),
    ("# fs_hz=50\ntime_s,temp_c,gyro_x_dps,gyro_y_dps,gyro_z_dps\n0,20,1,2,3\n0.1,20,1,2,3\n0.2,20,1,2,3\n",
     "disagrees with the samples"),
    ("time_s,temp_c,gyro_x_dps,gyro_y_dps,gyro_z_dps\n0,20,abc,2,3\n", "no samples after the header"),
])
def test_what_is_not_about_one_line_is_still_refused(tmp_path, text, reason):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(RecordingError, match=reason) as refused:
        load_recording(path, bad_lines="drop")
    assert "\n" not in str(refused.value) and "bad_lines=drop" not in str(refused.value)


def test_every_by_line_refusal_names_the_remedy(tmp_path):
    damaged, _ = _case_with_every_reason(tmp_path)
    with pytest.raises(RecordingError) as refused:
        load_recording(damaged)
    # the cells of every line are counted before any number is read: line 8 is named before line 6
    assert str(refused.value) == (f"{damaged}: line 8: malformed row: 7 cells where the header names 6 columns; python "
                                  f"scripts/convert.py input={damaged} output=NEW.csv bad_lines=drop leaves out "
                                  "such lines, counted")
    for kind, column in (("missing", 4), ("infinite", 1), ("extra_cell", 1), ("cut_short", 0), ("time", 0)):
        lines = good_lines(4)
        lines[2] = damage(lines[2], kind, column, lines[1].split(",")[0])
        with pytest.raises(RecordingError, match=r"line 5: .*; python scripts/convert.py input=.* output=NEW.csv "
                                                 r"bad_lines=drop leaves out such lines, counted$"):
            load_recording(write(tmp_path / f"{kind}.csv", lines))


def test_bad_lines_takes_refuse_or_drop_and_only_for_contract_csvs(tmp_path):
    path = write(tmp_path / "clean.csv", good_lines(4))
    with pytest.raises(GyronetError, match="bad_lines='skip': use refuse or drop"):
        convert_with_options(path, tmp_path / "out.csv", "csv", bad_lines="skip")
    with pytest.raises(GyronetError, match="bad_lines=drop is for contract CSVs"):
        convert_with_options(path, tmp_path / "out.csv", "lpms", bad_lines="drop")


def test_script_refuses_by_default_and_recovers_with_drop(tmp_path):
    damaged, kept = _case_with_every_reason(tmp_path)

    def run(*overrides: str) -> subprocess.CompletedProcess:
        return subprocess.run([sys.executable, "scripts/convert.py", f"input={damaged}", *overrides,
                               f"hydra.run.dir={tmp_path / 'hydra'}"], cwd=ROOT, capture_output=True, text=True,
                              timeout=120)

    refused = run(f"output={tmp_path / 'a.csv'}")
    assert refused.returncode == 2 and not (tmp_path / "a.csv").exists()
    assert refused.stderr.strip().splitlines()[-1].endswith("bad_lines=drop leaves out such lines, counted")
    done = run(f"output={tmp_path / 'b.csv'}", "bad_lines=drop")
    assert done.returncode == 0, done.stderr
    assert_same(load_recording(tmp_path / "b.csv"), load_recording(kept))


def test_a_spreadsheet_export_with_a_bad_line_is_recovered_too(tmp_path):
    path = tmp_path / "semi.csv"
    path.write_text("time_s;temp_c;gyro_x_dps;gyro_y_dps;gyro_z_dps\n0,0;20,5;1,25;2;3\n0,1;20,5;abc;2;3\n"
                    "0,2;20,5;1,5;2;3\n")
    out = convert(path, tmp_path / "out.csv", "csv", bad_lines="drop")
    np.testing.assert_array_equal(out.columns["gyro_x_dps"], [1.25, 1.5])
    assert out.meta["dropped_detail"] == "non_numeric:1"


def test_one_stamp_corrupted_far_ahead_costs_only_its_own_line(tmp_path):
    """Every line after a stamp 1e9 s ahead was 'not increasing' over it, and all of them were left out."""
    lines = good_lines(50)
    written = list(lines)
    written[10] = ",".join(["1e9", *lines[10].split(",")[1:]])
    recovered = load_recording(write(tmp_path / "damaged.csv", written, meta=""), bad_lines="drop")
    assert_same(recovered, load_recording(write(tmp_path / "kept.csv", lines[:10] + lines[11:], meta="")))
    assert recovered.dropped_lines == {"time_not_increasing": 1}


def test_a_left_out_line_does_not_hide_a_cut_last_cell(tmp_path):
    """The cut-cell check looked above the last line before the bad lines were left out: a dropped line's short
    cells ('1') made '0.3', the cut of '0.3234', look whole, and it was kept as a sample."""
    names = "time_s,temp_c,gyro_x_dps,gyro_y_dps,gyro_z_dps\n"
    good = "".join(f"{i / 10:.4f},25.1234,0.1234,0.2234,0.3234\n" for i in range(10))
    damaged = tmp_path / "damaged.csv"
    damaged.write_text(names + good + "x,1,1,1,1\n" + "5.0000,25.1234,0.1234,0.2234,0.3")
    kept = tmp_path / "kept.csv"
    kept.write_text(names + good + "5.0000,25.1234,0.1234,0.2234,0.3")
    recovered, want = load_recording(damaged, bad_lines="drop"), load_recording(kept)
    assert want.cut_rows == 1
    assert_same(recovered, want)
    assert recovered.cut_rows == 1 and recovered.dropped_lines == {"non_numeric": 1}


def test_a_short_unterminated_last_line_counts_as_cut_either_way(tmp_path):
    """A write cut off in the last line is dropped as such by default (cut_rows); drop counted it as a cell_count."""
    lines = good_lines(6)
    path = tmp_path / "cut.csv"
    path.write_text(",".join(NAMES) + "\n" + "".join(f"{line}\n" for line in lines) + lines[0][:5])
    want = load_recording(path)
    assert want.cut_rows == 1
    recovered = load_recording(path, bad_lines="drop")
    assert_same(recovered, want)
    assert recovered.cut_rows == 1 and recovered.dropped_lines == {}
    assert convert(path, tmp_path / "out.csv", "csv", bad_lines="drop").meta["dropped_detail"] == "cut_last_line:1"


def test_a_quoted_cell_over_two_lines_is_one_record_either_way(tmp_path):
    """The filter split a quoted body line by line: a logger's note holding a line end (read whole by default)
    opened a quote that swallowed every row after it, left out without a count."""
    names = "time_s,temp_c,gyro_x_dps,gyro_y_dps,gyro_z_dps,note\n"
    rows = [f"{i / 10},25,0.1,0.2,0.3,ok" for i in range(10)]
    rows[4] = '0.4,25,0.1,0.2,0.3,"two\nlines"'
    path = tmp_path / "note.csv"
    path.write_text(names + "\n".join(rows) + "\n")
    recovered = load_recording(path, bad_lines="drop")
    assert_same(recovered, load_recording(path))
    assert recovered.dropped_lines == {} and len(recovered) == 10
    rows[4], rows[7] = '0.4,25,abc,0.2,0.3,"two\nlines"', "0.7,25,0.1,0.2,0.3"  # a bad record over two lines
    path.write_text(names + "\n".join(rows) + "\n")
    recovered = load_recording(path, bad_lines="drop")
    np.testing.assert_array_equal(recovered.columns["time_s"], [i / 10 for i in range(10) if i not in (4, 7)])
    assert recovered.dropped_lines == {"non_numeric": 1, "cell_count": 1}
