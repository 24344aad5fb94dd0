"""``python -m plex_ma.evaluate``: deterministic evaluation of a checkpoint on fixed episodes.

    python -m plex_ma.evaluate --checkpoint runs/plex-gru-cpu/latest.pt --split test --episodes 1000 --json out.json

The first ``--episodes`` episodes of the split's fixed episode file are each run once with
greedy actions (the planner's mean sub-goal and most likely stop decision, the executor's
most likely action). Prints a table and writes JSON with ``success``, ``spl``, ``reward``,
``distance_to_goal``, ``collisions`` and ``episodes``, overall and again under ``close``
and ``far`` (start-to-goal geodesic distance below / above 5.76 m, the paper's Fig. 5b).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import warnings
from pathlib import Path

import numpy as np
import torch

from plex_ma.config import DEVICE_HELP, TrainConfig
from plex_ma.envs.rules import CLOSE_FAR_SPLIT, PLANNER
from plex_ma.envs.sim import generate_episodes, load_episodes
from plex_ma.envs.vector import PlexVectorEnv, PointNavVectorEnv
from plex_ma.trainers.checkpoint import CheckpointError, load_checkpoint
from plex_ma.trainers.device import DeviceError, resolve_device
from plex_ma.trainers.driver import PlexDriver, make_executor, make_planner
from plex_ma.trainers.plex import build_policies, env_kwargs, saved_config

METRICS = ("success", "spl", "reward", "distance_to_goal", "collisions")


def load_policies(path: str | Path, device: str | torch.device = "cpu") -> tuple[TrainConfig, dict]:
    """The config and networks stored in a checkpoint (loaded with ``weights_only=True``),
    on ``device``."""
    state = load_checkpoint(path)
    known = {f.name for f in dataclasses.fields(TrainConfig)}
    cfg = TrainConfig(**{k: v for k, v in saved_config(state).items() if k in known})
    nets = build_policies(cfg)
    try:
        for k, m in nets.items():
            m.load_state_dict(state["models"][k])
            m.eval().to(device)
    except (KeyError, RuntimeError) as e:
        raise CheckpointError(f"checkpoint {path}: its weights do not match method {cfg.method}: {e}") from None
    return cfg, nets


def episode_set(env, split: str, n: int, seed: int):
    """The first ``n`` fixed episodes of the env's split (generated if it has no file)."""
    eps = env.worlds.fixed_episodes
    if eps is None:
        eps = generate_episodes(env.worlds.bank, n, seed)
    if n > len(eps):
        warnings.warn(f"only {len(eps)} episodes in the {split} set; evaluating those", stacklevel=2)
    return list(eps[:n])


def run_episodes(cfg: TrainConfig, nets: dict, split: str = "test", episodes: int = 100, scenes: str | None = None,
                 num_envs: int = 8, episodes_file: str | None = None, recorder=None, sample: bool = False,
                 planner: str = "learned", executor: str = "learned", seed: int = 0) -> list[dict]:
    """Run each episode once; returns one result dict per episode (by episode_id).

    Actions are greedy, or sampled with ``sample`` (seeded by ``seed``, on a fork of torch's
    RNG: a caller's random stream, e.g. a training run's, is left as it was). For PLEX,
    ``planner`` and ``executor`` pick each agent's policy: 'learned' (the network in
    ``nets``), 'oracle' (shortest-path, ground truth) or 'random'."""
    devices = {p.device for net in nets.values() for p in net.parameters() if p.device.type == "cuda"}
    # fork only the generators in use (forking all of them would start every visible GPU)
    with torch.no_grad(), torch.random.fork_rng(devices=[d.index or 0 for d in devices]):
        torch.manual_seed(seed)
        return _run_episodes(cfg, nets, split, episodes, scenes, num_envs, episodes_file, recorder, sample, planner,
                             executor, seed)


def _run_episodes(cfg, nets, split, episodes, scenes, num_envs, episodes_file, recorder, sample, planner, executor,
                  seed) -> list[dict]:
    scenes = scenes or cfg.scenes
    kw = env_kwargs(dataclasses.replace(cfg, scenes=scenes), split)
    if episodes_file:
        kw["episodes_file"] = episodes_file
    plex = cfg.method.startswith("plex")
    env = PlexVectorEnv(num_envs, seed=0, **kw) if plex else PointNavVectorEnv(num_envs, seed=0, **kw)
    eps = episode_set(env, split, episodes, seed=12345)
    wanted = {e.episode_id for e in eps}
    if len(wanted) != len(eps):  # generated sets number their episodes 0..n-1; files must too
        raise ValueError("episode ids in the evaluation set are not unique")
    # Worlds take the set's episodes in order as they free up; once the set is exhausted
    # they cycle through it again and those repeats are ignored.
    env.worlds.fixed_episodes = eps
    scene_of = {e.episode_id: e.scene_id for e in eps}  # infos name the scene by index only
    results: dict[int, dict] = {}
    rng = np.random.default_rng(seed)

    def finish(infos, returns):
        for info, ret in zip(infos, returns):
            if info["episode_id"] in wanted and info["episode_id"] not in results:
                keep = ("success", "spl", "distance_to_goal", "collisions", "geodesic_distance", "episode_id",
                        "steps")
                eid = info["episode_id"]
                results[eid] = {**{m: info[m] for m in keep}, "scene_id": scene_of[eid], "reward": float(ret)}

    if plex:
        pl_kw = {"stop_prob": 0.02} if planner == "random" else {}  # random episodes end now and then
        drv = PlexDriver(env, make_planner(planner, env, nets.get("planner"), not sample, rng, **pl_kw),
                         make_executor(executor, env, nets.get("executor"), not sample, rng))
        drv.reset()
        if recorder is not None:
            recorder.begin(env)
        done = lambda: len(results) == len(eps)  # noqa: E731  (a planner that always stops never leaves decide)

        def on_decision(d):
            if recorder is not None:
                recorder.step(env, d.result, rows=d.rows)
            finish(d.result.episode_infos, drv.episode_returns)

        while not done():
            drv.decide(on_decision, until=done)
            if done():
                break
            s = drv.step()
            if recorder is not None:
                # stand-in executors send an all-zero ELI: nothing to show
                recorder.step(env, s.result, eli=s.out["eli"] if drv.executor.learns else None)
            finish(s.result.episode_infos, drv.episode_returns)
    else:
        policy = nets["policy"]
        obs = env.reset()
        if recorder is not None:
            recorder.begin(env)
        state = policy.initial_state(num_envs)
        starts = np.ones(num_envs, np.bool_)
        ret = np.zeros(num_envs)
        while len(results) < len(eps):
            out, state = policy.act(obs, state, starts, deterministic=not sample)
            obs, rew, term, trunc, infos = env.step(out["action"].cpu().numpy())
            if recorder is not None:
                recorder.step(env, (obs, rew, term, trunc, infos))
            ret += rew
            ended = np.flatnonzero(term | trunc)
            finish(infos, ret[ended])
            ret[ended] = 0.0
            starts = term | trunc
    if recorder is not None:
        recorder.end()
    return [results[e.episode_id] for e in eps]


def summarize(results: list[dict]) -> dict:
    """Means of the metrics overall and for close / far goals."""
    def agg(rs):
        out = {m: float(np.mean([r[m] for r in rs])) if rs else float("nan") for m in METRICS}
        out["episodes"] = len(rs)
        return out

    close = [r for r in results if r["geodesic_distance"] < CLOSE_FAR_SPLIT]
    far = [r for r in results if r["geodesic_distance"] >= CLOSE_FAR_SPLIT]
    return {**agg(results), "close": agg(close), "far": agg(far)}


def format_table(summary: dict, title: str = "") -> str:
    rows = [("all", summary), ("close", summary["close"]), ("far", summary["far"])]
    head = f"{'subset':<6} {'episodes':>8} " + " ".join(f"{m:>16}" for m in METRICS)
    lines = [title, head] if title else [head]
    for name, s in rows:
        lines.append(f"{name:<6} {s['episodes']:>8} " + " ".join(f"{s[m]:>16.3f}" for m in METRICS))
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(prog="python -m plex_ma.evaluate", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--checkpoint", default=None,
                   help="checkpoint file (e.g. runs/x/latest.pt, or pretrained:plex-gru); not needed when both "
                        "PLEX agents are stand-ins")
    p.add_argument("--planner", choices=["learned", "oracle", "random", "map", "map-los"], default="learned",
                   help="PLEX planner: the checkpoint's, the shortest-path oracle (ground truth), random, or "
                        "shortest paths on the agent's own ego map (no ground truth)")
    p.add_argument("--executor", choices=["learned", "oracle", "random"], default="learned",
                   help="PLEX executor: the checkpoint's, the shortest-path oracle (ground truth) or random")
    p.add_argument("--sample", action="store_true", help="sample the learned agents' actions (seeded) instead of greedy")
    p.add_argument("--seed", type=int, default=0, help="seeds --sample and the random stand-ins")
    p.add_argument("--split", choices=["val", "test"], default="test", help="episode set")
    p.add_argument("--episodes", type=int, default=1000, help="how many of the set's episodes to run")
    p.add_argument("--scenes", default=None, help="scene source (default: the one trained on)")
    p.add_argument("--episodes-file", default=None, help="a fixed episode file instead of the split's default")
    p.add_argument("--num-envs", type=int, default=8, help="worlds run in parallel")
    p.add_argument("--json", default=None, help="write the summary and per-episode results here")
    p.add_argument("--record", default=None, help="also record the episodes to this .rrd file (rerun)")
    p.add_argument("--torch-threads", type=int, default=1,
                   help="torch threads (1: small batches run fastest on a small, shared machine)")
    p.add_argument("--device", default="auto", help=DEVICE_HELP)
    a = p.parse_args(argv)
    if a.torch_threads > 0:
        torch.set_num_threads(a.torch_threads)
    try:
        device = resolve_device(a.device)
    except DeviceError as e:
        p.error(str(e))
    if a.episodes < 1:
        p.error("--episodes must be >= 1")
    needs_nets = a.checkpoint is not None or "learned" in (a.planner, a.executor)
    if a.checkpoint is None and needs_nets:
        p.error("--checkpoint is needed unless neither --planner nor --executor is learned")
    try:
        cfg, nets = load_policies(a.checkpoint, device) if a.checkpoint else (TrainConfig(), {})
    except CheckpointError as e:
        print(f"error: {e}", file=sys.stderr)
        raise SystemExit(2)
    if not cfg.method.startswith("plex") and (a.planner, a.executor) != ("learned", "learned"):
        p.error(f"--planner/--executor apply to PLEX; the checkpoint is {cfg.method}")
    if a.episodes_file:
        load_episodes(a.episodes_file)  # fail early with a clear message
    recorder = None
    if a.record:
        from plex_ma.viz.record import EpisodeRecorder

        recorder = EpisodeRecorder(a.record)
    results = run_episodes(cfg, nets, a.split, a.episodes, a.scenes, a.num_envs, a.episodes_file, recorder,
                           sample=a.sample, planner=a.planner, executor=a.executor, seed=a.seed)
    summary = summarize(results)
    agents = agents_label(cfg, a.planner, a.executor)
    mode = "sampled" if a.sample else "greedy"
    print(format_table(summary, f"{agents} on {a.scenes or cfg.scenes}/{a.split}, {mode} "
                                f"({a.checkpoint or 'no checkpoint'})"))
    if a.json:
        Path(a.json).parent.mkdir(parents=True, exist_ok=True)
        Path(a.json).write_text(json.dumps({**summary, "method": cfg.method, "agents": agents,
                                            "planner": a.planner, "executor": a.executor,
                                            "ground_truth": "oracle" in (a.planner, a.executor), "mode": mode,
                                            "seed": a.seed, "checkpoint": str(a.checkpoint),
                                            "split": a.split, "scenes": a.scenes or cfg.scenes,
                                            "per_episode": results}, indent=1))
    return summary


def agents_label(cfg: TrainConfig, planner: str, executor: str) -> str:
    """e.g. 'plex-gru', or 'plex-gru: planner oracle (ground truth), executor learned'."""
    if not cfg.method.startswith("plex") or (planner, executor) == ("learned", "learned"):
        return cfg.method
    gt = lambda k: " (ground truth)" if k == "oracle" else ""  # noqa: E731
    return f"{cfg.method}: planner {planner}{gt(planner)}, executor {executor}{gt(executor)}"


if __name__ == "__main__":
    main(sys.argv[1:])
