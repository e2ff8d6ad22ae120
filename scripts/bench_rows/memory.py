"""Memory over long streams: stream.py's RSS over an hour of 1 kHz data, the live Allan monitor's over 30 h.

Both use ``live.py``'s pseudo-terminal pair and 1 kHz recording; the goal is flat memory, not speed.
"""
from __future__ import annotations

import subprocess
import sys
from typing import Any

from .harness import ROOT, Context, bench, row, trained_bundle
from .live import FS_HZ, RSS_GOAL_MB_PER_H, recording_1khz, rss_figures, run_pair


@bench("stream_rss_hour")
def stream_rss_hour(ctx: Context) -> dict[str, Any]:
    """RSS of stream.py against samples over one hour of 1 kHz data, flooded through the pty (goal: flat, < 10 MB/h)."""
    n = ctx.size(int(3600 * FS_HZ), 30_000)
    run = run_pair(ctx, "rss_hour", recording_1khz(ctx, n), trained_bundle(ctx, "default"), "lpbus", 0, n)
    memory = rss_figures(run["rss"])
    rss_mb = run["rss"][1:, 2]
    hours = n / FS_HZ / 3600.0
    notes = (f"{n} samples ({hours:g} h of 1 kHz data) flooded in {run['elapsed_s']:.0f} s, default bundle: RSS "
             f"{memory['rss_start_mb']:.0f} MB at the first row, {rss_mb.max():.0f} MB at most, "
             f"{memory['rss_end_mb']:.0f} MB at the end; growth over the second half "
             f"{memory['rss_growth_mb_per_h']:.1f} MB per hour of data (goal < {RSS_GOAL_MB_PER_H:g}: "
             f"{'met' if memory['rss_growth_mb_per_h'] < RSS_GOAL_MB_PER_H else 'NOT met'}); the live Allan "
             f"history (0.1 s bins, capped at 24 h) grows by about 1 MB per hour of data by design")
    return row("stream_rss_hour", run["elapsed_s"], None, notes, n_samples=n, rss=memory,
               rss_mb_by_rows=[[int(r), float(mb)] for r, _, mb in run["rss"][1::max(1, len(rss_mb) // 60)]])


_HISTORY_SCRIPT = """
import os, sys, time
import numpy as np
from gyronet.deploy.stream.live import LiveAllan
def rss_mb():
    with open("/proc/self/statm") as handle:
        return int(handle.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 1e6
hours, fs_hz = int(sys.argv[1]), 10.0
allan = LiveAllan(None, 60.0, fs_hz)
rate_dps = np.random.default_rng(0).normal(0.0, 0.1, (int(3600 * fs_hz), 3))
rss, reports = [rss_mb()], []
start = time.perf_counter()
for hour in range(hours):
    for i, sample in enumerate(rate_dps):
        allan.add(3600.0 * hour + i / fs_hz, sample)
    rss.append(rss_mb())
    t = time.perf_counter()
    allan.report(step=3600 * (hour + 1))
    reports.append(time.perf_counter() - t)
print(time.perf_counter() - start, *rss, "|", *reports)
"""


@bench("live_allan_history")
def live_allan_history(ctx: Context) -> dict[str, Any]:
    """The live Allan monitor's memory over 30 h of a 10 Hz stream (one 0.1 s bin a sample): bounded by its cap."""
    hours = ctx.size(30, 2)
    proc = subprocess.run([sys.executable, "-c", _HISTORY_SCRIPT, str(hours)], cwd=ROOT, env=ctx.env(),
                          capture_output=True, text=True, check=True)
    head, tail = proc.stdout.split("|")
    elapsed_s, *rss_mb = (float(v) for v in head.split())
    reports_s = [float(v) for v in tail.split()]
    growth = {f"{h}h": round(rss_mb[h] - rss_mb[0], 1) for h in (1, 12, 24, hours) if h <= hours}
    notes = (f"{hours} h of data: RSS growth over the start " + ", ".join(f"{k} +{v} MB" for k, v in growth.items())
             + f" (history capped at 24 h of bins, then halved); one report on the whole history takes "
             f"{1e3 * reports_s[0]:.0f} ms at 1 h, {1e3 * max(reports_s):.0f} ms at most")
    return row("live_allan_history", elapsed_s, None, notes, rss_growth_mb=growth, report_s=reports_s)
