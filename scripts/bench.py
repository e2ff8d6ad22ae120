"""Benchmarks against reference tools: python scripts/bench.py [--only NAME ...] [--json PATH] [--quick] [--full].

Each row is one function registered with ``@bench("name")`` in a module of ``scripts/bench_rows/``
(``harness.py`` holds the registry and the helpers). It gets a :class:`Context` (sizes, a work
folder for generated files) and returns ``row(...)``: ``name``, ``ours_s``, ``reference_s``,
``ratio`` (ours / reference: below 1 is faster than the reference), ``notes`` and any extra
named figures (``samples_per_s``, ``p99_ms``, a breakdown). To add a row, write one more decorated
function. Rows registered with ``long=True`` (the GA sweep) run only when named with ``--only``
or under ``--full``. The harness adds each row's wall time and the 1-minute load average while it
ran (``load_1m``): the machine may be shared, so compare ratios from the same run. Generated data
and results go under ``outputs/bench/`` (not versioned) and are reused between runs. ``--quick``
shrinks every size for a smoke test.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from bench_rows import BENCHES, LONG, Context
from bench_rows.harness import ROOT, LoadSampler


def _table(rows: list[dict[str, Any]]) -> str:
    def fmt(value: Any) -> str:
        return "-" if value is None else f"{value:.3f}" if isinstance(value, float) else str(value)

    header = f"{'name':24} {'ours_s':>9} {'reference_s':>12} {'ratio':>7}  notes"
    lines = [header, "-" * len(header)]
    lines += [f"{r['name']:24} {fmt(r['ours_s']):>9} {fmt(r['reference_s']):>12} {fmt(r['ratio']):>7}  {r['notes']}"
              for r in rows]
    return "\n".join(lines)


def _run(name: str, ctx: Context) -> dict[str, Any]:
    """One row, with its wall time and the load average around it; a failure becomes a FAILED row."""
    start = time.perf_counter()
    with LoadSampler() as load:
        try:
            result = BENCHES[name](ctx)
        except Exception as err:  # one broken row must not hide the others
            result = {"name": name, "ours_s": None, "reference_s": None, "ratio": None,
                      "notes": f"FAILED: {type(err).__name__}: {err}", "failed": True}
    result["row_wall_s"] = round(time.perf_counter() - start, 1)
    result["load_1m"] = {k: round(v, 2) for k, v in load.summary().items()}
    return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", nargs="+", metavar="NAME", choices=sorted(BENCHES),
                        help="run only these rows (default: all but the long ones)")
    parser.add_argument("--full", action="store_true", help=f"also run the long rows ({', '.join(sorted(LONG))})")
    parser.add_argument("--json", type=Path, default=ROOT / "outputs" / "bench" / "bench.json",
                        help="where to write the rows as JSON")
    parser.add_argument("--quick", action="store_true", help="small sizes, for a smoke test")
    parser.add_argument("--work-dir", type=Path, default=ROOT / "outputs" / "bench",
                        help="folder for generated data (reused between runs)")
    parser.add_argument("--list", action="store_true", help="list the rows and exit")
    args = parser.parse_args(argv)
    if args.list:
        print("\n".join(f"{name}{' (long)' if name in LONG else ''}: {(fn.__doc__ or '').strip()}"
                        for name, fn in BENCHES.items()))
        return 0
    ctx = Context(quick=args.quick, work_dir=args.work_dir.resolve())
    ctx.work_dir.mkdir(parents=True, exist_ok=True)
    names = args.only or [name for name in BENCHES if args.full or name not in LONG]
    rows = []
    for name in names:
        rows.append(_run(name, ctx))
        last = rows[-1]
        print(_table([last]).splitlines()[-1] + f"  [load {last['load_1m']['mean']:.1f}]", file=sys.stderr, flush=True)
    print(_table(rows))
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps({"quick": args.quick, "machine": platform.platform(),
                                     "cpu_count": os.cpu_count(), "python": platform.python_version(),
                                     "numpy": np.__version__, "load_avg_at_end": os.getloadavg(),
                                     "rows": rows}, indent=2) + "\n")
    return 1 if any(r.get("failed") for r in rows) else 0


if __name__ == "__main__":
    sys.exit(main())
