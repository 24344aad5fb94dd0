"""Table 1, Fig. 4 and Fig. 5a/b (paper section 5): every method at one equal budget.

One command trains every *arm* (a method with its options) for every seed with the
public CLIs, evaluates each run greedily, and writes the table and the figures::

    python -m plex_ma.experiments table1 --budget 100000 --seeds 0 1 2 --jobs 2

* Training: ``python -m plex_ma.train --preset PRESET --method M --seed S --total-steps
  BUDGET --run-dir RUNS/ARM-sS``. Every arm gets the same budget of environment steps
  (executor actions).
* Evaluation: ``python -m plex_ma.evaluate`` on the first ``--eval-episodes`` procgen test
  episodes and the first ``--r2v-episodes`` real-plan (r2v) test episodes.
* Resuming: a run whose evaluation JSON exists is skipped; an interrupted training resumes
  from its checkpoint (the train CLI does that by itself). Re-running the command after a
  crash therefore finishes the job; ``--report-only`` only rebuilds the outputs.

Outputs under ``--out`` (default ``results/table1/``):

* ``table1.json``: per arm, every seed's test metrics and their mean and standard
  deviation (procgen test, close/far, r2v test), and the training steps each seed needed to
  reach each training success of ``--success-levels`` (0.5, the paper's claim, and 0.8),
  plus the configuration and provenance;
* ``table1.md``: the same as Markdown: one table of the means over seeds, one of every seed;
* ``fig4.png``: training reward and success (the last 100 training episodes at each
  logged step) against environment steps, mean over seeds with the seeds' range shaded;
* ``fig5a.png``: PLEX-GRU with and without the ELI (curves and test results);
* ``fig5b.png``: close against far test goals for PLEX-GRU and PPO-GRU;
* ``runs/ARM-sS/``: each run's ``metrics.jsonl.gz``, evaluation JSONs and train log
  (checkpoints stay in ``--runs-dir``, which is not committed).
"""

from __future__ import annotations

import argparse
import gzip
import json
import os
import shutil
import subprocess
import sys
import time
import warnings
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from plex_ma.cli import output_path
from plex_ma.trainers.base import EpisodeStats
from plex_ma.trainers.evaluation import METRICS

from . import repo_root
from .common import machine, mean_sd_se, provenance, pyplot, save_figure, write_json



@dataclass(frozen=True)
class Arm:
    name: str
    label: str  # as the paper's table and figures name it
    train_args: tuple[str, ...]


ARMS: dict[str, Arm] = {a.name: a for a in [
    Arm("plex-gru", "PLEX GRU", ("--method", "plex-gru")),
    Arm("plex-smt", "PLEX SMT", ("--method", "plex-smt")),
    Arm("ppo-gru", "PPO GRU", ("--method", "ppo-gru")),
    Arm("ppo-smt", "PPO SMT", ("--method", "ppo-smt")),
    # the flat GRU agent with the planner's ego map and map encoder: the hierarchy's gain apart from the map's
    Arm("ppo-gru-map", "PPO GRU+map", ("--method", "ppo-gru-map")),
    Arm("plex-gru-noeli", "PLEX GRU, no ELI", ("--method", "plex-gru", "--no-eli")),
    Arm("plex-gru-mix", "PLEX GRU, procgen+r2v", ("--method", "plex-gru", "--scenes", "procgen+r2v")),
]}
DEFAULT_ARMS = ["plex-gru", "plex-smt", "plex-gru-noeli", "ppo-gru", "ppo-smt", "ppo-gru-map"]


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--arms", nargs="+", default=DEFAULT_ARMS, choices=list(ARMS),
                   help="which arms to run (default: the two PLEX and two flat methods, the no-ELI ablation and the map control)")
    p.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2], help="training seeds (>= 3 for the table)")
    p.add_argument("--budget", type=int, default=100_000, help="environment steps per run (equal for every arm)")
    p.add_argument("--preset", default="cpu", choices=["smoke", "cpu", "paper"], help="train preset")
    p.add_argument("--eval-episodes", type=int, default=200, help="procgen test episodes per run")
    p.add_argument("--r2v-episodes", type=int, default=100, help="real-plan test episodes per run (0: skip)")
    p.add_argument("--jobs", type=int, default=1, help="runs trained at the same time")
    p.add_argument("--success-levels", type=float, nargs="+", default=[0.5, 0.8],
                   help="report the training steps each run needs to reach these successes (the paper's claim: 0.5)")
    p.add_argument("--runs-dir", type=output_path(directory=True), default=None,
                   help="where runs and checkpoints go (default: runs/table1 at the repository root)")
    p.add_argument("--report-only", action="store_true", help="only rebuild the table and figures from the runs")
    p.add_argument("--extra", nargs=argparse.REMAINDER, default=[],
                   help="further train CLI options for every run (e.g. --extra --num-envs 8); must come last")


# ---------------------------------------------------------------------------- running
class RunFailed(RuntimeError):
    """A training or evaluation child exited with an error (a stopped training resumes later)."""


def _call(cmd: list[str], log_path: Path, mode: str) -> None:
    """Run a CLI child with its output (and the command, first) in ``log_path``."""
    with open(log_path, mode) as log:
        log.write("$ " + " ".join(cmd[1:]) + "\n")
        log.flush()
        rc = subprocess.run(cmd, stdout=log, stderr=subprocess.STDOUT, cwd=repo_root()).returncode
    if rc != 0:
        raise RunFailed(f"{cmd[2]} exited with status {rc}; its log: {log_path}")


def _run_one(arm: Arm, seed: int, args, run_dir: Path, keep: Path) -> dict:
    """Train (or resume) and evaluate one run; copy its small outputs to ``keep``."""
    py = sys.executable
    keep.mkdir(parents=True, exist_ok=True)
    ckpt = run_dir / "latest.pt"
    done = keep / "eval_test_procgen.json"
    t0 = time.time()
    if not done.is_file():
        cmd = [py, "-m", "plex_ma.train", "--preset", args.preset, *arm.train_args, "--seed", str(seed),
               "--total-steps", str(args.budget), "--run-dir", str(run_dir), "--no-progress",
               "--keep-checkpoints", "1", *args.extra]
        _call(cmd, keep / "train.log", "a")
        evals = [("r2v", args.r2v_episodes, keep / "eval_test_r2v.json")] if args.r2v_episodes > 0 else []
        evals.append(("procgen", args.eval_episodes, done))
        for scenes, n, out in evals:
            cmd = [py, "-m", "plex_ma.evaluate", "--checkpoint", str(ckpt), "--split", "test",
                   "--scenes", scenes, "--episodes", str(n), "--num-envs", "16", "--torch-threads", "1",
                   "--json", str(out.with_suffix(".part"))]
            _call(cmd, keep / f"eval_{scenes}.log", "w")
        with open(run_dir / "metrics.jsonl", "rb") as f, \
                gzip.GzipFile(keep / "metrics.jsonl.gz", "wb", mtime=0) as g:
            shutil.copyfileobj(f, g)
        for _, _, out in evals:  # procgen last: its file marks the run as done
            os.replace(out.with_suffix(".part"), out)
    return {"arm": arm.name, "seed": seed, "seconds": round(time.time() - t0, 1)}


def run_all(args, out: Path) -> list[dict]:
    runs_dir = Path(args.runs_dir) if args.runs_dir else repo_root() / "runs" / "table1"
    # Seed-major order: if the budget of time runs out, whole seeds are complete.
    jobs = [(ARMS[a], s) for s in args.seeds for a in args.arms]
    with ThreadPoolExecutor(max_workers=max(1, args.jobs)) as pool:
        futures = [pool.submit(_run_one, arm, s, args, runs_dir / f"{arm.name}-s{s}",
                               out / "runs" / f"{arm.name}-s{s}") for arm, s in jobs]
        return [f.result() for f in futures]


# ---------------------------------------------------------------------------- reporting
def _load_eval(path: Path) -> dict | None:
    if not path.is_file():
        return None
    d = json.loads(path.read_text())
    d.pop("per_episode", None)
    return d


def _load_curve(path: Path) -> dict | None:
    """A run's training curve: reward and success of its last 100 training episodes (sampled
    actions) at each logged step, NaN until 100 have ended."""
    if not path.is_file():
        return None
    with gzip.open(path, "rt") as f:
        rows = [json.loads(line) for line in f if line.strip()]
    rows = [r for r in rows if r.get("metrics/episodes", 0) > 0]
    own = np.array([r["metrics/episodes"] >= EpisodeStats.window for r in rows], bool)
    return {"step": np.array([r["step"] for r in rows], float),
            "reward": np.where(own, [r["reward"] for r in rows], np.nan),
            "success": np.where(own, [r["metrics/success"] for r in rows], np.nan)}


def steps_to_success(curve: dict | None, level: float) -> int | None:
    """The first logged step at which the last 100 training episodes (a full window) reach
    success ``level``; None if the run never does."""
    if curve is None:
        return None
    hit = np.flatnonzero(curve["success"] >= level)  # NaN (a window not yet full) compares False
    return int(curve["step"][hit[0]]) if len(hit) else None


def _summary(values: list[float]) -> dict:
    return {"values": values, **mean_sd_se(np.array(values))} if values else {"values": []}


def collect(args, out: Path) -> dict:
    table = {}
    for name in args.arms:
        per_seed, agg = {}, {}
        for s in args.seeds:
            d = out / "runs" / f"{name}-s{s}"
            ev = {"procgen": _load_eval(d / "eval_test_procgen.json"), "r2v": _load_eval(d / "eval_test_r2v.json")}
            if ev["procgen"] is not None:
                per_seed[s] = ev
        for src in ("procgen", "r2v"):
            for part in ("all", "close", "far"):
                for m in METRICS:
                    vals = []
                    for ev in per_seed.values():
                        e = ev[src]
                        if e is None:
                            continue
                        e = e if part == "all" else e.get(part, {})
                        if e.get("episodes", 0) > 0 and e.get(m) is not None:
                            vals.append(float(e[m]))
                    agg.setdefault(src, {}).setdefault(part, {})[m] = _summary(vals)
        curves = {s: _load_curve(out / "runs" / f"{name}-s{s}" / "metrics.jsonl.gz") for s in sorted(per_seed)}
        reach = {str(level): {s: steps_to_success(c, level) for s, c in curves.items()} for level in args.success_levels}
        table[name] = {"label": ARMS[name].label, "seeds": sorted(per_seed), "test": agg,
                       "per_seed": {s: _seed_row(ev) for s, ev in sorted(per_seed.items())},
                       "steps_to_success": reach}
    return table


def _seed_row(ev: dict) -> dict:
    """One seed's figures for the per-seed table (None where an evaluation is missing)."""
    p, r = ev["procgen"], ev["r2v"] or {}
    return {"success": p.get("success"), "spl": p.get("spl"), "collisions": p.get("collisions"),
            "success_close": p.get("close", {}).get("success"), "success_far": p.get("far", {}).get("success"),
            "r2v_success": r.get("success"), "r2v_spl": r.get("spl")}


def _fmt(s: dict, nd: int = 3) -> str:
    if not s.get("values"):
        return "-"
    if len(s["values"]) == 1:  # one seed: no spread to report
        return f"{s['mean']:.{nd}f}"
    return f"{s['mean']:.{nd}f} ± {s['std']:.{nd}f}"


def write_markdown(table: dict, args, path: Path) -> None:
    levels = [str(v) for v in args.success_levels]
    lines = [f"Budget {args.budget:,} environment steps per run, preset `{args.preset}`; greedy evaluation on "
             f"{args.eval_episodes} procgen test episodes and {args.r2v_episodes} r2v test episodes. Steps to a "
             f"success: the first logged step at which the last 100 training episodes (sampled actions; for "
             f"PLEX, with the learned planner acting) reach it (-: never).", "",
             "Mean ± std over seeds:", "",
             "| method | seeds | reward | success | SPL | collisions | reward, close | reward, far | "
             "success, close | success, far | r2v reward | r2v success | r2v SPL |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for t in table.values():
        p, r = t["test"]["procgen"], t["test"]["r2v"]
        lines.append(f"| {t['label']} | {len(t['seeds'])} | {_fmt(p['all']['reward'])} | "
                     f"{_fmt(p['all']['success'])} | {_fmt(p['all']['spl'])} | {_fmt(p['all']['collisions'], 1)} | "
                     f"{_fmt(p['close']['reward'])} | {_fmt(p['far']['reward'])} | {_fmt(p['close']['success'])} | "
                     f"{_fmt(p['far']['success'])} | {_fmt(r['all']['reward'])} | {_fmt(r['all']['success'])} | "
                     f"{_fmt(r['all']['spl'])} |")
    lines += ["", "Every seed:", "",
              "| method | seed | success | SPL | collisions | success, close / far | r2v success | r2v SPL | "
              + " | ".join(f"steps to {v}" for v in levels) + " |",
              "|---|---:|---:|---:|---:|---:|---:|---:|" + "---:|" * len(levels)]

    def num(v, nd=3):
        return "-" if v is None else f"{v:.{nd}f}"

    for t in table.values():
        for s, row in t["per_seed"].items():
            reach = ["-" if (v := t["steps_to_success"][lv][s]) is None else f"{v:,}" for lv in levels]
            lines.append(f"| {t['label']} | {s} | {num(row['success'])} | {num(row['spl'])} | "
                         f"{num(row['collisions'], 1)} | {num(row['success_close'])} / {num(row['success_far'])} | "
                         f"{num(row['r2v_success'])} | {num(row['r2v_spl'])} | " + " | ".join(reach) + " |")
    path.write_text("\n".join(lines) + "\n")


def _curves(out: Path, name: str, seeds: list[int]) -> list[dict]:
    return [c for s in seeds if (c := _load_curve(out / "runs" / f"{name}-s{s}" / "metrics.jsonl.gz"))]


def mean_band(curves: list[dict], key: str, grid: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, int] | None:
    """Mean, min and max over seeds of curve ``key`` on ``grid``, and the seeds counted; NaN
    where no seed has logged a full window yet, None without any. A run resumed from an older
    checkpoint restarted its window empty, so its curve has NaN stretches: each seed's line
    is drawn across them."""
    ys = [np.interp(grid, c["step"][ok], c[key][ok], left=np.nan, right=np.nan)
          for c in curves if (ok := ~np.isnan(c[key])).any()]
    if not ys:
        return None
    with warnings.catch_warnings():  # grid steps before any seed's first full window are all-NaN
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nanmean(ys, axis=0), np.nanmin(ys, axis=0), np.nanmax(ys, axis=0), len(ys)


def _plot_mean_band(ax, curves: list[dict], key: str, label: str, budget: int) -> None:
    grid = np.linspace(0, budget, 101)
    if (band := mean_band(curves, key, grid)) is None:
        return
    mean, lo, hi, seeds = band
    line, = ax.plot(grid, mean, label=f"{label} ({seeds} seeds)")
    ax.fill_between(grid, lo, hi, color=line.get_color(), alpha=0.2)


def plot_curves(out: Path, args, arms: list[str], path: Path, title: str) -> None:
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    for name in arms:
        curves = _curves(out, name, args.seeds)
        for ax, key in zip(axes, ("reward", "success")):
            _plot_mean_band(ax, curves, key, ARMS[name].label, args.budget)
    for ax, key in zip(axes, ("reward", "success")):
        ax.set_xlabel("environment steps")
        ax.set_ylabel(f"training {key} (last 100 episodes)")
        ax.grid(alpha=0.3)
    if axes[0].get_legend_handles_labels()[0]:
        axes[0].legend(fontsize=8)
    fig.suptitle(title)
    save_figure(fig, path)
    plt.close(fig)


def plot_fig5b(table: dict, path: Path) -> None:
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.6))
    names = [n for n in ("plex-gru", "ppo-gru") if n in table]
    for ax, m in zip(axes, ("reward", "success")):
        for i, name in enumerate(names):
            for j, part in enumerate(("close", "far")):
                s = table[name]["test"]["procgen"][part][m]
                if not s.get("values"):
                    continue
                x = j + 0.38 * (i - 0.5)
                ax.bar(x, s["mean"], width=0.36, yerr=s["std"], capsize=3, color=f"C{i}",
                       label=table[name]["label"] if j == 0 else None)
                ax.plot([x] * len(s["values"]), s["values"], "k.", ms=4)
        ax.set_xticks([0, 1], ["close (< 5.76 m)", "far"])
        ax.set_ylabel(f"test {m}")
        ax.grid(alpha=0.3, axis="y")
    if axes[0].get_legend_handles_labels()[0]:
        axes[0].legend(fontsize=8)
    fig.suptitle("Fig. 5b: close vs. far goals (procgen test; bars: mean ± std, dots: seeds)")
    save_figure(fig, path)
    plt.close(fig)


def check(args) -> None:
    for flag, least in (("budget", 1), ("eval_episodes", 1), ("r2v_episodes", 0), ("jobs", 1)):
        if getattr(args, flag) < least:
            raise ValueError(f"--{flag.replace('_', '-')} must be >= {least}, got {getattr(args, flag)}")
    if not all(0 < v <= 1 for v in args.success_levels):
        raise ValueError(f"--success-levels must be in (0, 1], got {args.success_levels}")


def main(args, out: Path) -> dict:
    t0 = time.time()
    try:
        runs = [] if args.report_only else run_all(args, out)
    except RunFailed as e:
        raise SystemExit(f"table1: {e}") from None
    table = collect(args, out)
    write_json(out / "table1.json", {
        "config": {k: (str(v) if isinstance(v, Path) else v) for k, v in vars(args).items()},
        "table": table, "runs": runs, "machine": machine(), "provenance": provenance(),
        "seconds": round(time.time() - t0, 1)})
    write_markdown(table, args, out / "table1.md")
    plot_curves(out, args, [a for a in args.arms if a in ("plex-gru", "plex-smt", "ppo-gru", "ppo-smt", "ppo-gru-map")],
                out / "fig4.png", f"Fig. 4: training curves, budget {args.budget:,} steps")
    if "plex-gru" in args.arms and "plex-gru-noeli" in args.arms:
        plot_curves(out, args, ["plex-gru", "plex-gru-noeli"], out / "fig5a.png",
                    "Fig. 5a: PLEX GRU with and without the ELI")
    plot_fig5b(table, out / "fig5b.png")
    return {name: {"seeds": len(t["seeds"]),
                   "success": t["test"]["procgen"]["all"]["success"].get("mean"),
                   "reward": t["test"]["procgen"]["all"]["reward"].get("mean")} for name, t in table.items()}
