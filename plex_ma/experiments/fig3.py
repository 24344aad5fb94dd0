"""Fig. 3 of the paper (section 4.4): how far does a random policy get in N actions?

Setup (paper 4.4, docs/spec.md section 8): ``starts`` (500) start poses in the training scenes
(procedural ``train`` split by default). Start ``k`` lies in scene ``k mod #scenes``, so
recurring scenes get different start points; each start is the start position and the
uniform random heading of an episode drawn by Habitat's rules (``sample_episode``). The
policy picks uniformly among MOVE_FORWARD, TURN_LEFT and TURN_RIGHT (no STOP) for N
actions, N = 2..25. For every start and N we measure the geodesic distance from the start
to the end position and that distance divided by N, and average over the starts.

Two ways to get the N-action endpoints (``--mode``):

* ``independent`` (default): a fresh random rollout of exactly N actions for every N,
  so the values for different N are statistically independent;
* ``prefix``: one 25-action rollout per start, read after each of its first N actions.

The endpoint of an N-action prefix has exactly the distribution of an independent N-action
rollout, so both modes estimate the same means; only the correlation between the N differ.

Distances. ``geodesic_grid`` is the project's geodesic (``Geodesics.distance``: A* over the
8-connected 5 cm navigable grid, end points linked to the centres of the surrounding
cells). That graph overestimates short distances: it reports ~3 cm between a point and
itself and up to 9 cm (2-5 cm on average) too much for a free straight move of 0.25-1 m.
Random walks of 2-25 actions move only 0.2-2 m, so the bias matters at small N. ``geodesic`` is therefore the
exact geodesic wherever the straight segment between start and end is free for the agent
(it is then the euclidean distance) and the grid A* value elsewhere; both are reported.

Ego-map coverage: the planner's ego map has 0.5 m cells, and the paper picks N_EX = 10 for
"a high probability of exploring more than a unit distance in the egocentric map". We
report P(distance > 0.5 m) (and > 1 m) for every N. "More than" is strict, with a 1 um
allowance for round-off: two forward moves in a straight line cover exactly 0.5 m.

A free-space reference (the same action model on an empty floor, euclidean = geodesic)
separates what the walls do from what the action model does.
"""

from __future__ import annotations

import argparse
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from plex_ma.envs.sim import BatchedSim, Geodesics, scene_bank
from plex_ma.envs.sim.episodes import sample_episode

from .common import machine, mean_sd_se, proportion, provenance, pyplot, save_figure, write_json

FORWARD_STEP = 0.25
TURN_DEG = 10.0
N_EX = 10  # the paper's executor horizon
EGO_CELL = 0.5  # m, the planner's ego-map cell
EPS = 1e-6  # round-off allowance in "more than one cell"


@dataclass
class Fig3Config:
    starts: int = 500
    n_min: int = 2
    n_max: int = 25
    seed: int = 0
    mode: str = "independent"  # or "prefix"
    scenes: str = "procgen"
    split: str = "train"
    num_scenes: int | None = None  # None: the split's default (72 training scenes)
    resolution: int = 8  # rendering is irrelevant here; 8 is the simulator's minimum
    batch: int = 250  # worlds stepped at once (results do not depend on it)
    free_walks: int = 100_000  # free-space reference walks

    def validate(self) -> None:
        if self.starts < 2:
            raise ValueError(f"starts must be >= 2, got {self.starts}")
        if not (1 <= self.n_min <= self.n_max):
            raise ValueError(f"need 1 <= n_min <= n_max, got {self.n_min}, {self.n_max}")
        if self.mode not in ("independent", "prefix"):
            raise ValueError(f"mode must be 'independent' or 'prefix', got {self.mode!r}")
        for name, least in (("batch", 1), ("free_walks", 2)):
            if getattr(self, name) < least:
                raise ValueError(f"{name} must be >= {least}, got {getattr(self, name)}")


# ------------------------------------------------------------------------ geometry
def segment_free(grid, a: np.ndarray, b: np.ndarray) -> bool:
    """Whether the agent can move straight from ``a`` to ``b`` (every point navigable).

    Samples the segment every quarter cell, as the simulator's motion does."""
    L = float(np.hypot(*(b - a)))
    n = max(2, int(math.ceil(L / (grid.cell_size * 0.25))) + 1)
    t = np.linspace(0.0, 1.0, n)[:, None]
    return bool(grid.is_navigable(a[None, :] + t * (b - a)[None, :]).all())


def free_space_walks(ns: np.ndarray, walks: int, rng: np.random.Generator) -> dict:
    """The same random policy on an empty floor: distance after N actions, per N."""
    n_max = int(ns.max())
    acts = rng.integers(1, 4, size=(walks, n_max))
    h0 = rng.uniform(-math.pi, math.pi, size=(walks, 1))
    dh = np.where(acts == 2, 1.0, np.where(acts == 3, -1.0, 0.0)) * math.radians(TURN_DEG)
    heading = h0 + np.cumsum(dh, axis=1)  # a forward move keeps the heading it starts with
    fwd = (acts == 1) * FORWARD_STEP
    x = np.cumsum(fwd * np.cos(heading), axis=1)
    y = np.cumsum(fwd * np.sin(heading), axis=1)
    d = np.hypot(x, y)[:, ns - 1]  # (walks, len(ns))
    out = {"mean": [], "se": [], "normalised_mean": [], "p_beyond_cell": [], "p_beyond_two_cells": []}
    for j, n in enumerate(ns):
        s = mean_sd_se(d[:, j])
        out["mean"].append(s["mean"])
        out["se"].append(s["se"])
        out["normalised_mean"].append(s["mean"] / n)
        out["p_beyond_cell"].append(float((d[:, j] > EGO_CELL + EPS).mean()))
        out["p_beyond_two_cells"].append(float((d[:, j] > 2 * EGO_CELL + EPS).mean()))
    return out


# ------------------------------------------------------------------------ the run
def draw_starts(bank, cfg: Fig3Config, rng: np.random.Generator) -> list:

    geo = Geodesics(bank)
    return [sample_episode(bank, k % len(bank), rng, geo, episode_id=k)[0] for k in range(cfg.starts)]


def rollouts(bank, episodes: list, ns: np.ndarray, cfg: Fig3Config, rng: np.random.Generator):
    """End positions (starts, len(ns), 2) and collision counts (starts, len(ns))."""

    K = len(episodes)
    n_max = int(ns.max())
    if cfg.mode == "prefix":
        actions = {"all": rng.integers(1, 4, size=(K, n_max))}
    else:  # one independent action sequence per (start, N), drawn in a fixed order
        actions = {int(n): rng.integers(1, 4, size=(K, int(n))) for n in ns}
    ends = np.zeros((K, len(ns), 2))
    coll = np.zeros((K, len(ns)), np.int64)
    col_of = {int(n): j for j, n in enumerate(ns)}
    sims: dict[int, BatchedSim] = {}
    for lo in range(0, K, cfg.batch):
        rows = np.arange(lo, min(lo + cfg.batch, K))
        B = len(rows)
        if B not in sims:
            sims[B] = BatchedSim(bank, B, resolution=cfg.resolution, egomap=False, seed=cfg.seed)
        sim = sims[B]
        for i, k in enumerate(rows):
            sim.reset_world(i, episodes[k])  # computes the (unused) goal field once
        start_pos, start_heading = sim.pos.copy(), sim.heading.copy()
        if cfg.mode == "prefix":
            hits = np.zeros(B, np.int64)
            for t in range(n_max):
                hits += sim.step(actions["all"][rows, t])
                if t + 1 in col_of:
                    ends[rows, col_of[t + 1]] = sim.pos
                    coll[rows, col_of[t + 1]] = hits
        else:
            for n in ns:
                n = int(n)
                # Back to the same starts. Only the pose matters for motion, so it is restored
                # directly: a full reset_world per world and N re-renders every world and costs
                # ~15x the whole rollout here (no sensor output is read in this experiment).
                sim.pos[:] = start_pos
                sim.heading[:] = start_heading
                hits = np.zeros(B, np.int64)
                for t in range(n):
                    hits += sim.step(actions[n][rows, t])
                ends[rows, col_of[n]] = sim.pos
                coll[rows, col_of[n]] = hits
    return ends, coll


def measure(bank, episodes: list, ends: np.ndarray):
    """Grid-A* geodesic, exact-where-visible geodesic, euclidean and line of sight per (start, N)."""

    geo = Geodesics(bank)
    K, J = ends.shape[:2]
    grid_d = np.zeros((K, J))
    exact = np.zeros((K, J))
    euclid = np.zeros((K, J))
    los = np.zeros((K, J), bool)
    unreachable = 0
    for k, ep in enumerate(episodes):
        s = bank.scene_ids.index(ep.scene_id)
        a = np.asarray(ep.start_position, np.float64)
        g = bank.grids[s]
        for j in range(J):
            b = ends[k, j]
            e = float(np.hypot(*(b - a)))
            d = geo.distance(s, a, b)
            if not math.isfinite(d):  # motion reached a point the no-corner-cutting grid cannot
                unreachable += 1
                d = e
            v = segment_free(g, a, b)
            grid_d[k, j], euclid[k, j], los[k, j] = d, e, v
            exact[k, j] = e if v else max(d, e)
    return grid_d, exact, euclid, los, unreachable


def summarise(ns: np.ndarray, d: np.ndarray) -> dict:
    out = {k: [] for k in ("mean", "std", "se", "median", "q10", "q90", "normalised_mean", "normalised_std",
                           "normalised_se", "p_beyond_cell", "p_beyond_cell_se", "p_beyond_two_cells")}
    for j, n in enumerate(ns):
        col = d[:, j]
        s, sn = mean_sd_se(col), mean_sd_se(col / n)
        pc = proportion(col > EGO_CELL + EPS)
        for k, v in (("mean", s["mean"]), ("std", s["std"]), ("se", s["se"]), ("median", np.median(col)),
                     ("q10", np.quantile(col, 0.1)), ("q90", np.quantile(col, 0.9)),
                     ("normalised_mean", sn["mean"]), ("normalised_std", sn["std"]), ("normalised_se", sn["se"]),
                     ("p_beyond_cell", pc["p"]), ("p_beyond_cell_se", pc["se"]),
                     ("p_beyond_two_cells", float((col > 2 * EGO_CELL + EPS).mean()))):
            out[k].append(float(v))
    return out


def run_fig3(cfg: Fig3Config) -> dict:
    """Run the experiment; returns the JSON-ready results (no files written)."""

    cfg.validate()
    t0 = time.perf_counter()
    bank = scene_bank(cfg.scenes, cfg.split, cfg.num_scenes)
    ss_starts, ss_actions, ss_free = np.random.SeedSequence(cfg.seed).spawn(3)
    ns = np.arange(cfg.n_min, cfg.n_max + 1)
    t1 = time.perf_counter()
    episodes = draw_starts(bank, cfg, np.random.default_rng(ss_starts))
    t2 = time.perf_counter()
    ends, coll = rollouts(bank, episodes, ns, cfg, np.random.default_rng(ss_actions))
    t3 = time.perf_counter()
    grid_d, exact, euclid, los, unreachable = measure(bank, episodes, ends)
    t4 = time.perf_counter()
    free = free_space_walks(ns, cfg.free_walks, np.random.default_rng(ss_free))
    scene_count = np.bincount([k % len(bank) for k in range(cfg.starts)], minlength=len(bank))
    res = {
        "experiment": "fig3",
        "description": "geodesic distance from the start after N uniformly random actions among "
                       "FORWARD/LEFT/RIGHT (no STOP), and that distance / N, over random starts",
        "config": asdict(cfg),
        "scenes": {"count": len(bank), "starts_per_scene_min": int(scene_count.min()),
                   "starts_per_scene_max": int(scene_count.max())},
        "N": ns.tolist(),
        "geodesic": summarise(ns, exact),
        "geodesic_grid": summarise(ns, grid_d),
        "euclidean_mean": euclid.mean(0).tolist(),
        "line_of_sight_fraction": los.mean(0).tolist(),
        "collisions_mean": coll.mean(0).tolist(),
        "p_any_collision": (coll > 0).mean(0).tolist(),
        "grid_unreachable_endpoints": int(unreachable),
        "free_space": free,
        "notes": {
            "geodesic": "exact geodesic where the start-end segment is free for the agent (= euclidean), "
                        "else the grid A* value",
            "geodesic_grid": "Geodesics.distance: A* on the 8-connected 5 cm grid (overestimates short distances by a few cm)",
            "p_beyond_cell": f"P(distance > {EGO_CELL} m), one ego-map cell",
            "p_beyond_two_cells": f"P(distance > {2 * EGO_CELL} m)",
            "free_space": "same action model on an empty floor (euclidean distance), "
                          f"{cfg.free_walks} walks",
            "mode": "independent: a fresh N-action rollout per N; prefix: endpoints of one "
                    f"{cfg.n_max}-action rollout",
        },
    }
    g = res["geodesic"]
    j10 = int(np.flatnonzero(ns == N_EX)[0]) if N_EX in ns else None
    res["highlights"] = {
        "first_N_with_p_beyond_cell_at_least_0.5": _first(ns, g["p_beyond_cell"], 0.5),
        "first_N_with_mean_geodesic_above_cell": _first(ns, g["mean"], EGO_CELL),
        "peak_normalised_N": int(ns[int(np.argmax(g["normalised_mean"]))]),
        "peak_normalised_mean": float(max(g["normalised_mean"])),
        "at_N_EX": None if j10 is None else {
            "N": N_EX, "geodesic_mean": g["mean"][j10], "geodesic_se": g["se"][j10],
            "normalised_mean": g["normalised_mean"][j10], "p_beyond_cell": g["p_beyond_cell"][j10],
            "geodesic_grid_mean": res["geodesic_grid"]["mean"][j10]},
    }
    res["timing_seconds"] = {"scene_bank": t1 - t0, "starts": t2 - t1, "rollouts": t3 - t2,
                             "geodesics": t4 - t3, "total": time.perf_counter() - t0}
    res["machine"] = machine()
    res["provenance"] = provenance()
    return res


def _first(ns, values, level):
    for n, v in zip(ns, values):
        if v >= level:
            return int(n)
    return None


# ------------------------------------------------------------------------ figures
def plot(res: dict, out_dir: Path) -> list[Path]:
    plt = pyplot()
    ns = np.array(res["N"])
    g, gg, fr = res["geodesic"], res["geodesic_grid"], res["free_space"]
    K = res["config"]["starts"]
    fig, axes = plt.subplots(1, 2, figsize=(10.5, 4.0))
    for ax, key, sek, title, ylabel in (
        (axes[0], "mean", "se", "(a) geodesic distance from the start", "geodesic distance (m)"),
        (axes[1], "normalised_mean", "normalised_se", "(b) geodesic distance / N", "metres per action"),
    ):
        for d, lab, c, m in ((g, "our world (exact where visible)", "C0", "o"),
                             (gg, "our world (grid A*)", "C1", "s")):
            y, se = np.array(d[key]), np.array(d[sek])
            ax.plot(ns, y, marker=m, ms=3.5, color=c, label=lab)
            ax.fill_between(ns, y - 1.96 * se, y + 1.96 * se, color=c, alpha=0.2, lw=0)
        fy = np.array(fr["mean"] if key == "mean" else fr["normalised_mean"])
        ax.plot(ns, fy, "k--", lw=1, label="empty floor (same policy)")
        ax.axvline(N_EX, color="grey", ls=":", lw=1)
        ax.text(N_EX + 0.3, ax.get_ylim()[1] * 0.02 + ax.get_ylim()[0], "$N_{EX}=10$", color="grey", fontsize=8)
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("number of random actions N")
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
    axes[0].axhline(EGO_CELL, color="grey", ls="-.", lw=1)
    axes[0].text(ns[-1], EGO_CELL - 0.04, "one ego-map cell (0.5 m)", color="grey", fontsize=8, ha="right", va="top")
    axes[0].legend(fontsize=8, loc="upper left", bbox_to_anchor=(0.0, 0.93))
    fig.suptitle(f"Random policy (FORWARD/LEFT/RIGHT), {K} starts in {res['scenes']['count']} training scenes, "
                 f"{res['config']['mode']} rollouts; bands: 95% CI", fontsize=9)
    p1 = save_figure(fig, out_dir / "fig3.png")
    plt.close(fig)

    fig, ax = plt.subplots(figsize=(5.5, 4.0))
    for d, lab, c in ((g, "our world (exact where visible)", "C0"), (gg, "our world (grid A*)", "C1")):
        y, se = np.array(d["p_beyond_cell"]), np.array(d["p_beyond_cell_se"])
        ax.errorbar(ns, y, yerr=1.96 * se, color=c, marker="o", ms=3, capsize=2, label=lab + ", > 0.5 m")
    ax.plot(ns, g["p_beyond_two_cells"], color="C0", ls="--", marker=".", label="our world (exact), > 1 m")
    ax.plot(ns, fr["p_beyond_cell"], "k--", lw=1, label="empty floor, > 0.5 m")
    ax.axvline(N_EX, color="grey", ls=":", lw=1)
    ax.set_ylim(0, 1)
    ax.set_xlabel("number of random actions N")
    ax.set_ylabel("P(distance from start > threshold)")
    ax.set_title("Probability of leaving the start's ego-map cell", fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    p2 = save_figure(fig, out_dir / "fig3_cell_probability.png")
    plt.close(fig)
    return [p1, p2]


# ------------------------------------------------------------------------ CLI
def add_arguments(p: argparse.ArgumentParser) -> None:
    d = Fig3Config()
    p.add_argument("--starts", type=int, default=d.starts, help="number of random starts (paper: 500)")
    p.add_argument("--n-min", type=int, default=d.n_min)
    p.add_argument("--n-max", type=int, default=d.n_max)
    p.add_argument("--mode", choices=("independent", "prefix"), default=d.mode,
                   help="a fresh rollout per N, or the prefixes of one n-max-action rollout per start")
    p.add_argument("--scenes", default=d.scenes, help="scene source")
    p.add_argument("--split", default=d.split)
    p.add_argument("--num-scenes", type=int, default=None, help="scenes in the split (default: 72)")
    p.add_argument("--resolution", type=int, default=d.resolution, help="render size (irrelevant; min 8)")
    p.add_argument("--batch", type=int, default=d.batch, help="worlds stepped at once")
    p.add_argument("--free-walks", type=int, default=d.free_walks, help="empty-floor reference walks")


def config(args: argparse.Namespace) -> Fig3Config:
    return Fig3Config(starts=args.starts, n_min=args.n_min, n_max=args.n_max, seed=args.seed, mode=args.mode,
                      scenes=args.scenes, split=args.split, num_scenes=args.num_scenes,
                      resolution=args.resolution, batch=args.batch, free_walks=args.free_walks)


def check(args: argparse.Namespace) -> None:
    config(args).validate()


def main(args: argparse.Namespace, out_dir: Path) -> dict:
    res = run_fig3(config(args))
    write_json(out_dir / "fig3.json", res)
    figs = plot(res, out_dir)
    return {"files": [str(out_dir / "fig3.json")] + [str(f) for f in figs], "highlights": res["highlights"]}
