"""Offline compensation: Compensator.process on a multi-million-sample recording, and compensate.py."""
from __future__ import annotations

import cProfile
import pstats
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from .harness import ROOT, Context, bench, paper_recording, row, run_command, timed, trained_bundle

SAMPLES_GOAL_PER_S = 1e6


def _long_columns(ctx: Context) -> dict[str, np.ndarray]:
    """The paper recording tiled end to end (time keeps increasing, one sample period at each seam)."""
    from gyronet.recordings.data import load_recording

    recording = load_recording(paper_recording(ctx))
    tiles = ctx.size(8, 2)
    period_s = float(np.median(np.diff(recording.time_s)))
    span_s = float(recording.time_s[-1] - recording.time_s[0]) + period_s
    return {name: (np.concatenate([values + k * span_s for k in range(tiles)]) if name == "time_s"
                   else np.tile(values, tiles)) for name, values in recording.columns.items()}


def _long_csv(ctx: Context, columns: dict[str, np.ndarray]) -> Path:
    """The tiled recording as a CSV for compensate.py, written once."""
    from gyronet.recordings.data import write_recording

    path = ctx.work_dir / f"compensate_long_{len(columns['time_s'])}.csv"
    if not path.exists():
        partial = path.with_suffix(".partial")
        period_s = float(columns["time_s"][1] - columns["time_s"][0])
        write_recording(partial, columns, {"fs_hz": f"{1.0 / period_s:g}"})
        partial.replace(path)
    return path


def _breakdown(bundle: Path, columns: dict[str, np.ndarray]) -> dict[str, float]:
    """Best-of-2 seconds in features, the TorchScript model, and the rest of Compensator.process."""
    import torch

    from gyronet.bundle.compensator import CHUNK_ROWS, Compensator

    compensator = Compensator.load(bundle)

    def features() -> np.ndarray:
        compensator.reset()
        return compensator.extractor.process(columns)

    features_s, x = timed(features, repeat=2)
    inputs = torch.from_numpy(x)

    def model(chunk: int) -> None:
        with torch.no_grad():
            for start in range(0, len(inputs), chunk):
                compensator.model(inputs[start:start + chunk])

    model_s, _ = timed(model, CHUNK_ROWS, repeat=2)  # as Compensator.drift calls it
    threads = torch.get_num_threads()
    one_call_s, _ = timed(model, len(inputs), repeat=2)
    torch.set_num_threads(1)
    chunked_1t_s, _ = timed(model, CHUNK_ROWS, repeat=2)
    one_call_1t_s, _ = timed(model, len(inputs), repeat=2)
    torch.set_num_threads(threads)
    return {"features_s": features_s, "model_s": model_s, "model_one_call_s": one_call_s,
            "model_1thread_s": chunked_1t_s, "model_one_call_1thread_s": one_call_1t_s, "torch_threads": threads,
            "chunk_rows": CHUNK_ROWS}


def _profile_top(bundle: Path, columns: dict[str, np.ndarray], n: int = 4) -> list[str]:
    """The functions with the most own time in one process() call, as 'name tottime s'."""
    from gyronet.bundle.compensator import Compensator

    compensator = Compensator.load(bundle)
    profiler = cProfile.Profile()
    profiler.runcall(compensator.process, columns)
    stats = pstats.Stats(profiler).stats  # {(file, line, name): (cc, nc, tottime, cumtime, callers)}
    top = sorted(stats.items(), key=lambda item: -item[1][2])[:n]
    return [f"{Path(f).name}:{line}({name}) {s[2]:.3f} s" for (f, line, name), s in top]


def _io_split(bundle: Path, csv: Path, out_csv: Path) -> dict[str, float]:
    """compensate_file's steps, timed apart in-process: load, compensate, write."""
    from gyronet.bundle.compensator import Compensator
    from gyronet.recordings.data import load_recording
    from gyronet.bundle.offline import compensate_recording, output_columns, write_compensated

    start = time.perf_counter()
    compensator = Compensator.load(bundle)
    recording = load_recording(csv)
    load_s = time.perf_counter() - start
    process_s, out = timed(compensate_recording, compensator, recording)
    write_s, _ = timed(write_compensated, out_csv, output_columns(recording.time_s, recording.temp_c, out), bundle)
    return {"load_s": load_s, "process_s": process_s, "write_s": write_s}


@bench("compensate_batch")
def compensate_batch(ctx: Context) -> dict[str, Any]:
    """Compensator.process on ~3.6 M samples (default bundle) against the PX4 cubic bundle; goal >= 1 M samples/s."""
    from gyronet.bundle.compensator import Compensator

    columns = _long_columns(ctx)
    n = len(columns["time_s"])
    bundles = {model: trained_bundle(ctx, model) for model in ("default", "poly3")}
    process_s = {}
    for model, bundle in bundles.items():
        compensator = Compensator.load(bundle)

        def run() -> None:
            compensator.reset()
            compensator.process(columns)

        process_s[model], _ = timed(run, repeat=3)
    parts = _breakdown(bundles["default"], columns)
    parts["rest_s"] = process_s["default"] - parts["features_s"] - parts["model_s"]
    top = _profile_top(bundles["default"], columns)
    csv = _long_csv(ctx, columns)
    cli_s = {}
    outputs = [ctx.work_dir / f"compensated_{model}.csv" for model in (*bundles, "io_split")]
    try:
        for (model, bundle), output in zip(bundles.items(), outputs):
            cli_s[model] = run_command([sys.executable, str(ROOT / "scripts" / "compensate.py"), f"model={bundle}",
                                        f"input={csv}", f"output={output}",
                                        f"hydra.run.dir={ctx.path('hydra_compensate')}"], ctx)
        io = _io_split(bundles["default"], csv, outputs[-1])
    finally:  # hundreds of MB each, and nothing reads them
        for output in outputs:
            output.unlink(missing_ok=True)
    io_s = io["load_s"] + io["write_s"]
    rate = n / process_s["default"]
    goal = "met" if rate >= SAMPLES_GOAL_PER_S else "NOT met"
    notes = (f"{n} samples ({ctx.size(8, 2)} x paper tiled): {rate / 1e6:.2f} M samples/s (goal >= 1 M/s: {goal}) vs "
             f"poly3 {n / process_s['poly3'] / 1e6:.2f} M/s; process = features {parts['features_s']:.2f} s + model "
             f"{parts['model_s']:.2f} s (in {parts['chunk_rows']}-row chunks, {parts['torch_threads']} torch threads; "
             f"one call on all rows {parts['model_one_call_s']:.2f} s; 1 thread {parts['model_1thread_s']:.2f} s, "
             f"one call {parts['model_one_call_1thread_s']:.2f} s) + rest {parts['rest_s']:.2f} s; compensate.py "
             f"{cli_s['default']:.1f} s (poly3 {cli_s['poly3']:.1f} s), of which I/O ~{io_s:.1f} s "
             f"({io_s / cli_s['default']:.0%}: load {io['load_s']:.1f} s, write {io['write_s']:.1f} s)")
    return row("compensate_batch", process_s["default"], process_s["poly3"], notes, n_samples=n,
               samples_per_s=rate, reference_samples_per_s=n / process_s["poly3"], breakdown_s=parts,
               profile_top=top, cli_s=cli_s["default"], cli_reference_s=cli_s["poly3"],
               cli_ratio=cli_s["default"] / cli_s["poly3"], cli_io_s=io, cli_io_fraction=io_s / cli_s["default"])
