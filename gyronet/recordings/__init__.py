"""Recordings: the CSV format (CONTRACT.md section 1), fast reading and writing, other tools' formats.

Also which samples may enter a causal state (``guard``, ``skipping``) and the steady sample clock
(``rate_watch``). May import: ``gyronet.errors``, ``gyronet.atomic``.
"""
