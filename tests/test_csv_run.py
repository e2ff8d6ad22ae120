"""The CSV flood path (``CsvLineParser(blocks=True)``, :mod:`gyronet.deploy.stream.csv_run`) against the per-line path.

A stream of good lines with damage of every kind (flipped bytes, cut lines, garbage, cells too
many or too few, not numbers the way ``float`` would take them, time going back a little and a
lot, jumping ahead, NaN and overflow, repeated, cut and new headers, comments, blank lines,
``\\r\\n`` endings, lines too long) is fed in random chunk sizes to both parsers. Taken apart into
samples, the flood path's output must be the per-line path's: the same samples and faults in the
same order, every value the same float64 to the bit, and the check and the headers left in the
same state.
"""
import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gyronet.deploy.stream import CsvLineParser, Fault, Sample, SampleCheck, encode_csv_header
from gyronet.deploy.stream.csv_run import MIN_RUN_LINES, LineRun
from gyronet.deploy.stream.events import SampleBlock, as_samples

NAMES = ["time_s", "temp_c", "gyro_x_dps", "gyro_y_dps", "gyro_z_dps", "acc_x_g"]
NEEDED = NAMES[:5]
MAX_LINE_BYTES = 300
DAMAGE = ["flip", "cut", "cut_keep_end", "extra_cell", "missing_cell", "junk", "back_small", "back_large", "jump",
          "nan", "overflow", "spaces", "long_digits", "underscore", "double_point", "empty_cell", "lone_sign",
          "header", "new_header", "header_cut", "comment", "blank", "crlf", "bare_cr", "long_line", "non_ascii",
          "plus_point", "exponent", "header_pair"]


def key(item) -> tuple:
    """What must match exactly: floats by their bits (``hex`` tells -0.0 from 0.0)."""
    if isinstance(item, Fault):
        return ("fault", item.reason, item.raw, item.detail)
    assert isinstance(item, Sample)
    return ("sample", item.time_s.hex(), tuple((k, v.hex()) for k, v in item.values.items()), item.new_segment)


def cell_text(value: float, rng: np.random.Generator) -> str:
    """A number as a sensor might print it: few digits, full repr, or an exponent."""
    form = rng.integers(4)
    if form == 0:
        return f"{value:.4f}"
    if form == 1:
        return repr(value)
    if form == 2:
        return f"{value:.3e}"
    return f"{value:.9g}"


def damaged_stream(rng: np.random.Generator, n_lines: int, damage_rate: float, crlf: bool = False) -> bytes:
    """A header and ``n_lines`` lines 1 ms apart, each damaged with probability ``damage_rate`` by one of ``DAMAGE``."""
    end = "\r\n" if crlf else "\n"
    header = ",".join(NAMES) + end
    pieces, time_s = [header], 100.0
    for _ in range(n_lines):
        time_s += 1e-3
        cells = [repr(time_s)] + [cell_text(float(v), rng) for v in rng.normal(0.0, 10.0, len(NAMES) - 1)]
        line = ",".join(cells) + end
        kind = DAMAGE[rng.integers(len(DAMAGE))] if rng.random() < damage_rate else None
        at = int(rng.integers(1, len(cells)))  # a cell other than time_s
        if kind == "flip":
            data = bytearray(line.encode())
            i = int(rng.integers(len(data)))
            data[i] ^= 1 << int(rng.integers(8))
            pieces.append(data.decode("latin-1"))
            continue
        if kind == "cut":
            line = line[:rng.integers(1, len(line))]
        elif kind == "cut_keep_end":
            line = line[:rng.integers(0, len(line) - len(end))] + end
        elif kind == "extra_cell":
            line = line[:-len(end)] + ",1.5" + end
        elif kind == "missing_cell":
            line = ",".join(cells[:-1]) + end
        elif kind == "junk":
            pieces.append(rng.integers(0, 256, rng.integers(1, 40), dtype=np.uint8).tobytes().decode("latin-1"))
        elif kind in ("back_small", "back_large", "jump"):
            step_s = {"back_small": -0.5, "back_large": -5.0, "jump": 7200.0}[kind]
            line = ",".join([repr(time_s + step_s)] + cells[1:]) + end
            time_s = time_s if kind == "back_small" else time_s + step_s
        elif kind in ("nan", "overflow", "spaces", "long_digits", "underscore", "double_point", "empty_cell",
                      "lone_sign", "plus_point", "exponent"):
            cells[at] = {"nan": "nan", "overflow": "1e999", "spaces": " 1.25", "long_digits": "0.1234567890123456789",
                         "underscore": "1_0", "double_point": "1.2.3", "empty_cell": "", "lone_sign": "-",
                         "plus_point": "+.5", "exponent": "-7E+2"}[kind]
            line = ",".join(cells) + end
        elif kind == "header":
            pieces.append(header)
        elif kind == "new_header":  # a new column, and some lines that fit it (or none: a stray)
            pieces.append(",".join([*NAMES, "vdd_v"]) + end)
            for _ in range(rng.integers(0, 2 * MIN_RUN_LINES)):
                time_s += 1e-3
                pieces.append(",".join([repr(time_s), *cells[1:], "3.3"]) + end)
        elif kind == "header_pair":  # a new header, then the old one again before any line: the new one a stray
            pieces += [",".join([*NAMES, "vdd_v"]) + end, header]
        elif kind == "header_cut":
            pieces.append(header[:rng.integers(1, len(header) - 1)] + end)
        elif kind == "comment":
            pieces.append("# note" + end)
        elif kind == "blank":
            pieces.append(end)
        elif kind == "crlf":
            line = line.rstrip("\r\n") + "\r\n"
        elif kind == "bare_cr":
            line = line[:5] + "\r" + line[5:]
        elif kind == "long_line":
            cells[at] = "1" + "0" * MAX_LINE_BYTES
            line = ",".join(cells) + end
        elif kind == "non_ascii":
            line = line[:-len(end)] + "\u00b0" + end
        pieces.append(line)
    return "".join(pieces).encode("latin-1")


def parse(stream: bytes, cuts: list[int], blocks: bool) -> tuple[list, CsvLineParser]:
    check = SampleCheck(restart_back_s=1.0, restart_jump_s=3600.0)
    parser = CsvLineParser(MAX_LINE_BYTES, required=NEEDED, check=check, blocks=blocks)
    out, start = [], 0
    for stop in [*cuts, len(stream)]:
        out += parser.feed(stream[start:stop])
        start = stop
    return out + parser.flush(), parser


def state(parser: CsvLineParser) -> tuple:
    previous = parser._previous.cells if parser._previous is not None else None
    return parser.check.last_time_s, parser.check.n_restarts, parser.header, previous


def assert_same(stream: bytes, cuts: list[int]) -> list:
    """Both paths on ``stream`` cut at ``cuts``; returns the flood path's raw output."""
    per_line, slow = parse(stream, cuts, blocks=False)
    flood, fast = parse(stream, cuts, blocks=True)
    assert [key(item) for item in as_samples(flood)] == [key(item) for item in per_line]
    assert state(fast) == state(slow)
    return flood


def random_cuts(rng: np.random.Generator, n_bytes: int, max_read: int) -> list[int]:
    cuts = np.cumsum(rng.integers(1, max_read + 1, size=n_bytes + 1))
    return sorted(cuts[cuts < n_bytes].tolist())


@pytest.mark.parametrize("crlf", [False, True])
@pytest.mark.parametrize("seed", range(3))
def test_flood_path_equals_per_line_path_on_damaged_streams(seed, crlf):
    rng = np.random.default_rng(seed)
    stream = damaged_stream(rng, n_lines=4000, damage_rate=0.02, crlf=crlf)
    flood = assert_same(stream, random_cuts(rng, len(stream), 8000))
    per_line, _ = parse(stream, [], blocks=False)
    # the flood path did the bulk of the work, and most kinds of damage were met
    blocks = [item for item in flood if isinstance(item, SampleBlock)]
    assert sum(map(len, blocks)) > 0.6 * sum(isinstance(item, Sample) for item in per_line) and len(blocks) > 20
    reasons = {item.reason for item in per_line if isinstance(item, Fault)}
    assert {"garbage", "truncated", "bad_field_count", "non_numeric", "nan", "time_not_increasing",
            "bad_header"} <= reasons
    assert any(isinstance(item, Sample) and item.new_segment for item in per_line)
    assert any(isinstance(item, Sample) and "vdd_v" in item.values for item in per_line)  # a new header took
    assert any(isinstance(item, Fault) and item.detail == "no line fitted it" for item in per_line)


def _run_property(max_examples: int) -> None:
    @settings(max_examples=max_examples, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow])
    @given(seed=st.integers(0, 2**32 - 1), damage_rate=st.sampled_from([0.0, 0.01, 0.1, 0.5]),
           max_read=st.sampled_from([1, 50, 4096, 65536]), crlf=st.booleans())
    def one(seed, damage_rate, max_read, crlf):
        rng = np.random.default_rng(seed)
        stream = damaged_stream(rng, n_lines=int(rng.integers(1, 400)), damage_rate=damage_rate, crlf=crlf)
        assert_same(stream, random_cuts(rng, len(stream), max_read))

    one()


def test_flood_path_equals_per_line_path_for_any_damage_and_chunking():
    _run_property(settings().max_examples)


@pytest.mark.slow
def test_flood_path_equals_per_line_path_larger_budget():
    _run_property(400)


def test_a_run_stops_at_the_first_bad_line_and_resumes_after_it():
    lines = [f"{1.0 + i / 1000!r},25.0,0.5,-0.25,1e-3,0.0\n".encode() for i in range(3 * MIN_RUN_LINES)]
    lines[MIN_RUN_LINES + 3] = lines[MIN_RUN_LINES + 3].replace(b"0.5", b"0.5x")
    stream = encode_csv_header(NAMES) + b"".join(lines)
    out, _ = parse(stream, [], blocks=True)
    assert [type(item).__name__ for item in out] == ["SampleBlock", "Fault", "SampleBlock"]
    assert (len(out[0]), out[1].reason, len(out[2])) == (MIN_RUN_LINES + 3, "non_numeric", 2 * MIN_RUN_LINES - 4)
    assert out[0].columns["gyro_z_dps"][0] == 1e-3 and math.copysign(1.0, out[0].columns["acc_x_g"][0]) == 1.0


def test_fewer_lines_than_a_run_go_line_by_line_and_a_run_needs_a_header():
    stream = encode_csv_header(NAMES) + b"".join(f"{1.0 + i / 1000!r},25,0,0,0,0\n".encode()
                                                 for i in range(MIN_RUN_LINES - 1))
    out, _ = parse(stream, [], blocks=True)
    assert len(out) == MIN_RUN_LINES - 1 and all(isinstance(item, Sample) for item in out)
    headless, _ = parse(stream[stream.index(b"\n") + 1:] * 3, [], blocks=True)
    assert {item.reason for item in headless} == {"no_header"}


def test_values_are_floats_reading_to_the_bit():
    run = LineRun(["time_s", "x"], 100)
    cells = ["-0", "-0.0", "+.5", "5.", "1e22", "1e23", "1e-22", "4.9e-324", "0.1", "123456789012345678",
             "1.7976931348623157e308", "2.2250738585072011e-308", "9007199254740993", "-.0e-0"]
    text = b"".join(f"{i + 1},{c}\n".encode() for i, c in enumerate(cells * MIN_RUN_LINES))
    block, step, _ = run.decode(bytearray(text), 0, SampleCheck())
    assert step == len(text) and len(block) == len(cells) * MIN_RUN_LINES
    assert [v.hex() for v in block.columns["x"][:len(cells)].tolist()] == [float(c).hex() for c in cells]
