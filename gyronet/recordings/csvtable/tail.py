"""A file cut inside its last cell: the unterminated last line whose number lost its tail is dropped.

A logger killed mid-write, a copy interrupted, a download cut: the file ends without a line end and
its last number may be a prefix of what was written (``0.99759152`` cut to ``0.99``), a silently
wrong value. A last line with fewer cells, or an empty last cell, is caught by the line's shape
(``gyronet.recordings.csvtable.shape.check_shape``); this module looks at a last line that has every cell.

The rule (the same in the fuzz suite's reference reader): the cell is whole unless it is shorter,
in characters, significant digits or exponent digits, than every one of the same column's cells on
the ``LOOKBACK_ROWS`` lines above it. A complete file that only lacks its final line end therefore
reads whole (its last number is as long as the numbers above it); a cut that leaves a number at
least as long as the shortest above it changes the value by less than that column's own coarsest
rounding, so it is kept. A dropped line is named in one warning and counted (``Table.cut_rows``),
never refused: the rows before it are good samples.
"""
from __future__ import annotations

import logging
import re
from pathlib import Path

log = logging.getLogger(__name__)

LOOKBACK_ROWS = 1000
_MANTISSA = re.compile(r"[+-]?(\d*)\.?(\d*)(?:[eE][+-]?(\d*))?")


def cell_shape(cell: str) -> tuple[int, int, int | None]:
    """(characters, significant digits, exponent digits or None) of a stripped cell."""
    match = _MANTISSA.fullmatch(cell)
    if match is None:
        return len(cell), 0, None
    digits = (match.group(1) + match.group(2)).lstrip("0")
    exponent = match.group(3)
    return len(cell), len(digits), None if exponent is None else len(exponent)


def cut_reason(cell: str, above: list[str]) -> str | None:
    """Why ``cell`` (the unterminated last line's last cell) looks cut, given the cells above it; None: whole."""
    if not above:
        return None
    length, digits, exponent = cell_shape(cell)
    shapes = [cell_shape(c) for c in above]
    if length < min(s[0] for s in shapes):
        return f"{length} characters, the {len(above)} cells above it have at least {min(s[0] for s in shapes)}"
    if digits < min(s[1] for s in shapes):
        return f"{digits} significant digits, the cells above it have at least {min(s[1] for s in shapes)}"
    exponents = [s[2] for s in shapes if s[2] is not None]
    if exponent is not None and exponents and exponent < min(exponents):
        return f"{exponent} exponent digits, the cells above it have at least {min(exponents)}"
    return None


def drop_cut_last_line(path: Path, body: bytes, delimiter: str, n_names: int, first_line: int) -> tuple[bytes, int]:
    """``body`` without its last line if that line ends the file unterminated with a cut last cell; and 0 or 1.

    Parameters
    ----------
    path
        The file, for the warning.
    body
        The table's bytes after the header, ``\\n`` line ends.
    delimiter
        The cell separator.
    n_names
        Columns the header names.
    first_line
        The file line number of the body's first line, for the warning.
    """
    if not body or body.endswith(b"\n") or b'"' in body:
        return body, 0  # terminated, or quoted cells: check_shape and the text path judge those
    start = body.rfind(b"\n") + 1
    cells = body[start:].decode("utf-8", "replace").strip(" \t").split(delimiter)
    if len(cells) != n_names or not cells[-1].strip(" \t"):
        return body, 0  # blank, short or with an empty last cell (check_shape's case), or a delimiter after it
    cell = cells[-1].strip(" \t")
    above, stop = [], start - 1
    while stop > 0 and len(above) < LOOKBACK_ROWS:
        begin = body.rfind(b"\n", 0, stop) + 1
        row = body[begin:stop].decode("utf-8", "replace").strip(" \t").split(delimiter)
        if len(row) >= n_names and row[n_names - 1].strip(" \t"):
            above.append(row[n_names - 1].strip(" \t"))
        stop = begin - 1
    reason = cut_reason(cell, above)
    if reason is None:
        return body, 0
    log.warning("%s: line %d, the last, ends the file without a line end and its last cell %r looks cut (%s): "
                "dropped, the rows before it are read", path, first_line + body.count(b"\n"), cell[:40], reason)
    return body[:start], 1
