"""A file that already follows CONTRACT.md section 1: loaded and validated as it is.

Spreadsheet dialects of it are read too: ``;`` or tab between cells, decimal commas (``1,5;2,25``),
UTF-16, trailing commas; the converted file is then plain contract CSV.
"""
from __future__ import annotations

import collections
import os
from pathlib import Path

from gyronet.errors import GyronetError
from gyronet.recordings.data import Recording, load_recording

BAD_LINES = ("refuse", "drop")


def import_contract(path: str | os.PathLike, sensor: str | None = None, bad_lines: str = "refuse") -> Recording:
    """Load a conforming recording; its metadata is kept and the provenance keys are added if absent.

    Parameters
    ----------
    path
        A CONTRACT.md CSV (``.csv`` or ``.csv.gz``).
    sensor
        Sets the ``sensor`` metadata when the file has none.
    bad_lines
        ``refuse`` (default) a file with a malformed line, naming it; ``drop`` leaves such lines out, counted in
        ``dropped_rows`` and ``dropped_detail`` (added to those of an earlier conversion).

    Returns
    -------
    Recording
        As ``gyronet.recordings.data.load_recording`` returns it (delimiter and decimal mark sniffed); a file
        converted earlier keeps its ``source_format`` and ``source_file``. Auxiliary columns that
        were not numbers throughout are listed in ``dropped_columns``.

    Raises
    ------
    RecordingError
        Whatever ``load_recording`` finds wrong, in one line.
    """
    if bad_lines not in BAD_LINES:
        raise GyronetError(f"bad_lines={bad_lines!r}: use {' or '.join(BAD_LINES)}")
    recording = load_recording(path, delimiter=None, decimal=None, bad_lines=bad_lines)
    recording.meta.setdefault("source_format", "csv")
    recording.meta.setdefault("source_file", Path(path).name)
    if sensor is not None:
        recording.meta.setdefault("sensor", sensor)
    if recording.dropped:
        recording.meta["dropped_columns"] = ";".join(recording.dropped)
    if bad_lines == "drop":
        _count_dropped(recording.meta, {**recording.dropped_lines, "cut_last_line": recording.cut_rows})
    return recording


def _count_dropped(meta: dict[str, str], counts: dict[str, int]) -> None:
    """Add the lines left out to ``dropped_rows`` / ``dropped_detail``, as every importer records them
    (``gyronet.recordings.importers._common.finish``), so that a re-converted file keeps its earlier count."""
    detail: collections.Counter = collections.Counter()
    for item in filter(None, meta.get("dropped_detail", "").split(";")):
        key, _, value = item.partition(":")
        detail[key] += int(value) if value.isdigit() else 0
    detail.update(counts)
    earlier = meta.get("dropped_rows", "0")
    meta["dropped_rows"] = str((int(earlier) if earlier.isdigit() else 0) + sum(counts.values()))
    if any(detail.values()):
        meta["dropped_detail"] = ";".join(f"{k}:{v}" for k, v in detail.items() if v)
