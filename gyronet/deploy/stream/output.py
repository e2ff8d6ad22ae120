"""The live output CSV and the run summary, written so that a kill or a full disk never leaves half a line.

Each chunk of compensated samples (one sample, or every frame that one read brought) is one
``os.write`` of whole lines on an unbuffered file: a kill (even SIGKILL) leaves complete lines
only, and a write that fails part-way (ENOSPC, EIO) is cut back to its last complete line before
the error is raised. The summary JSON is written to a temporary file and renamed, so it is whole
or absent.

A flood's chunk is formatted column by column: ``repr`` of every float (the shortest text that
reads back as the same float64) was most of the live loop's CPU (3.5 us of ~8 a sample, 8 floats
a row). Where ``orjson`` is installed it writes a column's digits (the same shortest round trip,
about ten times faster), and only where its text is ``repr``'s: finite values from 1e-4 to 1e15
and zeros (a test compares them); ``repr`` writes the others (tiny sigmas, NaN, inf).
"""
from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

try:
    import orjson
except ImportError:  # an optional speed-up: repr alone writes the same bytes
    orjson = None

from gyronet.bundle.compensator import Compensated
from gyronet.bundle.offline import compensated_meta, output_columns
from gyronet.deploy.stream.summary import OutputError, refuse_gzip_name

log = logging.getLogger(__name__)


# one output line from floats, in output_names() order (a test checks it against write's)
_ROW = b"%r,%r,%r,%r,%r,%d,%d,%r,%r,%r\n"
_NO_SIGMA = (float("nan"),) * 3
# orjson writes a float as repr does from ORJSON_LOW (below: 0.00001 for 1e-05) up to ORJSON_HIGH (above: 1e15
# is still positional in both, 1e16 is 1e+16 for repr, 1e16 for orjson; the margin keeps clear of that)
ORJSON_LOW, ORJSON_HIGH = 1e-4, 1e15


def output_names() -> list[str]:
    """The columns of a compensated file, in the offline writer's order."""
    empty = Compensated(np.empty((0, 3)), np.empty((0, 3)), np.empty(0, dtype=bool))
    return list(output_columns(np.empty(0), np.empty(0), empty))


def _float_texts(values: np.ndarray) -> list[bytes]:
    """A column's values as ``repr`` writes them (``%r``), through orjson (at once) where its text is the same."""
    if orjson is None:
        return [b"%r" % value for value in values.tolist()]
    values = np.ascontiguousarray(values, dtype=np.float64)
    texts = orjson.dumps(values, option=orjson.OPT_SERIALIZE_NUMPY)[1:-1].split(b",")
    magnitude = np.abs(values)
    same = ((magnitude >= ORJSON_LOW) & (magnitude < ORJSON_HIGH)) | (values == 0.0)  # NaN is not
    if not same.all():
        for i in np.flatnonzero(~same).tolist():
            texts[i] = b"%r" % float(values[i])
    return texts


def _int_texts(values: np.ndarray) -> list[bytes]:
    """Each integer as ``%d`` writes it."""
    if orjson is None:
        return [b"%d" % value for value in values.tolist()]
    values = np.ascontiguousarray(values, dtype=np.int64)
    return orjson.dumps(values, option=orjson.OPT_SERIALIZE_NUMPY)[1:-1].split(b",")


class LiveWriter:
    """The output CSV, one line per compensated sample, on disk as soon as ``write`` returns.

    Raises
    ------
    OutputError
        When the file cannot be created or written (the file then ends with a complete line).
    """

    def __init__(self, path: str | Path, bundle_dir: str | Path, still_s: float = 0.0, static_rate_dps=None):
        self.path = Path(path)
        self.names = output_names()
        self.n_rows = 0
        self._size = 0
        refuse_gzip_name(self.path)
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._fd: int | None = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o666)
        except OSError as err:
            raise OutputError(f"{self.path}: cannot create the output ({err.strerror or err})") from None
        meta = compensated_meta(bundle_dir, still_s, static_rate_dps)
        header = "".join(f"# {key}={value}\n" for key, value in meta.items()) + ",".join(self.names) + "\n"
        self._write(header.encode("utf-8"), 0)

    def write(self, time_s: np.ndarray, temp_c: np.ndarray, out: Compensated) -> None:
        """Write the compensated samples of ``out`` (one or many) in one ``os.write``."""
        columns = output_columns(np.atleast_1d(time_s), np.atleast_1d(temp_c), out)
        n = len(columns["time_s"])
        if n == 0:
            return
        texts = [_int_texts(columns[name]) if columns[name].dtype.kind in "biu" else _float_texts(columns[name])
                 for name in self.names]
        self._write(b"\n".join(map(b",".join, zip(*texts))) + b"\n", n)

    def write_rows(self, rows: list[tuple]) -> None:
        """A few compensated samples in plain floats, each (time_s, 3 rates, temp_c, out_of_range, bad_input,
        3 drift sigmas): the lines ``write`` makes for them, in one ``os.write``. A row without the sigmas
        (the older 5-tuple, or None for them) writes NaN there, as ``write`` does."""
        self._write(b"".join([_ROW % (float(t), float(x), float(y), float(z), float(temp_c), out_of_range, bad_input,
                                      *(_NO_SIGMA if not sigma or sigma[0] is None else map(float, sigma[0])))
                              for t, (x, y, z), temp_c, out_of_range, bad_input, *sigma in rows]), len(rows))

    def _write(self, data: bytes, n_rows: int) -> None:
        if self._fd is None:
            raise OutputError(f"{self.path}: the output is closed")
        done = 0
        try:
            while done < len(data):
                done += os.write(self._fd, data[done:])
        except OSError as err:
            # whole lines only: keep the complete lines written, cut the part-written one off again
            kept = data.rfind(b"\n", 0, done) + 1
            if kept < done:
                try:
                    os.ftruncate(self._fd, self._size + kept)
                except OSError:  # pragma: no cover - truncating frees space; nothing else to try
                    log.error("%s: could not cut a part-written line off", self.path)
            self._size += kept
            self.n_rows += data.count(b"\n", 0, kept) if n_rows else 0
            self.close()
            raise OutputError(f"{self.path}: cannot write ({err.strerror or err}) after {self.n_rows} rows; "
                              f"the file ends with the last complete row") from None
        self._size += len(data)
        self.n_rows += n_rows

    def close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None
