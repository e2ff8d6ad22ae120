"""CSV lines against LP-BUS frames flooded through a pty: emulate_sensor.py -> pty -> stream.py, in turns.

The same 1 kHz recording and default bundle as the ``stream_pty`` flood; three runs a round:
LP-BUS (the flood path of frames), CSV lines (the flood path of lines, ``gyronet.deploy.stream.csv_run``)
and CSV lines with that path off (``probe.py stream_per_line``: every line through the per-line
parser, the loop before it). Rounds alternate the three so that a load that comes and goes falls
on all of them; each run's samples/s and its CPU per sample (what the load changes least) are
kept, and the row quotes the best round of each and the ratios within the same round.
"""
from __future__ import annotations

import math
import time
from typing import Any

import numpy as np

from .harness import Context, bench, row, trained_bundle
from .live import recording_1khz, run_pair

CSV_GOAL_IDLE_PER_S = 100_000.0  # issue 24 item 3
CSV_GOAL_LOADED_PER_S = 30_000.0
RUNS = {"lpbus": ("lpbus", None), "csv": ("csv", None), "csv_per_line": ("csv", "stream_per_line")}


def _parse_cpu_us(recording, n_lines: int = 50_000) -> dict[str, dict[str, float]]:
    """In-process, the recording's first ``n_lines`` as the emulator sends them, fed in reads of 4 and 64 KiB to the
    per-line and the block parser in turns: CPU per line, us (best of three)."""
    from gyronet.recordings.data import load_recording
    from gyronet.deploy.stream import CsvLineParser, plan_stream

    columns = {c: v[:n_lines] for c, v in load_recording(recording).columns.items()}
    plan = plan_stream(columns, "csv")
    data = plan.preamble + b"".join(event.data for event in plan.events)
    spent: dict[str, dict[str, float]] = {"per_line": {}, "block": {}}
    for read_bytes in (4096, 65536):
        for _ in range(3):
            for name, blocks in (("per_line", False), ("block", True)):
                parser = CsvLineParser(blocks=blocks)
                start = time.process_time()
                for i in range(0, len(data), read_bytes):
                    parser.feed(data[i:i + read_bytes])
                us = 1e6 * (time.process_time() - start) / n_lines
                key = f"{read_bytes // 1024}k_reads"
                spent[name][key] = min(spent[name].get(key, math.inf), us)
    return spent


@bench("stream_csv_flood")
def stream_csv_flood(ctx: Context) -> dict[str, Any]:
    """CSV lines vs LP-BUS frames flooded through a pty into stream.py, in turns: samples/s (goal CSV >= 100,000/s idle, >= 30,000/s loaded)."""
    n, n_rounds = ctx.size(120_000, 3_000), ctx.size(2, 1)
    bundle = trained_bundle(ctx, "default")
    recording = recording_1khz(ctx, n)
    rounds: list[dict[str, dict[str, float]]] = []
    for i in range(n_rounds):
        figures = {}
        for name, (protocol, mode) in RUNS.items():
            run = run_pair(ctx, f"csv_flood_{name}_{i}", recording, bundle, protocol, 0, n, probe_mode=mode)
            figures[name] = {"samples_per_s": n / run["elapsed_s"], "elapsed_s": run["elapsed_s"],
                             "cpu_us": 1e6 * run["cpu_s"] / n, "parse_us": 1e6 * run["stage_s"]["parse"] / n,
                             "rows_per_write": float(np.mean(run["chunk_rows"]))}
        rounds.append(figures)
    parse_us = _parse_cpu_us(recording, min(n, 50_000))
    best = {name: max(rounds, key=lambda r: r[name]["samples_per_s"])[name] for name in RUNS}
    # the ratios within each round (the same machine state), then the round with the fastest CSV
    top = max(rounds, key=lambda r: r["csv"]["samples_per_s"])
    csv_per_s, lpbus_per_s = top["csv"]["samples_per_s"], top["lpbus"]["samples_per_s"]
    ratios = [{"csv_over_lpbus": r["csv"]["samples_per_s"] / r["lpbus"]["samples_per_s"],
               "csv_over_per_line": r["csv"]["samples_per_s"] / r["csv_per_line"]["samples_per_s"]} for r in rounds]

    def verdict(ok: bool) -> str:
        return "met" if ok else "NOT met"

    def one(name: str, figures: dict[str, float]) -> str:
        return (f"{name} {figures['samples_per_s']:,.0f}/s (CPU {figures['cpu_us']:.1f} us a sample: "
                f"{1e6 / figures['cpu_us']:,.0f}/s of one core; parse {figures['parse_us']:.2f} us; "
                f"{figures['rows_per_write']:.0f} rows a write)")

    notes = "; ".join([
        f"{n} samples of a 1 kHz recording flooded (speed=0), default bundle, resample=true, {n_rounds} round(s) "
        f"of LP-BUS, CSV, CSV line by line in turns",
        "fastest CSV round: " + ", ".join(one(name, top[name]) for name in RUNS),
        f"CSV / LP-BUS in that round {csv_per_s / lpbus_per_s:.2f}, CSV flood / line by line "
        f"{ratios[rounds.index(top)]['csv_over_per_line']:.1f}x; all rounds: " + ", ".join(
            f"CSV {r['csv']['samples_per_s']:,.0f}, LP-BUS {r['lpbus']['samples_per_s']:,.0f}, line by line "
            f"{r['csv_per_line']['samples_per_s']:,.0f}/s" for r in rounds),
        "in-process parse CPU a line (per-line -> block): " + ", ".join(
            f"{key.replace('_', ' ')} {parse_us['per_line'][key]:.1f} -> {parse_us['block'][key]:.1f} us "
            f"({parse_us['per_line'][key] / parse_us['block'][key]:.1f}x)" for key in parse_us["block"]),
        f"goal >= {CSV_GOAL_IDLE_PER_S:,.0f}/s idle: {verdict(csv_per_s >= CSV_GOAL_IDLE_PER_S)}, >= "
        f"{CSV_GOAL_LOADED_PER_S:,.0f}/s loaded: {verdict(csv_per_s >= CSV_GOAL_LOADED_PER_S)} (see load_1m)"])
    return row("stream_csv_flood", top["csv"]["elapsed_s"], top["lpbus"]["elapsed_s"], notes,
               samples_per_s=csv_per_s, reference_samples_per_s=lpbus_per_s, best_by_run=best, rounds=rounds,
               ratios=ratios, parse_cpu_us_per_line=parse_us, n_samples=n)
