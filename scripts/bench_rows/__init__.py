"""The rows of scripts/bench.py, one module per topic; importing this package registers them all.

The registry and helpers are in :mod:`.harness`; ``probe.py`` is a script the ``stream_pty`` row runs.
"""
from . import reference, training, offline, live, memory, live_csv  # noqa: F401  (registration order = default run order)
from . import c_export  # noqa: F401  (the C99 compensator, format=c)
from .harness import BENCHES, LONG, Context

__all__ = ["BENCHES", "LONG", "Context"]
