"""Fuzzing the recording loader: every damaged file is refused in one line or read exactly right.

Each example is a recording the generator writes itself (its own values, formatted in one of several
ways), wrapped in a variant a user may hand over (CRLF, a BOM, UTF-16, latin-1 comments, gzip, blank
lines, trailing commas, quotes, spaces), then damaged (truncation, random bytes, extra or missing
cells, NaN/inf/empty cells, time that does not increase, a duplicated header name, a repeated header
line, a huge field, a wrong ``# fs_hz``, a damaged gzip stream). The expected outcome comes from a
small reference reader of CONTRACT.md section 1 written here, slow and plain: the loader must refuse
exactly what it refuses, with a one-line ``RecordingError``, and otherwise return exactly its columns
and numbers; without damage, the numbers must be the generator's own. Any other exception fails.
"""
from __future__ import annotations

import collections
import csv
import gzip
import io
import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gyronet.recordings.data import REQUIRED_COLUMNS, load_recording
from gyronet.errors import RecordingError

AUX = ("vdd_v", "board_temp_c", "acc_z_g")
NA = {"", "#N/A", "#N/A N/A", "#NA", "-1.#IND", "-1.#QNAN", "-NaN", "-nan", "1.#IND", "1.#QNAN", "<NA>", "N/A",
      "NA", "NULL", "NaN", "None", "n/a", "nan", "null"}
NUMBER = re.compile(r"[+-]?(((\d+\.?\d*|\.\d+)([eE][+-]?\d+)?)|[iI][nN][fF]([iI][nN][iI][tT][yY])?)")
CONTROL = re.compile(r"[\x00-\x08\x0b\x0c\x0e-\x1f\x7f-\x9f]")
NASTY = [",", "\n", "\r", " ", "\t", "#", "-", "+", ".", "e", "E", "x", "0", "9", "\x00", "\x0b", "ÿ", "°", "n",
         "a", "i", "f", ";"]


# ----------------------------------------------------------------------------- the reference


class Refused(Exception):
    """The reference reader refuses the file."""


def _cell_value(text: str) -> float | None:
    """A cell as the contract reads it: NA spellings are NaN, numbers are numbers, the rest None."""
    text = text.strip(" \t")
    if text in NA:
        return math.nan
    if NUMBER.fullmatch(text) is None:
        return None
    return float(text)


def _shape(cell: str) -> tuple[int, int, int | None]:
    """Characters, significant digits and exponent digits (None: no exponent) of a cell."""
    cell = cell.strip(" \t")
    mantissa, _, exponent = cell.lower().partition("e")
    if not re.fullmatch(r"[+-]?\d*\.?\d*", mantissa) or (exponent and not re.fullmatch(r"[+-]?\d*", exponent)):
        return len(cell), 0, None
    digits = "".join(ch for ch in mantissa if ch.isdigit()).lstrip("0")
    return len(cell), len(digits), (len(exponent.lstrip("+-")) if "e" in cell.lower() else None)


def _looks_cut(cell: str, above: list[str]) -> bool:
    """The contract's rule for an unterminated last cell: shorter than every cell above it (up to 1000) in
    characters, significant digits or exponent digits."""
    if not above:
        return False
    mine, theirs = _shape(cell), [_shape(c) for c in above]
    exponents = [t[2] for t in theirs if t[2] is not None]
    return (mine[0] < min(t[0] for t in theirs) or mine[1] < min(t[1] for t in theirs)
            or (mine[2] is not None and bool(exponents) and mine[2] < min(exponents)))


def reference(text: str, quoted: bool) -> tuple[list[str], dict[str, list[float]], dict[str, str], list[int]]:
    """Read a recording's text: (column names kept, values, metadata, file line of each row)."""
    text = text.replace("\r\n", "\n").replace("\r", "\n")
    lines = text.split("\n")
    meta: dict[str, str] = {}
    for index, line in enumerate(lines):
        stripped = line.strip()
        if CONTROL.search(stripped):
            raise Refused("binary")
        if not stripped:
            continue
        if stripped.startswith("#"):
            key, sep, value = stripped[1:].partition("=")
            if sep:
                meta[key.strip()] = value.strip()
            continue
        header_index = index
        break
    else:
        raise Refused("no header")
    names = [n.strip() for n in (next(csv.reader([lines[header_index].strip()])) if quoted
                                 else lines[header_index].strip().split(","))]
    if len(names) < 2 or len(names) > 10_000:
        raise Refused("header")
    while names and not names[-1]:
        names.pop()
    if any(len(n) > 256 for n in names) or "" in names or len(set(names)) < len(names):
        raise Refused("header names")
    if any(c not in names for c in REQUIRED_COLUMNS):
        raise Refused("missing column")
    body = "\n".join(lines[header_index + 1:])
    if quoted:
        reader = csv.reader(io.StringIO(body), strict=False)
        rows, numbers = [], []
        limit = csv.field_size_limit(len(body) + 1)
        try:
            for row in reader:
                if row and not (len(row) == 1 and not row[0].strip(" \t")):
                    rows.append(row)
                    numbers.append(header_index + 1 + reader.line_num)
        finally:
            csv.field_size_limit(limit)
        terminated = body.rstrip(" \t").endswith("\n") or not rows
    else:
        physical = body.split("\n")
        if physical and physical[-1] == "":
            physical.pop()
        rows, numbers = [], []
        for offset, line in enumerate(physical):
            if line.strip(" \t"):
                rows.append(line.split(","))
                numbers.append(header_index + 2 + offset)
        # the last line with cells ends with a newline (or only blank text follows it)
        terminated = not rows or body.endswith("\n") or not physical[-1].strip(" \t")
    n = len(names)
    if rows and not terminated and (len(rows[-1]) < n or (len(rows[-1]) == n and not rows[-1][-1].strip(" \t"))):
        rows, numbers = rows[:-1], numbers[:-1]  # a last line cut short
    elif rows and not terminated and not quoted and len(rows[-1]) == n and _looks_cut(rows[-1][-1], [
            r[n - 1] for r in rows[-2::-1] if len(r) >= n and r[n - 1].strip(" \t")][:1000]):
        rows, numbers = rows[:-1], numbers[:-1]  # a last line cut inside its last cell
    if not rows:
        raise Refused("no samples")
    for row in rows:
        if len(row) < n or any(c.strip(" \t") for c in row[n:]):
            raise Refused("cells")
    values = {name: [_cell_value(row[i]) for row in rows] for i, name in enumerate(names)}
    kept = []
    for name in names:
        usable = all(v is not None and math.isfinite(v) for v in values[name])
        if name in REQUIRED_COLUMNS and not usable:
            raise Refused(f"bad {name}")
        if usable:
            kept.append(name)
    time_s = values["time_s"]
    if any(b <= a for a, b in zip(time_s, time_s[1:])):
        raise Refused("time")
    if "fs_hz" in meta:
        try:
            declared = float(meta["fs_hz"])
        except ValueError:
            raise Refused("fs_hz") from None
        if not (math.isfinite(declared) and declared > 0):
            raise Refused("fs_hz")
        if len(time_s) > 1:
            measured = 1.0 / float(np.median(np.diff(time_s)))
            if abs(declared - measured) > 0.05 * measured:
                raise Refused("fs_hz")
    return kept, {k: values[k] for k in kept}, meta, numbers


# ----------------------------------------------------------------------------- the generator


@dataclass
class Case:
    names: list[str]
    cells: list[list[str]]  # the formatted cells, row by row, in ``names`` order
    values: dict[str, list[float]]
    meta_lines: list[str]
    variant: dict = field(default_factory=dict)
    damage: list = field(default_factory=list)  # damage to the text or the gzip stream
    damaged: bool = False  # any damage at all, to the text or to the cells

    def __repr__(self) -> str:  # short, for hypothesis' report: a huge field is cut
        cut = [[c if len(c) < 40 else f"{c[:20]}...({len(c)} chars)" for c in row] for row in self.cells]
        return (f"Case(names={self.names}, cells={cut}, meta_lines={self.meta_lines}, variant={self.variant}, "
                f"damage={self.damage})")

    def text(self) -> str:
        quote = self.variant.get("quotes", False)
        space = " " if self.variant.get("spaces") else ""
        trail = self.variant.get("trailing")

        def join(cells):
            cells = [f'"{c}"' if quote else f"{space}{c}{space}" for c in cells]
            return ",".join(cells)

        header = join(self.names) + ("," if trail == "all" else "")
        rows = [join(r) + ("," if trail in ("all", "rows") else "") for r in self.cells]
        blank = self.variant.get("blank")
        if blank is not None:
            rows.insert(blank % (len(rows) + 1), " \t" if blank % 2 else "")
        text = "\n".join([*self.meta_lines, header, *rows]) + "\n"
        for kind, *args in self.damage:
            text = _damage_text(text, kind, args)
        if self.variant.get("crlf"):
            text = text.replace("\n", "\r\n")
        return text

    def data(self) -> bytes:
        text = self.text()
        encoding = self.variant.get("encoding", "utf-8")
        if encoding == "utf-16":
            raw = text.encode("utf-16")  # with its BOM
        elif encoding == "latin-1":
            raw = text.encode("latin-1")
        else:
            raw = (b"\xef\xbb\xbf" if self.variant.get("bom") else b"") + text.encode("utf-8")
        if self.variant.get("gzip"):
            raw = gzip.compress(raw, mtime=0)
            for kind, *args in self.damage:
                if kind == "gzip_cut":
                    raw = raw[:max(0, len(raw) - 1 - args[0] % len(raw))]
                elif kind == "gzip_byte":
                    position = args[0] % len(raw)
                    raw = raw[:position] + bytes([args[1]]) + raw[position + 1:]
        return raw


def _damage_text(text: str, kind: str, args: list) -> str:
    if kind == "truncate":
        return text[:args[0] % (len(text) + 1)]
    if kind == "byte":
        position, char, mode = args[0] % (len(text) + 1), args[1], args[2]
        if mode == "insert":
            return text[:position] + char + text[position:]
        if mode == "delete":
            return text[:position] + text[position + 1:]
        return text[:position] + char + text[position + 1:]
    return text


def _format(value: float, style: int) -> str:
    return (repr(value), f"{value:.9g}", f"{value:.17g}", f"{value:.6e}", f"{value:.3f}")[style]


@st.composite
def cases(draw) -> Case:
    n_rows = draw(st.integers(1, 12))
    aux = draw(st.lists(st.sampled_from(AUX), unique=True, max_size=2))
    names = draw(st.permutations([*REQUIRED_COLUMNS, *aux]))
    notes = draw(st.booleans())
    if notes:
        names = [*names, "notes"]
    fs_hz = draw(st.sampled_from([1.0, 10.0, 50.0, 100.0, 1000.0]))
    t0 = draw(st.sampled_from([0.0, 12.5, 86400.0]))
    finite = st.floats(-1e3, 1e3, allow_nan=False, allow_infinity=False)
    style = draw(st.integers(0, 4))
    columns: dict[str, list[str]] = {"time_s": [repr(t0 + i / fs_hz) for i in range(n_rows)]}
    for name in names:
        if name == "notes":
            columns[name] = [draw(st.sampled_from(["ok", "door open", "°C"])) for _ in range(n_rows)]
        elif name != "time_s":
            columns[name] = [_format(draw(finite), style) for _ in range(n_rows)]
    cells = [[columns[name][i] for name in names] for i in range(n_rows)]
    values = {name: [float(c) for c in columns[name]] for name in names if name != "notes"}
    meta_lines = []
    if draw(st.booleans()):
        meta_lines.append(f"# fs_hz={fs_hz:g}")
    if draw(st.booleans()):
        meta_lines.append("# sensor=bench 3 (°C)")
    variant = {
        "crlf": draw(st.booleans()),
        "encoding": draw(st.sampled_from(["utf-8", "utf-8", "utf-16", "latin-1"])),
        "bom": draw(st.booleans()),
        "gzip": draw(st.booleans()),
        "blank": draw(st.none() | st.integers(0, 20)),
        "trailing": draw(st.sampled_from([None, None, "all", "rows"])),
        "quotes": draw(st.booleans()) and not notes,
        "spaces": draw(st.booleans()),
    }
    case = Case(list(names), cells, values, meta_lines, variant)
    for _ in range(draw(st.integers(0, 2))):
        _draw_damage(draw, case)
    return case


def _draw_damage(draw, case: Case) -> None:
    case.damaged = True
    kind = draw(st.sampled_from(["truncate", "byte", "extra_cell", "missing_cell", "bad_cell", "time", "dup_name",
                                 "repeat_header", "huge", "fs", "gzip"]))
    row = draw(st.integers(0, len(case.cells) - 1))
    column = draw(st.integers(0, len(case.names) - 1))
    if kind == "truncate":
        case.damage.append(("truncate", draw(st.integers(0, 10_000))))
    elif kind == "byte":
        case.damage.append(("byte", draw(st.integers(0, 10_000)), draw(st.sampled_from(NASTY)),
                            draw(st.sampled_from(["insert", "delete", "replace"]))))
        case.variant["quotes"] = False  # the reference splits quoted text with the csv module only
    elif kind == "extra_cell":
        case.cells[row] = case.cells[row][:column] + [draw(st.sampled_from(["7", "", "x"]))] + case.cells[row][column:]
    elif kind == "missing_cell":
        case.cells[row] = case.cells[row][:column] + case.cells[row][column + 1:]
    elif kind == "bad_cell" and column < len(case.cells[row]):  # an earlier missing_cell may have shortened it
        case.cells[row][column] = draw(st.sampled_from(["nan", "NaN", "inf", "-inf", "", "NA", "null", " ", "1e999",
                                                        "abc", "1,5", "0x10", "1_000"]))
    elif kind == "time" and len(case.cells) > 1 and "time_s" in case.names:  # an earlier damage may rename it
        where = case.names.index("time_s")
        row = max(row, 1)
        case.cells[row][where] = case.cells[row - 1][where]
    elif kind == "dup_name":
        case.names[column] = case.names[(column + 1) % len(case.names)]
    elif kind == "repeat_header":
        case.cells.insert(row, list(case.names))
    elif kind == "huge" and column < len(case.cells[row]):  # as bad_cell: the row may be short
        case.cells[row][column] = draw(st.sampled_from(["1" + "0" * 200_000, "x" * 200_000, "0." + "0" * 200_000 + "1"]))
    elif kind == "fs":
        case.meta_lines.append(f"# fs_hz={draw(st.sampled_from(['0', 'nan', 'abc', '-5', '1e9', '']))}")
    elif kind == "gzip":
        case.variant["gzip"] = True
        case.damage.append((draw(st.sampled_from(["gzip_cut", "gzip_byte"])), draw(st.integers(0, 10_000)),
                            draw(st.integers(0, 255))))


# ----------------------------------------------------------------------------- the property


def _expected(case: Case):
    """The reference's reading of the damaged text, or Refused; a damaged gzip stream may be either."""
    try:
        return reference(case.text(), case.variant["quotes"])
    except Refused as refused:
        return refused


def _check(case: Case, path: Path, outcomes: collections.Counter) -> None:
    path.write_bytes(case.data())
    expected = _expected(case)
    gzip_damaged = any(kind.startswith("gzip_") for kind, *_ in case.damage)
    try:
        rec = load_recording(path)
    except RecordingError as err:
        message = str(err)
        assert len(message.splitlines()) == 1 and str(path) in message, message
        assert isinstance(expected, Refused) or gzip_damaged, f"refused a file the reference reads: {message}"
        outcomes["refused"] += 1
        return
    assert not isinstance(expected, Refused), f"read a file the reference refuses ({expected})"
    names, values, meta, numbers = expected
    assert list(rec.columns) == names
    for name in names:
        np.testing.assert_array_equal(rec.columns[name], np.asarray(values[name], dtype=np.float64), err_msg=name)
    assert rec.lines.tolist() == numbers
    assert rec.meta == meta
    if not case.damaged:  # the reference itself agrees with the generator's own numbers
        assert set(names) == set(case.values) and all(values[n] == case.values[n] for n in names)
    outcomes["accepted"] += 1


def _run(tmp_path: Path, max_examples: int) -> collections.Counter:
    outcomes: collections.Counter = collections.Counter()

    @settings(max_examples=max_examples, deadline=None, derandomize=True,
              suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                     HealthCheck.function_scoped_fixture])
    @given(case=cases())
    def one(case: Case) -> None:
        suffix = ".csv.gz" if case.variant.get("gzip") and len(case.damage) % 2 else ".csv"
        _check(case, tmp_path / f"fuzz{suffix}", outcomes)

    one()
    return outcomes


def test_fuzzed_recordings_are_refused_in_one_line_or_read_exactly(tmp_path):
    outcomes = _run(tmp_path, settings().max_examples * 5)
    assert outcomes["refused"] > 0 and outcomes["accepted"] > 0, outcomes


@pytest.mark.slow
def test_fuzzed_recordings_larger_budget(tmp_path):
    outcomes = _run(tmp_path, 1200)
    assert outcomes["refused"] > 40 and outcomes["accepted"] > 40, outcomes


def test_every_variant_without_damage_is_read_as_written(tmp_path):
    base = dict(names=[*REQUIRED_COLUMNS, "vdd_v"], meta_lines=["# fs_hz=10", "# sensor=bench (°C)"])
    cells = [[repr(i / 10), "20.5", "0.25", "-1e-05", "3", "3.3"] for i in range(5)]
    values = {n: [float(r[i]) for r in cells] for i, n in enumerate(base["names"])}
    variants = [{}, {"crlf": True}, {"bom": True}, {"encoding": "utf-16"}, {"encoding": "latin-1"}, {"gzip": True},
                {"blank": 2}, {"blank": 3}, {"trailing": "all"}, {"trailing": "rows"}, {"quotes": True},
                {"spaces": True}, {"crlf": True, "encoding": "utf-16", "gzip": True, "trailing": "all", "blank": 1}]
    for number, variant in enumerate(variants):
        case = Case(base["names"], [list(r) for r in cells], values, base["meta_lines"], {"quotes": False, **variant})
        path = tmp_path / f"v{number}.csv"
        path.write_bytes(case.data())
        rec = load_recording(path)
        assert list(rec.columns) == base["names"], variant
        for name, expected in values.items():
            assert rec.columns[name].tolist() == expected, (variant, name)
