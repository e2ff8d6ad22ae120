"""The run summary JSON, written whole or not at all, and the error of every stream output (no torch here).

``record.py`` needs both without the compensator's imports, so they live apart from
:mod:`.output` (which re-exports them).
"""
from __future__ import annotations

import json
import os
from pathlib import Path

from gyronet.errors import GyronetError


class OutputError(GyronetError):
    """The output (or the summary) cannot be written: a full disk, a folder that is not writable."""


def write_summary(path: str | Path, summary: dict) -> None:
    """Write the summary JSON whole (temporary file, then rename).

    Raises
    ------
    OutputError
        When it cannot be written; no partial file is left.
    """
    path = Path(path)
    temporary = path.with_name(path.name + ".tmp")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        temporary.write_text(json.dumps(summary, indent=2) + "\n")
        os.replace(temporary, path)
    except OSError as err:
        try:
            temporary.unlink(missing_ok=True)
        except OSError:  # its folder is not there either
            pass
        raise OutputError(f"{path}: cannot write the summary ({err.strerror or err})") from None


def refuse_gzip_name(path: Path) -> None:
    """A stream's rows reach the disk line by line, as they come: a ``.gz`` name would promise a compression it lacks."""
    if path.name.lower().endswith(".gz"):
        raise OutputError(f"{path}: a stream is written line by line and cannot be gzip-compressed; give a .csv "
                          "name and gzip the file afterwards (a .csv.gz reads back as it is)")
