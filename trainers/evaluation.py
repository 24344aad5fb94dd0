"""Evaluation on fixed episodes: a checkpoint's networks (or stand-in policies) run once
per episode through the one rollout driver, with the metrics summed up overall and under
close and far goals. ``python -m plex_ma.evaluate`` is its command line."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import torch
from plex_ma.envs.sim.episodes import CLOSE_FAR_SPLIT
from plex_ma.envs.vector import PlexVectorEnv, PointNavVectorEnv

from plex_ma.config import TrainConfig

from .checkpoint import CheckpointError, load_checkpoint
from .driver import PlexDriver, make_executor, make_planner
from .base import build_policies, env_kwargs, reads_ego_map, saved_config

METRICS = ("success", "spl", "reward", "distance_to_goal", "collisions")


def load_policies(path: str | Path, device: str | torch.device = "cpu") -> tuple[TrainConfig, dict]:
    """The config and networks stored in a checkpoint (loaded with ``weights_only=True``),
    on ``device``."""
    state = load_checkpoint(path)
    cfg = saved_config(state)
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
    eps = env.fixed_episodes
    if eps is None:
        eps = env.generate_episodes(n, seed)
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
    ``nets``), 'oracle' (shortest-path, ground truth) or 'random'; the planner also 'map' or
    'map-los' (hand-written planners on the ego map) or 'vin' (the value-iteration module's sub-goal)."""
    devices = {p.device for net in nets.values() for p in net.parameters() if p.device.type == "cuda"}
    # fork only the generators in use (forking all of them would start every visible GPU)
    with torch.no_grad(), torch.random.fork_rng(devices=[d.index or 0 for d in devices]):
        torch.manual_seed(seed)
        return _run_episodes(cfg, nets, split, episodes, scenes, num_envs, episodes_file, recorder, sample, planner,
                             executor, seed)


def _run_episodes(cfg, nets, split, episodes, scenes, num_envs, episodes_file, recorder, sample, planner, executor,
                  seed) -> list[dict]:
    kw = env_kwargs(cfg, split) | ({"scenes": scenes} if scenes else {})
    if episodes_file:
        kw["episodes_file"] = episodes_file
    plex = cfg.method.startswith("plex")
    env = PlexVectorEnv(num_envs, seed=0, **kw) if plex else \
        PointNavVectorEnv(num_envs, seed=0, egomap=reads_ego_map(nets), **kw)
    eps = episode_set(env, split, episodes, seed=12345)
    wanted = {e.episode_id for e in eps}
    if len(wanted) != len(eps):  # generated sets number their episodes 0..n-1; files must too
        raise ValueError("episode ids in the evaluation set are not unique")
    # Worlds take the set's episodes in order as they free up; once the set is exhausted
    # they cycle through it again and those repeats are ignored.
    env.fixed_episodes = eps
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
        drv = PlexDriver(env, make_planner(planner, env, nets.get("planner"), not sample, rng,
                                              fine_map=cfg.planner_fine_map, **pl_kw),
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
