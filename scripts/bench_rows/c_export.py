"""The C99 compensator (format=c): its cost per sample against compensate.py's Python path, and its code size."""
from __future__ import annotations

import re
import shutil
import subprocess
import time
from typing import Any

import numpy as np

from .harness import Context, bench, paper_recording, row, timed, trained_bundle

NS_GOAL_PER_SAMPLE = 2000.0  # under 2 us a sample
FLASH_GOAL_BYTES = 8192  # text + data of the object file, default model
CFLAGS = ["-std=c99", "-Wall", "-Wextra", "-Werror", "-pedantic"]
LIVE_SAMPLES = 2000


def _size_bytes(size_tool: str, obj) -> int:
    """text + data of an object file (flash), from binutils' ``size``."""
    out = subprocess.run([size_tool, str(obj)], capture_output=True, text=True, check=True).stdout.splitlines()
    text, data = out[1].split()[:2]
    return int(text) + int(data)


@bench("c_compensator")
def c_compensator(ctx: Context) -> dict[str, Any]:
    """The generated C (-O2), default bundle, paper recording, against Compensator.process; goals < 2 us, < 8 KB."""
    from gyronet.bundle.compensator import Compensator
    from gyronet.recordings.data import GYRO_COLUMNS, load_recording
    from gyronet.deploy.c_export import DRIVER, write_c

    cc, size_tool = shutil.which("cc") or shutil.which("gcc"), shutil.which("size")
    if cc is None or size_tool is None:
        raise RuntimeError("needs a C compiler (cc) and binutils' size")
    bundle = trained_bundle(ctx, "default")
    work = ctx.path("c_export")
    shutil.rmtree(work, ignore_errors=True)
    summary = write_c(bundle, work / "c")
    sizes = {}
    for opt in ("-O2", "-Os"):
        obj = work / f"gyronet_compensator{opt}.o"
        subprocess.run([cc, *CFLAGS, opt, "-c", str(work / "c" / "gyronet_compensator.c"), "-o", str(obj)], check=True)
        sizes[opt] = _size_bytes(size_tool, obj)
    driver = work / "driver"
    subprocess.run([cc, *CFLAGS, "-O2", "-I", str(work / "c"), str(DRIVER), str(work / "gyronet_compensator-O2.o"),
                    "-lm", "-o", str(driver)], check=True)

    recording = load_recording(paper_recording(ctx))
    columns = recording.columns
    n = len(recording)
    names = ["time_s", "temp_c", *GYRO_COLUMNS]
    np.savetxt(work / "in.csv", np.column_stack([columns[c] for c in names]), delimiter=",", fmt="%.17g",
               header=",".join(names), comments="")
    proc = subprocess.run([str(driver), str(work / "in.csv"), str(work / "out.csv"), "5"], capture_output=True,
                          text=True, check=True)
    c_ns = float(re.search(r"ns_per_sample=([0-9.]+)", proc.stderr).group(1))

    compensator = Compensator.load(bundle)

    def batch():
        compensator.reset()
        return compensator.process(columns)

    batch_s, expected = timed(batch, repeat=3)
    c_out = np.loadtxt(work / "out.csv", delimiter=",", skiprows=1)
    max_diff = float(np.abs(c_out[:, :3] - expected.rate_dps).max())
    compensator.reset()  # live: one sample a call, as stream.py does
    singles = [{k: v[i:i + 1] for k, v in columns.items()} for i in range(min(LIVE_SAMPLES, n))]
    start = time.perf_counter()
    for sample in singles:
        compensator.process(sample)
    live_ns = 1e9 * (time.perf_counter() - start) / len(singles)
    batch_ns = 1e9 * batch_s / n
    flash = sizes["-O2"]
    notes = (f"{n} samples: C {c_ns:.0f} ns/sample (goal < 2 us: {'met' if c_ns < NS_GOAL_PER_SAMPLE else 'NOT met'}) "
             f"vs Compensator.process {batch_ns:.0f} ns/sample batch (compensate.py; C/Python {c_ns / batch_ns:.2f}), "
             f"{live_ns / 1e3:.0f} us one sample a call (stream.py; C/Python {c_ns / live_ns:.4f}); object "
             f"text+data {flash} B at -O2, {sizes['-Os']} B at -Os (goal < 8 KB: "
             f"{'met' if flash < FLASH_GOAL_BYTES else 'NOT met'}); state {summary['state_bytes']} B; "
             f"max |C - Python| {max_diff:.2g} deg/s")
    return row("c_compensator", c_ns * 1e-9 * n, batch_s, notes, n_samples=n, c_ns_per_sample=c_ns,
               python_batch_ns_per_sample=batch_ns, python_live_ns_per_sample=live_ns,
               ratio_live=c_ns / live_ns, flash_bytes=sizes, state_bytes=summary["state_bytes"],
               max_diff_dps=max_diff, compiler=subprocess.run([cc, "--version"], capture_output=True,
                                                              text=True).stdout.splitlines()[0])
