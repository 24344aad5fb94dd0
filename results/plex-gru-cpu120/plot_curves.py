"""Training curves of the 2-hour PLEX-GRU run: python results/plex-gru-cpu120/plot_curves.py"""
import gzip
import json
from pathlib import Path

import numpy as np

from plex_ma.experiments.common import pyplot, save_figure

here = Path(__file__).parent
rows = [json.loads(line) for line in gzip.open(here / "metrics.jsonl.gz", "rt")]
rows = [r for r in rows if r.get("metrics/episodes", 0) > 0]
steps = np.array([r["step"] for r in rows])
plt = pyplot()
fig, axes = plt.subplots(1, 3, figsize=(14, 3.8))
for ax, key, label in zip(axes, ("reward", "metrics/success", "metrics/executor_success"),
                          ("episode reward", "success", "executor success")):
    y = np.array([r.get(key, np.nan) for r in rows], float)
    ax.plot(steps, y, lw=0.5, alpha=0.4)
    w = 25  # moving average over 25 logged updates
    ax.plot(steps[w - 1:], np.convolve(np.nan_to_num(y), np.ones(w) / w, mode="valid"))
    ax.axvline(924_672, color="k", ls=":", lw=1)
    ax.set_xlabel("environment steps")
    ax.set_title(f"{label} (last 100 episodes)", fontsize=10)
    ax.grid(alpha=0.3)
fig.suptitle("PLEX-GRU, cpu preset, 2 hours of training (dotted: resumed after 90 minutes)")
fig.tight_layout()
save_figure(fig, here / "curves.png")
