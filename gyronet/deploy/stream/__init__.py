"""Live sensor streams: framings (LP-BUS, CSV lines), a reconnecting serial reader, a sensor emulator.

The framing parsers are pure (bytes in, ``Sample`` or ``Fault`` out, any chunking); only
:mod:`gyronet.deploy.stream.reader` imports ``serial``. The live compensation loop that joins a stream to a
compensator bundle is :mod:`gyronet.deploy.stream.live`. Talking to an LPMS sensor before it streams
(identity, registers, outputs, rate, gyro auto-calibration; both LP-BUS generations) is
:mod:`gyronet.deploy.stream.lpbus_setup`, used by ``stream.py`` and ``record.py`` (:mod:`.record`).
"""
from typing import Iterable

from gyronet.deploy.stream.csvline import CsvLineParser, encode_csv_header, encode_csv_line, parse_number
from gyronet.deploy.stream.emulator import FaultPlan, StreamPlan, plan_stream
from gyronet.deploy.stream.events import FAULT_REASONS, Fault, FaultCounter, Sample, SampleCheck
from gyronet.deploy.stream.lpbus import LpBusParser, encode_lpbus, lpbus_frame, lrc
from gyronet.deploy.stream.lpbus_layout import DEFAULT_FIELDS, FIELDS, LpBusLayout
from gyronet.deploy.stream.reader import DEFAULT_BAUD, PortError, open_port, read_samples

__all__ = [
    "CsvLineParser", "encode_csv_header", "encode_csv_line", "parse_number",
    "FaultPlan", "StreamPlan", "plan_stream",
    "FAULT_REASONS", "Fault", "FaultCounter", "Sample", "SampleCheck",
    "LpBusParser", "encode_lpbus", "lpbus_frame", "lrc",
    "DEFAULT_FIELDS", "FIELDS", "LpBusLayout",
    "DEFAULT_BAUD", "PortError", "open_port", "read_samples",
    "make_parser",
]


def make_parser(protocol: str, layout: LpBusLayout | None = None, required: Iterable[str] = (),
                check: SampleCheck | None = None) -> LpBusParser | CsvLineParser:
    """The parser for ``protocol`` (``"lpbus"`` or ``"csv"``).

    ``required``: the columns a CSV header must carry (the consumer's inputs); ``check``: the
    time and value checks (default ``SampleCheck()``).
    """
    if protocol == "lpbus":
        return LpBusParser(layout, check=check)
    if protocol == "csv":
        return CsvLineParser(required=required, check=check)
    raise ValueError(f"protocol must be 'lpbus' or 'csv', got {protocol!r}")
