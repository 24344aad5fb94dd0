"""Scene sources from the command line: check them, or render them top-down.

    python -m plex_ma.scenes check r2v [--split all] [--episodes 5] [--compare procgen] [--json OUT]
    python -m plex_ma.scenes check procgen --split test
    python -m plex_ma.scenes check /path/to/plans          # a directory of plan files
    python -m plex_ma.scenes render r2v --out DIR --count 6 [--ids ID,ID]
    python -m plex_ma.scenes pack /path/to/plans | index  # maintainers: rebuild envs/sim/data/r2v

``check`` loads every scene of the source (for ``r2v`` every bundled plan of the split,
all 1,040 with ``--split all``; for a directory every ``*.txt`` in it; for ``procgen``
the split's default number of houses, or ``--num-scenes``) and reports how many load,
why the others fail (grouped by reason), the navigable area per scene (total, and the
largest connected component) and the geodesic distances of ``--episodes`` episodes
sampled per scene with the simulator's own sampler (Habitat's rules, docs/spec.md section 1),
checking each episode against those rules. ``--compare procgen`` adds the same figures
for procedural houses. ``--json OUT`` writes the summaries and the per-scene records.

``render`` writes one PNG per scene (:func:`plex_ma.envs.sim.topdown.topdown_view`;
walls dark, doors brown, furniture light brown, void white), with one sampled episode's
start (green, with its heading) and goal (red) unless ``--no-episode``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import sys
import time
import zlib
from collections import Counter, defaultdict
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
from PIL import Image

from plex_ma.cli import Parser, output_path
from plex_ma.envs.sim import r2v
from plex_ma.envs.sim.bank import SceneBank
from plex_ma.envs.sim.episodes import CLOSE_FAR_SPLIT, MAX_GEODESIC, MIN_GEODESIC, Geodesics, sample_episode
from plex_ma.envs.sim.procgen import generate_house
from plex_ma.envs.sim.r2v import DEFAULT_SCALE
from plex_ma.envs.sim.scene import SceneError, rasterize
from plex_ma.envs.sim.sources import DEFAULT_NUM_SCENES, SPLITS, procgen_seed
from plex_ma.envs.sim.topdown import topdown_view

GEODESIC_BINS = [1, 2, 3, 5, 7.5, 10, 15, 20, 30]
QUANTILES = [0, 5, 25, 50, 75, 95, 100]


# ----------------------------------------------------------------------------- one scene


def _tasks(source: str, split: str, num_scenes: int | None, scale) -> list[tuple]:
    """What to load: (kind, key, split, scale) per scene of the source."""

    splits = list(SPLITS) if split == "all" else [split]
    if source == "r2v":
        ids = [i for i in r2v.bundled_ids() if split == "all" or r2v.split_of(i) == split]
        tasks = [("r2v", pid, r2v.split_of(pid), scale) for pid in ids]
    elif source == "procgen":
        tasks = []
        for sp in splits:
            n = DEFAULT_NUM_SCENES[sp] if num_scenes is None else num_scenes
            tasks += [("procgen", i, sp, None) for i in range(n)]
        return tasks
    elif Path(source).is_dir():
        tasks = [("file", str(f), "any", scale) for f in sorted(Path(source).glob("*.txt"))]
        if not tasks:
            raise SystemExit(f"{source}: no plan files (*.txt) in this directory")
    else:
        raise SystemExit(f"unknown scene source {source!r}: use r2v, procgen or a directory of plan files")
    return tasks if num_scenes is None else tasks[:num_scenes]


def _load(task: tuple):
    """(scene_id, Scene, SceneGrid) of a task; raises SceneError for a reject."""

    kind, key, split, scale = task
    if kind == "r2v":
        scene, grid = r2v.load_plan_grid(r2v.bundled_plans()[key], key, scale=scale)
    elif kind == "file":
        scene, grid = r2v.load_plan_grid(key, scale=scale)
    else:
        scene = _procgen_one(split, key)
        grid = rasterize(scene)
    return scene.scene_id, scene, grid


def _procgen_one(split: str, index: int):

    return generate_house(procgen_seed(split, index), scene_id=f"procgen-{split}-{index:05d}")


def check_one(task: tuple, episodes: int = 5, seed: int = 0) -> dict:
    """Load one scene, measure it and sample ``episodes`` episodes in it."""

    kind, key, split, _ = task
    rec: dict = {"id": Path(str(key)).stem if kind != "procgen" else f"procgen-{split}-{key:05d}", "split": split}
    if kind in ("r2v", "file"):

        try:
            data = r2v.bundled_plans()[key] if kind == "r2v" else Path(key).read_bytes()
            rec["repairs"] = r2v.repair_stats(r2v.parse_plan(data, rec["id"]))
        except Exception:  # an unreadable plan: _load below reports why
            pass
    try:
        sid, scene, grid = _load(task)
    except SceneError as e:
        rec.update(status="rejected", reason=str(e))
        return rec
    except Exception as e:  # a crash is a bug of the loader: report it as such
        rec.update(status="crashed", reason=f"{type(e).__name__}: {e}")
        return rec
    comp = grid.component[grid.component >= 0]
    cs2 = grid.cell_size**2
    x0, y0, x1, y1 = scene.bounds()
    rec.update(status="ok", id=sid, navigable_m2=round(grid.navigable_area(), 3),
               largest_m2=round(float(np.bincount(comp).max()) * cs2, 3), rooms=int(grid.num_rooms),
               extent_m=[round(x1 - x0, 2), round(y1 - y0, 2)], doors=int(len(scene.doors)),
               boxes=int(len(scene.boxes)), geodesics=[], violations=[])
    if episodes <= 0:
        return rec
    bank = SceneBank([grid])
    geo = Geodesics(bank)
    rng = np.random.default_rng([seed, zlib.crc32(sid.encode())])
    for k in range(episodes):
        try:
            ep, _ = sample_episode(bank, 0, rng, geo, episode_id=k)
        except RuntimeError as e:
            rec["violations"].append(f"no episode: {e}")
            break
        s, g = np.array(ep.start_position), np.array(ep.goal_position)
        d = geo.distance(0, s, g)
        (rs, cs_), (rg, cg) = grid.world_to_cell(s), grid.world_to_cell(g)
        if not (grid.is_navigable(s) and grid.is_navigable(g)):
            rec["violations"].append(f"episode {k}: start or goal not navigable")
        elif grid.component[rs, cs_] != grid.component[rg, cg] or not math.isfinite(d):
            rec["violations"].append(f"episode {k}: start and goal not connected")
        elif not (MIN_GEODESIC <= ep.geodesic_distance <= MAX_GEODESIC):
            rec["violations"].append(f"episode {k}: geodesic {ep.geodesic_distance:.2f} m outside "
                                     f"[{MIN_GEODESIC}, {MAX_GEODESIC}]")
        rec["geodesics"].append(round(ep.geodesic_distance, 3))
    return rec


def _check_star(args):
    return check_one(*args)


# ----------------------------------------------------------------------------- summaries


def reason_key(reason: str) -> str:
    """Group a rejection message: drop the plan name, numbers and details after a colon."""

    msg = reason.split(": ", 1)[1] if reason.startswith(("plan '", "scene '")) and ": " in reason else reason
    msg = re.sub(r"line \d+", "line N", msg)
    head = msg.split(":", 1)[0]
    head = re.sub(r"\(.*?\)", "", head)
    head = re.sub(r"-?\d+(\.\d+)?", "#", head)
    return " ".join(head.split())


def _quantiles(x) -> dict:
    x = np.asarray(x, np.float64)
    if len(x) == 0:
        return {}
    out = {f"p{q}": round(float(np.percentile(x, q)), 2) for q in QUANTILES}
    out["mean"] = round(float(x.mean()), 2)
    return out


def summarise(name: str, recs: list[dict], episodes: int) -> dict:
    ok = [r for r in recs if r["status"] == "ok"]
    bad = [r for r in recs if r["status"] != "ok"]
    groups: dict[str, list[str]] = defaultdict(list)
    for r in bad:
        groups[("CRASH " if r["status"] == "crashed" else "") + reason_key(r["reason"])].append(r["id"])
    geos = [g for r in ok for g in r.get("geodesics", [])]
    viol = [f"{r['id']}: {v}" for r in ok for v in r.get("violations", [])]
    hist = np.histogram(geos, bins=GEODESIC_BINS)[0].tolist() if geos else []
    repairs: Counter = Counter()
    repaired_plans: Counter = Counter()
    for r in recs:
        for k, v in r.get("repairs", {}).items():
            repairs[k] += v
            repaired_plans[k] += bool(v)
    per_split = Counter(r["split"] for r in recs)
    ok_split = Counter(r["split"] for r in ok)
    return {
        "source": name,
        "scenes": len(recs),
        "loaded": len(ok),
        "rejected": len(bad),
        "crashed": sum(r["status"] == "crashed" for r in bad),
        "per_split": {sp: {"scenes": per_split[sp], "loaded": ok_split[sp]} for sp in sorted(per_split)},
        "reasons": {k: {"count": len(v), "examples": v[:3]} for k, v in
                    sorted(groups.items(), key=lambda kv: -len(kv[1]))},
        "navigable_m2": _quantiles([r["navigable_m2"] for r in ok]),
        "largest_component_m2": _quantiles([r["largest_m2"] for r in ok]),
        "rooms": _quantiles([r["rooms"] for r in ok]),
        "extent_m": _quantiles([max(r["extent_m"]) for r in ok]),
        "episodes_per_scene": episodes,
        "episodes": len(geos),
        "geodesic_m": _quantiles(geos),
        "geodesic_histogram": {"bins_m": GEODESIC_BINS, "counts": hist},
        "close_fraction": round(float(np.mean(np.asarray(geos) < CLOSE_FAR_SPLIT)), 3) if geos else None,
        "spec_violations": viol,
        "repairs": {k: {"total": repairs[k], "plans": repaired_plans[k]} for k in sorted(repairs)},
    }


def format_summary(s: dict) -> str:
    def q(d: dict, unit: str = "") -> str:
        if not d:
            return "-"
        return (f"min {d['p0']}, p5 {d['p5']}, p25 {d['p25']}, median {d['p50']}, p75 {d['p75']}, "
                f"p95 {d['p95']}, max {d['p100']}, mean {d['mean']}{unit}")

    n = max(s["scenes"], 1)
    lines = [f"== {s['source']}: {s['scenes']} scenes, {s['loaded']} load ({100 * s['loaded'] / n:.1f}%), "
             f"{s['rejected']} rejected" + (f", {s['crashed']} CRASHED" if s["crashed"] else "")]
    if len(s["per_split"]) > 1:
        lines.append("   per split: " + ", ".join(f"{sp} {v['loaded']}/{v['scenes']}"
                                                  for sp, v in s["per_split"].items()))
    for k, v in s["reasons"].items():
        lines.append(f"   {v['count']:5d} x {k}   (e.g. {', '.join(v['examples'][:2])})")
    if s.get("repairs"):
        lines.append("   repairs: " + ", ".join(f"{k.replace('_', ' ')} {v['total']} (in {v['plans']} plans)"
                                              for k, v in s["repairs"].items()))
    lines.append(f"   navigable area m^2:          {q(s['navigable_m2'])}")
    lines.append(f"   largest component m^2:       {q(s['largest_component_m2'])}")
    lines.append(f"   longer side m:               {q(s['extent_m'])}")
    lines.append(f"   rooms:                       {q(s['rooms'])}")
    if s["episodes"]:
        lines.append(f"   episodes: {s['episodes']} ({s['episodes_per_scene']} per scene), "
                     f"close (< {CLOSE_FAR_SPLIT} m) {100 * s['close_fraction']:.1f}%")
        lines.append(f"   geodesic distance m:         {q(s['geodesic_m'])}")
        b = s["geodesic_histogram"]["bins_m"]
        lines.append("   histogram: " + ", ".join(f"[{lo:g},{hi:g}) {c}" for lo, hi, c in
                                                zip(b[:-1], b[1:], s["geodesic_histogram"]["counts"])))
    lines.append(f"   SPEC section 1 violations:   {len(s['spec_violations'])}"
                 + "".join(f"\n      {v}" for v in s["spec_violations"][:10]))
    return "\n".join(lines)


def run_check(source: str, split: str, num_scenes: int | None, episodes: int, seed: int, jobs: int,
              scale) -> tuple[dict, list[dict]]:
    tasks = _tasks(source, split, num_scenes, scale)
    args = [(t, episodes, seed) for t in tasks]
    if jobs > 1 and len(tasks) > 8:
        with ProcessPoolExecutor(jobs) as ex:
            recs = list(ex.map(_check_star, args, chunksize=8))
    else:
        recs = [_check_star(a) for a in args]
    name = source if source in ("r2v", "procgen") else f"directory {source}"
    if scale is not None and source != "procgen":
        name += f" (scale {scale})"
    return summarise(f"{name}, split {split}", recs, episodes), recs


# ----------------------------------------------------------------------------- render


def render(source: str, out: str, count: int, split: str, ids: list[str] | None, px_per_m: float,
           episode: bool, seed: int, scale) -> list[str]:


    tasks = _tasks(source, split, None, scale)
    if ids:
        by_id = {(Path(str(t[1])).stem if t[0] != "procgen" else f"procgen-{t[2]}-{t[1]:05d}"): t for t in tasks}
        missing = [i for i in ids if i not in by_id]
        if missing:
            raise SystemExit(f"not in source {source!r} (split {split}): {', '.join(missing)}")
        tasks = [by_id[i] for i in ids]
    Path(out).mkdir(parents=True, exist_ok=True)
    written = []
    for t in tasks:
        if len(written) >= count:
            break
        try:
            sid, _scene, grid = _load(t)
        except SceneError as e:
            print(f"skip: {e}", file=sys.stderr)
            continue
        kw = {}
        if episode:
            bank = SceneBank([grid])
            rng = np.random.default_rng([seed, zlib.crc32(sid.encode())])
            try:
                ep, _ = sample_episode(bank, 0, rng, Geodesics(bank))
                kw = {"goal": ep.goal_position, "agent_pose": (*ep.start_position, ep.start_heading)}
            except RuntimeError:
                pass
        img = Image.fromarray(topdown_view(grid, px_per_m=px_per_m, **kw))
        img = img.quantize(colors=16, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE)
        path = Path(out) / f"{sid}.png"
        img.save(path, optimize=True)
        written.append(str(path))
        print(f"{path}  ({path.stat().st_size / 1024:.0f} KB, {grid.navigable_area():.1f} m^2 navigable)")
    return written


# ----------------------------------------------------------------------------- CLI


def _scale(s: str):
    if s == "auto":
        return s
    try:
        return float(s)
    except ValueError:
        raise argparse.ArgumentTypeError(f"scale must be metres per pixel or 'auto', got {s!r}") from None


def main(argv: list[str] | None = None) -> int:

    p = Parser(prog="python -m plex_ma.scenes", description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    splits = ["all", "train", "val", "test"]
    c = sub.add_parser("check", help="how many scenes load, why not, areas and episode distances")
    c.add_argument("source", help="r2v, procgen, or a directory of plan files")
    c.add_argument("--split", choices=splits, default="all")
    c.add_argument("--num-scenes", type=int, default=None, help="only the first N scenes (per split for procgen)")
    c.add_argument("--episodes", type=int, default=5, help="episodes sampled per scene (0: none)")
    c.add_argument("--compare", choices=["procgen", "none"], default="none",
                   help="also check procedural houses of the same split(s)")
    c.add_argument("--scale", type=_scale, default=DEFAULT_SCALE, help="metres per pixel of plans, or 'auto'")
    c.add_argument("--seed", type=int, default=0)
    c.add_argument("--jobs", type=int, default=os.cpu_count() or 1)
    c.add_argument("--json", default=None, type=output_path(), help="write the summaries and per-scene records here")
    r = sub.add_parser("render", help="top-down PNGs of a source's scenes")
    r.add_argument("source", help="r2v, procgen, or a directory of plan files")
    r.add_argument("--out", required=True, type=output_path(directory=True))
    r.add_argument("--count", type=int, default=6)
    r.add_argument("--split", choices=splits, default="all")
    r.add_argument("--ids", default=None, help="comma-separated scene ids (default: the first that load)")
    r.add_argument("--px-per-m", type=float, default=20.0)
    r.add_argument("--no-episode", action="store_true", help="do not draw a sampled episode's start and goal")
    r.add_argument("--scale", type=_scale, default=DEFAULT_SCALE, help="metres per pixel of plans, or 'auto'")
    r.add_argument("--seed", type=int, default=0)
    k = sub.add_parser("pack", help="(maintainers) rebuild envs/sim/data/r2v from a directory of plan files")
    k.add_argument("plans_dir")
    sub.add_parser("index", help="(maintainers) rebuild envs/sim/data/r2v/index.json from the bundled plans")
    a = p.parse_args(argv)

    if a.cmd in ("pack", "index"):

        idx = r2v.pack(a.plans_dir) if a.cmd == "pack" else r2v.write_index(r2v.build_index(r2v.bundled_plans()))
        print(f"{r2v.DATA_DIR}: {idx['num_plans']} plans, {idx['num_plans'] - len(idx['rejects'])} load, "
              f"splits {idx['split_sizes']}")
        return 0

    if a.cmd == "render":
        if a.count < 1:
            p.error("--count must be >= 1")
        render(a.source, a.out, a.count, a.split, a.ids.split(",") if a.ids else None, a.px_per_m,
               not a.no_episode, a.seed, a.scale)
        return 0

    t0 = time.perf_counter()
    runs = [(a.source, a.scale if a.source != "procgen" else None)]
    if a.compare == "procgen" and a.source != "procgen":
        runs.append(("procgen", None))
    summaries, records = [], {}
    for src, scale in runs:
        s, recs = run_check(src, a.split, a.num_scenes if src == a.source else None, a.episodes, a.seed,
                            max(1, a.jobs), scale)
        summaries.append(s)
        records[s["source"]] = recs
        print(format_summary(s), flush=True)
    elapsed = time.perf_counter() - t0
    print(f"({elapsed:.0f} s)")
    if a.json:
        Path(a.json).parent.mkdir(parents=True, exist_ok=True)
        Path(a.json).write_text(json.dumps({"command": "python -m plex_ma.scenes " + " ".join(
            sys.argv[1:] if argv is None else argv), "seconds": round(elapsed, 1), "summaries": summaries,
            "scenes": records}, indent=1))
    crashed = sum(s["crashed"] for s in summaries)
    violations = sum(len(s["spec_violations"]) for s in summaries)
    return 1 if crashed or violations else 0


if __name__ == "__main__":
    sys.exit(main())
