"""glibc's heap in a long live run: freed blocks below the mmap threshold go back to the system when trimmed."""
import json
import subprocess
import sys

import numpy as np
import pytest


HEAP_SCENARIO = """
import json, os
import numpy as np
from gyronet.deploy.stream.allocator import fix_mmap_threshold, trim_heap

def rss_mb():
    with open("/proc/self/statm") as handle:
        return int(handle.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 1e6

fixed = fix_mmap_threshold()  # the live loop's 4 MiB: 1 MB arrays now come from the heap
blocks = []
for _ in range(150):
    blocks.append(np.ones(125_000))  # 1 MB, touched: resident
    blocks.append(np.ones(1000))  # 8 kB above each (numpy caches only smaller), in use after the big ones go
held = rss_mb()
del blocks[::2]
freed = rss_mb()
trim_heap()
print(json.dumps({"fixed": fixed, "held": held, "freed": freed, "trimmed": rss_mb()}))
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's malloc (Linux)")
def test_trim_hands_back_the_free_middle_of_the_heap():
    """What the live Allan monitor's reports and doublings leave: blocks freed below blocks still in use.

    Run in a fresh interpreter: in a test worker, earlier tests leave holes in the heap that serve
    the 8 kB blocks, so the 1 MB ones sit together at its top and go back without a trim.
    """
    done = subprocess.run([sys.executable, "-c", HEAP_SCENARIO], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    rss = json.loads(done.stdout.strip().splitlines()[-1])
    assert rss["fixed"]
    assert rss["held"] - rss["freed"] < 30, f"glibc gave the middle of the heap back without a trim: {rss}"
    assert rss["freed"] - rss["trimmed"] > 100, rss


def test_every_live_allan_report_trims_the_heap_first(monkeypatch):
    """A report falls due every ``every_s`` of data, and it is what leaves the freed blocks."""
    import gyronet.deploy.stream.live_allan as live_allan

    trims = []
    monkeypatch.setattr(live_allan, "trim_heap", lambda: trims.append(True))
    allan = live_allan.LiveAllan(None, 60.0, 10.0)
    time_s = np.arange(0.0, 250.0, 0.1)
    allan.add_many(time_s, np.random.default_rng(0).normal(0.0, 0.1, (len(time_s), 3)))
    assert len(trims) == 4  # at 60, 120, 180 and 240 s
