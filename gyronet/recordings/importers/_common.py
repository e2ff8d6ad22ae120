"""What every importer shares: unit names, reading a text header, and turning columns into a Recording.

``finish`` is the one place where rows are dropped: rows with NaN or inf in a kept column and rows
that repeat the previous time stamp. Each drop is counted by reason, logged in one line and written
to the metadata (``dropped_rows``, ``dropped_detail``), so that nothing disappears silently. Time
that goes backwards is not a row to drop but a broken file: it raises a ``RecordingError``.
"""
from __future__ import annotations

import hashlib
import io
import logging
import re
from pathlib import Path
from typing import Mapping

import numpy as np

from gyronet.recordings.csvtable import read_preamble, read_source, to_utf8
from gyronet.recordings.data import BREAK_FACTOR, GYRO_COLUMNS, REQUIRED_COLUMNS, Recording
from gyronet.errors import RecordingError

log = logging.getLogger(__name__)

STANDARD_GRAVITY_M_S2 = 9.80665  # CGPM 1901; m/s^2 per g
ACC_COLUMNS = ("acc_x_g", "acc_y_g", "acc_z_g")
# a record is "regular" when this share of in-burst intervals is within 10 % of the median
REGULAR_SHARE = 0.9


def fahrenheit_to_c(temp_f: np.ndarray) -> np.ndarray:
    """degF -> degC."""
    # T_c = (T_f - 32) * 5 / 9
    return (np.asarray(temp_f, dtype=np.float64) - 32.0) * 5.0 / 9.0


def snake(text: str) -> str:
    """A header fragment as a snake_case name part: ``'LinAccX'`` -> ``'lin_acc_x'``, ``'m/s^2'`` -> ``'m_s2'``."""
    text = text.replace("µ", "u").replace("°", "deg").replace("%", "pct")
    text = re.sub(r"([a-z0-9])([A-Z])", r"\1_\2", text)
    text = re.sub(r"[^A-Za-z0-9]+", "_", text).strip("_").lower()
    return text or "unnamed"


def read_text(path: Path) -> bytes:
    """The file as UTF-8 bytes with ``\\n`` line ends (gunzipped, UTF-16 transcoded); see ``gyronet.recordings.csvtable``."""
    return to_utf8(read_source(path), path)


def read_header_line(path: Path, text: bytes | None = None) -> tuple[int, str]:
    """The first line that is neither blank nor a ``#`` comment: (1-based line number, text)."""
    _, line_no, header, _ = read_preamble(read_text(path) if text is None else text, path)
    return line_no, header


def read_numeric_table(path: Path, header_line: int, names: list[str], delimiter: str = ",",
                       decimal: str = ".") -> tuple[dict[str, np.ndarray], int]:
    """Read the rows under a header as float64 columns (quoted cells as pandas reads them).

    A non-numeric cell raises a ``RecordingError`` naming its line and column, except on the last
    line: a logger stopped mid-write leaves a cut line, which becomes NaN (dropped and counted later).

    Returns
    -------
    columns, first_data_line
        ``names[i]`` -> values, and the 1-based line number of the first data row.
    """
    import warnings

    import pandas as pd

    text = read_text(path)
    options = dict(skiprows=header_line, header=None, names=names, skipinitialspace=True, sep=delimiter, decimal=decimal,
                   skip_blank_lines=True, encoding="utf-8", encoding_errors="replace", comment=None,
                   index_col=False)
    with warnings.catch_warnings():
        # "Length of header or names does not match length of data": cells beyond the header
        warnings.simplefilter("error", pd.errors.ParserWarning)
        try:
            try:
                frame = pd.read_csv(io.BytesIO(text), dtype=np.float64, **options)
            except ValueError as err:
                if isinstance(err, (pd.errors.ParserError, pd.errors.EmptyDataError)):
                    raise
                frame = pd.read_csv(io.BytesIO(text), dtype=str, keep_default_na=False, **options)
                frame = _coerce_numeric(path, frame, header_line)
        except pd.errors.ParserError as err:
            text = str(err).strip().splitlines()[-1]
            raise RecordingError(f"{path}: malformed row ({text})") from None
        except pd.errors.ParserWarning:
            raise RecordingError(f"{path}: malformed row: the first data row has more cells than the header's "
                                 f"{len(names)}") from None
        except pd.errors.EmptyDataError:
            raise RecordingError(f"{path}: no samples after the header") from None
    if frame.empty:
        raise RecordingError(f"{path}: no samples after the header")
    return {name: frame[name].to_numpy(dtype=np.float64) for name in names}, header_line + 1


def _coerce_numeric(path: Path, frame, header_line: int):
    import pandas as pd

    out = {}
    last = len(frame) - 1
    for name in frame.columns:
        text = frame[name].astype(str).str.strip()
        values = pd.to_numeric(text, errors="coerce")
        bad = np.flatnonzero(values.isna().to_numpy() & (text != "").to_numpy()
                             & ~text.str.lower().isin(["nan", "inf", "-inf", "+inf"]).to_numpy())
        bad = bad[bad != last]
        if bad.size:
            raise RecordingError(f"{path}: line {header_line + 1 + int(bad[0])}: column {name!r}: "
                                 f"non-numeric value {text.iloc[bad[0]][:40]!r}")
        out[name] = values.to_numpy(dtype=np.float64)
    return pd.DataFrame(out)


def file_sha256(path: Path) -> str:
    """sha256 of the source file, so a converted recording names the bytes it came from."""
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def regular_rate_hz(time_s: np.ndarray) -> float | None:
    """The sampling rate if the record is regular (breaks between bursts allowed), else None."""
    if len(time_s) < 3:
        return None
    dt_s = np.diff(time_s)
    median_s = float(np.median(dt_s))
    if median_s <= 0:
        return None
    in_burst = dt_s[dt_s < BREAK_FACTOR * median_s]
    close = np.abs(in_burst - median_s) <= 0.1 * median_s
    if in_burst.size == 0 or close.mean() < REGULAR_SHARE:
        return None
    return 1.0 / float(np.median(in_burst))


def _ordered(columns: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    first = [c for c in REQUIRED_COLUMNS + ACC_COLUMNS if c in columns]
    return {name: columns[name] for name in first + [c for c in columns if c not in first]}


def finish(path: Path, columns: Mapping[str, np.ndarray], meta: Mapping[str, object],
           source_format: str, *, dropped: Mapping[str, int] | None = None,
           row_label: str = "row", first_row: int = 1, sha256: str | None = None) -> Recording:
    """Validate importer output, drop unusable rows (counted), and add the provenance metadata.

    Parameters
    ----------
    path
        The source file (named in errors and in ``source_file``).
    columns
        Column name -> values, all shape (n,), already in contract units.
    meta
        Importer metadata (``sensor``, format-specific keys); provenance keys are added here.
    source_format
        ``psim``, ``lpms``, ``ulog``, ...
    dropped
        Rows the importer already removed, by reason (e.g. ``{"spike": 3}``), counted in the total.
    row_label, first_row
        How errors name a row: ``f"{row_label} {first_row + index}"`` (a CSV line, a message, ...).
    sha256
        The source's hash, when it is not ``path``'s bytes (a bag folder); default: hash ``path``.

    Returns
    -------
    Recording
        Columns in contract order, ``time_s`` strictly increasing, every value finite.

    Raises
    ------
    RecordingError
        A required column is missing, time goes backwards, or no usable row is left.
    """
    counts = {k: int(v) for k, v in (dropped or {}).items() if v}
    columns = {k: np.asarray(v, dtype=np.float64) for k, v in columns.items()}
    missing = [c for c in REQUIRED_COLUMNS if c not in columns]
    if missing:
        raise RecordingError(f"{path}: no {', '.join(missing)} could be made from this file")
    lengths = {len(v) for v in columns.values()}
    if len(lengths) != 1:  # pragma: no cover - importer bug, not user input
        raise ValueError(f"columns of unequal length {sorted(lengths)}")
    index = np.arange(lengths.pop())

    meta_out = {k: str(v) for k, v in meta.items() if v is not None}
    empty = [c for c, v in columns.items() if c not in REQUIRED_COLUMNS and v.size and np.isnan(v).all()]
    for name in empty:
        del columns[name]
    if empty:
        log.info("%s: dropped column(s) with no value in any row: %s", path.name, ", ".join(empty))
        meta_out["dropped_columns"] = ";".join(empty)

    finite = np.logical_and.reduce([np.isfinite(v) for v in columns.values()])
    counts["nan"] = counts.get("nan", 0) + int((~finite).sum())
    columns = {k: v[finite] for k, v in columns.items()}
    index = index[finite]

    time_s = columns["time_s"]
    step_s = np.diff(time_s)
    back = np.flatnonzero(step_s < 0)
    if back.size:
        row = int(back[0]) + 1
        raise RecordingError(
            f"{path}: {row_label} {first_row + int(index[row])}: time {time_s[row]!r} s goes back "
            f"(previous {time_s[row - 1]!r} s); the file mixes records or is not in time order")
    keep = np.concatenate([[True], step_s > 0])
    counts["duplicate_time"] = counts.get("duplicate_time", 0) + int((~keep).sum())
    if (~keep).sum() > 0.01 * len(keep):  # not a stray repeat: stamps too coarse for the rate (a float32 clock)
        log.warning("%s: %d of %d rows repeat the time stamp before them and are dropped: the stamps are too "
                    "coarse for the rate (a float32 time after hours?); the rate written from them is wrong",
                    path.name, int((~keep).sum()), len(keep))
    columns = {k: v[keep] for k, v in columns.items()}
    if len(columns["time_s"]) == 0:
        raise RecordingError(f"{path}: no usable sample (every row was dropped: {_detail(counts)})")

    total = sum(counts.values())
    rate_hz = regular_rate_hz(columns["time_s"])
    meta_out = {"source_format": source_format, "source_file": path.name,
                "source_sha256": sha256 or file_sha256(path), **meta_out}
    if rate_hz is not None:
        meta_out["fs_hz"] = f"{rate_hz:.6g}"
    meta_out["dropped_rows"] = str(total)
    if total:
        meta_out["dropped_detail"] = _detail(counts)
    log.info("%s (%s): %d samples kept, %d row(s) dropped%s", path.name, source_format,
             len(columns["time_s"]), total, f" ({_detail(counts)})" if total else "")
    return Recording(_ordered(columns), meta_out, str(path))


def _detail(counts: Mapping[str, int]) -> str:
    return ";".join(f"{k}:{v}" for k, v in counts.items() if v) or "none"


def degrees(rate_rad_s: np.ndarray) -> np.ndarray:
    """rad/s -> deg/s."""
    return np.degrees(np.asarray(rate_rad_s, dtype=np.float64))


__all__ = ["ACC_COLUMNS", "GYRO_COLUMNS", "STANDARD_GRAVITY_M_S2", "degrees", "fahrenheit_to_c",
           "file_sha256", "finish", "read_header_line", "read_numeric_table", "read_text", "regular_rate_hz",
           "snake"]
