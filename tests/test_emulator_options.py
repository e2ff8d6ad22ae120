"""emulate_sensor.py's options: a link that would replace someone's file, and settings that ended in a traceback
(or were taken silently), are refused in one line before the recording loads."""
from __future__ import annotations

import os
from pathlib import Path

import pytest

from gyronet.errors import ConfigError
from gyronet.deploy.stream.pty_port import PtySensor
from test_commands import assert_one_line_error, run_cases


def test_a_link_over_a_regular_file_is_refused_and_the_file_kept(tmp_path):
    victim = tmp_path / "run1.csv"
    victim.write_text("time_s,temp_c\n")
    with pytest.raises(ConfigError, match="exists and is not a symlink"):
        PtySensor(victim).open()
    assert victim.read_text() == "time_s,temp_c\n"


def test_a_link_that_is_a_symlink_to_a_file_is_refused(tmp_path):
    (tmp_path / "target.csv").write_text("x\n")
    (tmp_path / "sensor").symlink_to(tmp_path / "target.csv")
    with pytest.raises(ConfigError, match="not to a pty"):
        PtySensor(tmp_path / "sensor").open()
    assert (tmp_path / "sensor").is_symlink()


def test_an_earlier_emulators_stale_link_is_replaced(tmp_path):
    link = tmp_path / "sensor"
    link.symlink_to("/dev/pts/999999")
    sensor = PtySensor(link)
    try:
        path = sensor.open()
        assert os.readlink(link) == path
    finally:
        sensor.close()
    assert not os.path.lexists(link)


def test_a_port_file_over_a_file_of_something_else_is_refused_and_an_earlier_ones_replaced(tmp_path):
    victim = tmp_path / "notes.txt"
    victim.write_text("chamber run 3: door opened at 14:02\n")
    with pytest.raises(ConfigError, match="port_file=.*holds no pty path"):
        PtySensor(port_file=victim)
    assert victim.read_text().startswith("chamber run 3")
    earlier = tmp_path / "port.txt"
    earlier.write_text("/dev/pts/999999\n")  # an earlier emulator's
    sensor = PtySensor(port_file=earlier)
    try:
        path = sensor.open()
        assert earlier.read_text() == path + "\n"
    finally:
        sensor.close()


def test_a_link_in_a_missing_folder_is_refused(tmp_path):
    with pytest.raises(ConfigError, match="does not exist"):
        PtySensor(tmp_path / "nope" / "sensor")


# ---------------------------------------------------------------- the script, in one zygote (test_commands.py)

def cases(work: Path, victim: Path, recording: Path) -> dict[str, tuple[list[str], tuple[str, ...]]]:
    """id: (arguments, what the one line must say)."""
    base = [f"input={recording}", "speed=0", "reader_timeout_s=0.1"]
    return {
        "link_is_a_file": ([*base, f"link={victim}"], (str(victim), "not a symlink")),
        "link_folder_missing": ([*base, f"link={work}/nope/sensor"], ("link=", "does not exist")),
        "speed_text": ([*base, "speed=abc"], ("speed must be a number, got 'abc'",)),
        "speed_negative": ([*base, "speed=-1"], ("speed must be 0",)),
        "protocol_typo": ([*base, "protocol=cvs"], ("error: protocol must be lpbus or csv, got 'cvs'",)),
        "fault_rate": ([*base, "faults.corrupt_rate=2"], ("faults: fault rates must be in [0, 1]",)),
        "unknown_model": ([*base, "sensor.model=LPMS-XYZ"], ("no emulated sensor 'LPMS-XYZ'", "LPMS-CU2")),
    }


@pytest.fixture(scope="module")
def results(tmp_path_factory, paper_csv) -> dict[str, dict]:
    work = tmp_path_factory.mktemp("emulate")
    victim = work / "victim.csv"
    victim.write_text("keep me\n")
    listed = cases(work, victim, paper_csv)
    by_id = run_cases([{"id": key, "script": "scripts/emulate_sensor.py", "args": [*args, f"hydra.run.dir={work / key}"]}
                       for key, (args, _) in listed.items()], work)
    for key, (_, expect) in listed.items():
        by_id[key]["expect"] = expect
    by_id["victim"] = {"text": victim.read_text() if victim.exists() else None}
    return by_id


@pytest.mark.parametrize("case", list(cases(Path("/w"), Path("/w/v.csv"), Path("/w/r.csv"))))
def test_bad_emulator_options_are_one_line(results, case):
    assert_one_line_error(results[case], *results[case]["expect"])
    assert results["victim"]["text"] == "keep me\n"
