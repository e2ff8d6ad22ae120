"""Importers: other people's recordings -> CONTRACT.md section 1 recordings.

One module per format, each a function ``import_<format>(path, **options) -> Recording``:

| format | module | what |
| --- | --- | --- |
| ``psim`` | ``psim`` | the PAN cubesat thermal-vacuum test CSV (shared/data/real/psim-tvc) |
| ``lpms`` | ``lpms`` | LP-Research LPMS log CSV (LPMS-Control, OpenMAT, OpenZen) |
| ``ulog`` | ``ulog`` | PX4 ULog ``.ulg`` (sensor_gyro, sensor_accel, sensor_gyro_fifo) via pyulog |
| ``rosbag`` | ``rosbag`` | ROS 1 ``.bag``, ROS 2 ``.db3``/``.mcap`` or bag folder (sensor_msgs/Imu + Temperature) via rosbags |
| ``csv`` | ``contract`` | a file that already follows the contract |

``import_recording(path, format="auto")`` picks the format from the file (``detect_format``) and
``convert`` writes the result. Every importer adds ``source_format``, ``source_file``,
``source_sha256``, ``sensor``, ``fs_hz`` (when the sampling is regular) and ``dropped_rows`` to the
metadata; see ``gyronet.recordings.importers._common.finish``.
"""
from __future__ import annotations

import inspect
import logging
import os
from pathlib import Path
from typing import Callable, Mapping

from gyronet.recordings.data import Recording, write_recording
from gyronet.errors import GyronetError, RecordingError
from gyronet.recordings.csvtable import other_tool, sniff, split_header
from gyronet.recordings.importers._common import read_header_line, read_text
from gyronet.recordings.importers.contract import BAD_LINES, import_contract
from gyronet.recordings.importers.lpms import import_lpms
from gyronet.recordings.importers.psim import import_psim
from gyronet.recordings.importers.rosbag import import_rosbag, is_rosbag
from gyronet.recordings.importers.ulog import import_ulog, is_ulog

log = logging.getLogger(__name__)

IMPORTERS: dict[str, Callable[..., Recording]] = {
    "psim": import_psim,
    "lpms": import_lpms,
    "ulog": import_ulog,
    "rosbag": import_rosbag,
    "csv": import_contract,
}
FORMATS = tuple(IMPORTERS)
# the values' digits; time_s is written exactly (repr): Unix time with microseconds needs 16 digits
FLOAT_FORMAT = "%.12g"


def detect_format(path: str | os.PathLike) -> str:
    """The format of a file, from its first bytes and header row.

    Raises
    ------
    RecordingError
        When no importer recognises the file.
    """
    path = Path(path)
    if is_rosbag(path):
        return "rosbag"
    if not path.is_file():
        raise RecordingError(f"{path}: no such file")
    if is_ulog(path) or path.suffix.lower() == ".ulg":
        return "ulog"
    if path.name.lower().endswith(".csv.gz"):
        return "csv"
    text = read_text(path)
    _, header = read_header_line(path, text)
    delimiter, _ = sniff(text)
    names = split_header(header, delimiter)  # a quoted header, as the loader reads it
    tool = other_tool(names)
    if tool is not None:
        return tool
    if "time_s" in {n.strip().lower() for n in names}:
        return "csv"
    raise RecordingError(f"{path}: cannot tell the format from the header ({header[:80]!r}); "
                         f"pass format={'|'.join(FORMATS)} (csv: the columns of docs/reference/recording-format.md, any of ',', ';' "
                         "or tab between cells)")


def import_recording(path: str | os.PathLike, format: str = "auto", **options) -> Recording:
    """Read any supported file as a recording.

    Parameters
    ----------
    path
        The source file.
    format
        ``auto`` or one of ``FORMATS``.
    **options
        The chosen importer's keyword arguments (``drop_spikes`` for psim, ``instance`` for ulog, ...).

    Returns
    -------
    Recording
        Contract columns and provenance metadata.

    Raises
    ------
    GyronetError
        An unknown format or option; a ``RecordingError`` for a file that cannot be used.
    """
    name = detect_format(path) if format == "auto" else format
    if name not in IMPORTERS:
        raise GyronetError(f"unknown format {format!r}; use auto or one of {', '.join(FORMATS)}")
    importer = IMPORTERS[name]
    accepted = list(inspect.signature(importer).parameters)[1:]
    unknown = sorted(set(options) - set(accepted))
    if unknown:
        raise GyronetError(f"format {name} has no option {', '.join(unknown)} (it takes {', '.join(accepted)})")
    if format == "auto":
        log.info("%s: detected format %s", Path(path).name, name)
    return importer(path, **options)


def convert(path: str | os.PathLike, output: str | os.PathLike, format: str = "auto",
            **options) -> Recording:
    """Import ``path`` and write it to ``output`` as a CONTRACT.md CSV.

    Parameters
    ----------
    path, format, **options
        As for ``import_recording``.
    output
        The CSV to write, with the provenance as ``# key=value`` lines; nothing is written on error.

    Returns
    -------
    Recording
        What was written.
    """
    recording = import_recording(path, format, **options)
    columns = {**recording.columns, "time_s": [repr(t) for t in recording.time_s.tolist()]}  # every digit
    write_recording(output, columns, recording.meta, float_format=FLOAT_FORMAT)
    log.info("wrote %s: %d samples, columns %s", output, len(recording), ", ".join(recording.columns))
    return recording


def convert_with_options(path: str | os.PathLike, output: str | os.PathLike, format: str = "auto",
                         sensor: str | None = None,
                         options_by_format: Mapping[str, Mapping[str, object]] | None = None,
                         bad_lines: str = "refuse") -> Recording:
    """``convert`` with the options of every format at hand, as ``conf/convert.yaml`` lists them.

    Only the options of the chosen (or detected) format are passed to its importer; ``bad_lines`` (``refuse``
    or ``drop``) only to the contract CSV's (``import_contract``).
    """
    name = detect_format(path) if format == "auto" else format
    if name not in IMPORTERS:
        raise GyronetError(f"unknown format {format!r}; use auto or one of {', '.join(FORMATS)}")
    options = dict((options_by_format or {}).get(name) or {})
    if sensor is not None:
        options["sensor"] = sensor
    if bad_lines not in BAD_LINES:
        raise GyronetError(f"bad_lines={bad_lines!r}: use {' or '.join(BAD_LINES)}")
    if bad_lines != "refuse":
        if name != "csv":
            raise GyronetError(f"bad_lines={bad_lines} is for contract CSVs (format=csv), not format={name}")
        options["bad_lines"] = bad_lines
    return convert(path, output, name, **options)


__all__ = ["FORMATS", "IMPORTERS", "convert", "convert_with_options", "detect_format", "import_contract", "import_lpms",
           "import_psim", "import_recording", "import_rosbag", "import_ulog"]
