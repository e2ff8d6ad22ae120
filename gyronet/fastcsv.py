"""A fast CSV writer for long numeric columns, in the format of :func:`gyronet.data.write_recording`.

``pandas.DataFrame.to_csv`` with ``float_format="%.9g"`` formats one cell at a time (about
25 s for the paper profile's recording and truth, 12 s for a 3.6 M-sample compensated file).
Here each column is written in fixed point with enough decimals for ``significant`` digits of
its largest value, by vectorised digit extraction into a byte matrix whose padding is then
dropped: about ten times faster. Leading and trailing zeros are dropped, so ``0.5`` is ``0.5``
and ``12.0`` is ``12``.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Mapping

import numpy as np

_PAD, _MINUS, _DOT, _COMMA, _NEWLINE, _ZERO = 0, ord("-"), ord("."), ord(","), ord("\n"), ord("0")
_MAX_DECIMALS = 15
_ROWS_PER_BLOCK = 32768


def _layout(values: np.ndarray, significant: int) -> tuple[int, int]:
    """(decimals, integer digits) that give ``significant`` digits to the column's largest value."""
    largest = float(np.max(np.abs(values))) if values.size else 0.0
    if largest == 0.0:
        return 0, 1
    decimals = int(np.clip(significant - 1 - np.floor(np.log10(largest)), 0, _MAX_DECIMALS))
    integer = int(np.rint(largest * 10.0**decimals)) // 10**decimals
    return decimals, len(str(integer))


def _field(values: np.ndarray, decimals: int, int_digits: int, separator: int) -> np.ndarray:
    """One column as a byte matrix (n, width), padded with zero bytes."""
    n = len(values)
    scaled = np.rint(np.abs(values) * 10.0**decimals).astype(np.int64)
    width = 1 + int_digits + (1 + decimals if decimals else 0) + 1
    out = np.zeros((n, width), dtype=np.uint8)
    out[:, 0] = np.where((values < 0) & (scaled > 0), _MINUS, _PAD)
    digit_cols = list(range(1, 1 + int_digits))
    if decimals:
        digit_cols += list(range(2 + int_digits, 2 + int_digits + decimals))
    remainder = scaled
    for col in reversed(digit_cols):  # least significant digit first
        quotient = remainder // 10
        out[:, col] = remainder - 10 * quotient
        remainder = quotient
    if decimals:
        fraction = out[:, 2 + int_digits:2 + int_digits + decimals]
        keep = np.logical_or.accumulate(fraction[:, ::-1] > 0, axis=1)[:, ::-1]  # no trailing zeros
        out[:, 1 + int_digits] = np.where(keep[:, 0], _DOT, _PAD)
        fraction[...] = np.where(keep, fraction + _ZERO, _PAD)
    integer = out[:, 1:1 + int_digits]
    keep = np.logical_or.accumulate(integer > 0, axis=1)  # no leading zeros, but keep a last 0
    keep[:, -1] = True
    integer[...] = np.where(keep, integer + _ZERO, _PAD)
    out[:, -1] = separator
    return out


def format_rows(columns: Mapping[str, np.ndarray], significant: int = 9) -> bytes:
    """The data rows of a CSV of ``columns`` (no header), ``\\n``-terminated."""
    arrays = [np.asarray(v, dtype=float) for v in columns.values()]
    layouts = [_layout(a, significant) for a in arrays]
    separators = [_COMMA] * (len(arrays) - 1) + [_NEWLINE]
    blocks = []
    for start in range(0, len(arrays[0]), _ROWS_PER_BLOCK):
        stop = start + _ROWS_PER_BLOCK
        matrix = np.concatenate([_field(a[start:stop], d, w, s)
                                 for a, (d, w), s in zip(arrays, layouts, separators)], axis=1)
        blocks.append(matrix.tobytes().translate(None, b"\x00"))
    return b"".join(blocks)


def write_csv(path: str | os.PathLike, columns: Mapping[str, np.ndarray],
              meta: Mapping[str, object] | None = None, significant: int = 9) -> Path:
    """Write ``# key=value`` lines, a header and the rows; columns must be finite and equal length."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    lengths = {len(v) for v in columns.values()}
    if len(lengths) != 1:
        raise ValueError(f"columns have different lengths: {sorted(lengths)}")
    if not all(np.all(np.isfinite(v)) for v in columns.values()):
        raise ValueError("columns must be finite")
    head = "".join(f"# {k}={v}\n" for k, v in (meta or {}).items()) + ",".join(columns) + "\n"
    with open(path, "wb") as handle:
        handle.write(head.encode("utf-8"))
        handle.write(format_rows(columns, significant))
    return path
