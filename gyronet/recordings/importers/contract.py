"""A file that already follows CONTRACT.md section 1: loaded and validated as it is.

Spreadsheet dialects of it are read too: ``;`` or tab between cells, decimal commas (``1,5;2,25``),
UTF-16, trailing commas; the converted file is then plain contract CSV.
"""
from __future__ import annotations

import os
from pathlib import Path

from gyronet.recordings.data import Recording, load_recording


def import_contract(path: str | os.PathLike, sensor: str | None = None) -> Recording:
    """Load a conforming recording; its metadata is kept and the provenance keys are added if absent.

    Parameters
    ----------
    path
        A CONTRACT.md CSV (``.csv`` or ``.csv.gz``).
    sensor
        Sets the ``sensor`` metadata when the file has none.

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
    recording = load_recording(path, delimiter=None, decimal=None)
    recording.meta.setdefault("source_format", "csv")
    recording.meta.setdefault("source_file", Path(path).name)
    if sensor is not None:
        recording.meta.setdefault("sensor", sensor)
    if recording.dropped:
        recording.meta["dropped_columns"] = ";".join(recording.dropped)
    return recording
