"""Draw docs/img/compensation.png from the quick start's outputs (run once by hand, not by the build).

python docs/img/make_compensation.py BUNDLE CYCLE.csv   # e.g. outputs/quickstart/run/compensator outputs/quickstart/cycle.csv
Raw and compensated gyro error (rate minus the simulator's true rate, 60 s means) on the held-out cycle.
"""
import sys
from pathlib import Path

import matplotlib
matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import pandas as pd

from gyronet.bundle.compensator import Compensator

bundle, cycle = sys.argv[1], Path(sys.argv[2])
rec = pd.read_csv(cycle, comment="#")
truth = pd.read_csv(cycle.with_name(cycle.name.replace(".csv", ".truth.csv")), comment="#")
comp = Compensator.load(bundle)
out = comp.process({c: rec[c].to_numpy(float) for c in rec.columns})
block = (rec["time_s"] // 60).to_numpy()
axes = "xyz"
raw = rec[[f"gyro_{a}_dps" for a in axes]].to_numpy() - truth[[f"true_rate_{a}_dps" for a in axes]].to_numpy()
cmp_ = np.asarray(out.rate_dps) - truth[[f"true_rate_{a}_dps" for a in axes]].to_numpy()
g = pd.DataFrame({"b": block, "t": rec["time_s"] / 3600, "T": rec["temp_c"],
                  **{f"raw{a}": raw[:, i] for i, a in enumerate(axes)},
                  **{f"cmp{a}": cmp_[:, i] for i, a in enumerate(axes)}}).groupby("b").mean()
fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(9, 3.4), dpi=90)
colours = {"x": "tab:blue", "y": "tab:orange", "z": "tab:green"}
for a in axes:
    ax1.plot(g["t"], g[f"raw{a}"], color=colours[a], lw=1, alpha=0.45, label=f"raw {a}")
    ax1.plot(g["t"], g[f"cmp{a}"], color=colours[a], lw=1.4, label=f"compensated {a}")
    ax2.plot(g["T"], g[f"raw{a}"], color=colours[a], lw=0.8, alpha=0.45)
    ax2.plot(g["T"], g[f"cmp{a}"], color=colours[a], lw=1.2)
ax1.set_xlabel("time, h")
ax1.set_ylabel("gyro error, deg/s (60 s means)")
ax1.legend(fontsize=7, ncol=2, loc="lower left")
tw = ax1.twinx()
tw.plot(g["t"], g["T"], color="0.5", lw=0.8, ls="--")
tw.set_ylabel("temperature, degC (dashed)", color="0.4")
ax2.set_xlabel("temperature, degC")
ax2.set_title("the same, against temperature", fontsize=9)
ax1.set_title("held-out thermal history (not trained on)", fontsize=9)
fig.tight_layout()
fig.savefig(Path(__file__).with_name("compensation.png"), dpi=90)
