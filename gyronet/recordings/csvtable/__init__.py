"""Reading a recording's CSV: bytes to text (``text``), the cells of every line (``shape``), numbers (``table``),
malformed lines left out on request (``badlines``).

``parse_table`` is the entry point (``gyronet.recordings.data.load_recording`` wraps it); the importers use the
text helpers to read other tools' files the same way.
"""
from gyronet.recordings.csvtable.badlines import bad_line, drop_bad_lines
from gyronet.recordings.csvtable.table import NA_TOKENS, Table, parse_table
from gyronet.recordings.csvtable.text import (MAX_COLUMNS, MAX_NAME_CHARS, check_header, other_tool, read_preamble,
                                              read_source, show, sniff, split_header, to_utf8)

__all__ = ["MAX_COLUMNS", "MAX_NAME_CHARS", "NA_TOKENS", "Table", "bad_line", "check_header", "drop_bad_lines",
           "other_tool", "parse_table", "read_preamble", "read_source", "show", "sniff", "split_header", "to_utf8"]
