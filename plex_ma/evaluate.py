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

from plex_ma.config import TrainConfig
from plex_ma.envs.rules import CLOSE_FAR_SPLIT, PLANNER
from plex_ma.envs.sim import generate_episodes, load_episodes
from plex_ma.envs.vector import PlexVectorEnv, PointNavVectorEnv
from plex_ma.trainers.checkpoint import CheckpointError, load_checkpoint
from plex_ma.trainers.plex import build_policies, env_kwargs, saved_config

METRICS = ("success", "spl", "reward", "distance_to_goal", "collisions")


def load_policies(path: str | Path) -> tuple[TrainConfig, dict]:
    """The config and networks stored in a checkpoint (loaded with ``weights_only=True``)."""
    state = load_checkpoint(path)
    known = {f.name for f in dataclasses.fields(TrainConfig)}
    cfg = TrainConfig(**{k: v for k, v in saved_config(state).items() if k in known})
    nets = build_policies(cfg)
    try:
        for k, m in nets.items():
            m.load_state_dict(state["models"][k])
            m.eval()
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


@torch.no_grad()
def run_episodes(cfg: TrainConfig, nets: dict, split: str = "test", episodes: int = 100, scenes: str | None = None,
                 num_envs: int = 8, episodes_file: str | None = None, recorder=None) -> list[dict]:
    """Run each episode once, greedily; returns one result dict per episode (by episode_id)."""
    scenes = scenes or cfg.scenes
    kw = env_kwargs(dataclasses.replace(cfg, scenes=scenes), split)
    if episodes_file:
        kw["episodes_file"] = episodes_file
    plex = cfg.method.startswith("plex")
    if plex:
        env = PlexVectorEnv(num_envs, seed=0, n_ex=cfg.n_ex, rho_max=cfg.rho_max, eli=cfg.eli, **kw)
    else:
        env = PointNavVectorEnv(num_envs, seed=0, **kw)
    eps = episode_set(env, split, episodes, seed=12345)
    wanted = {e.episode_id for e in eps}
    if len(wanted) != len(eps):  # generated sets number their episodes 0..n-1; files must too
        raise ValueError("episode ids in the evaluation set are not unique")
    # Worlds take the set's episodes in order as they free up; once the set is exhausted
    # they cycle through it again and those repeats (identical, as all is greedy) are ignored.
    env.worlds.fixed_episodes = eps
    results: dict[int, dict] = {}
    ret = np.zeros(num_envs)
    if plex:
        planner, executor = nets["planner"], nets["executor"]
        turn, pl_obs, ex_obs = env.reset()
        state = executor.initial_state(num_envs)
        starts = np.ones(num_envs, np.bool_)
    else:
        policy = nets["policy"]
        obs = env.reset()
        state = policy.initial_state(num_envs)
        starts = np.ones(num_envs, np.bool_)
    if recorder is not None:
        recorder.begin(env)

    def finish(res_infos, ended):
        for k, i in enumerate(ended):
            info = res_infos[k]
            if info["episode_id"] in wanted and info["episode_id"] not in results:
                keep = ("success", "spl", "distance_to_goal", "collisions", "geodesic_distance", "scene_id",
                        "episode_id", "steps")
                results[info["episode_id"]] = {**{m: info[m] for m in keep}, "reward": float(ret[i])}
            ret[i] = 0.0

    while len(results) < len(eps):
        if plex:
            while np.any(turn == PLANNER):
                rows = np.flatnonzero(turn == PLANNER)
                out = planner.act({k: v[rows] for k, v in pl_obs.items()}, deterministic=True)
                stop = np.zeros(num_envs, np.int64)
                sub = np.zeros((num_envs, 2), np.float32)
                stop[rows] = out["stop"].numpy()
                sub[rows] = out["subgoal_env"].numpy()
                res = env.step(stop=stop, subgoal=sub)
                ret += res.rewards[:, 0]
                if recorder is not None:
                    recorder.step(env, res, rows=rows)
                finish(res.episode_infos, np.flatnonzero(res.terminated | res.truncated))
                turn, pl_obs, ex_obs = res.turn, res.planner_obs, res.executor_obs
                starts[rows] = True
                if len(results) == len(eps):  # a planner that always stops never leaves this loop
                    break
            if len(results) == len(eps):
                break
            out, state = executor.act(ex_obs, state, starts, deterministic=True)
            res = env.step(action=out["action"].numpy(), eli=out["eli"].numpy())
            ret += res.rewards[:, 0]
            if recorder is not None:
                recorder.step(env, res, eli=out["eli"].numpy())
            ended = res.terminated | res.truncated
            finish(res.episode_infos, np.flatnonzero(ended))
            starts = (res.executor_turn_end & env.executor_memory_restart) | ended
            turn, pl_obs, ex_obs = res.turn, res.planner_obs, res.executor_obs
        else:
            out, state = policy.act(obs, state, starts, deterministic=True)
            obs, rew, term, trunc, infos = env.step(out["action"].numpy())
            if recorder is not None:
                recorder.step(env, (obs, rew, term, trunc, infos))
            ret += rew
            ended = term | trunc
            finish(infos, np.flatnonzero(ended))
            starts = ended
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
    p.add_argument("--checkpoint", required=True, help="checkpoint file (e.g. runs/x/latest.pt)")
    p.add_argument("--split", choices=["val", "test"], default="test", help="episode set")
    p.add_argument("--episodes", type=int, default=1000, help="how many of the set's episodes to run")
    p.add_argument("--scenes", default=None, help="scene source (default: the one trained on)")
    p.add_argument("--episodes-file", default=None, help="a fixed episode file instead of the split's default")
    p.add_argument("--num-envs", type=int, default=8, help="worlds run in parallel")
    p.add_argument("--json", default=None, help="write the summary and per-episode results here")
    p.add_argument("--record", default=None, help="also record the episodes to this .rrd file (rerun)")
    p.add_argument("--torch-threads", type=int, default=1,
                   help="torch threads (1: small batches run fastest on a small, shared machine)")
    a = p.parse_args(argv)
    if a.torch_threads > 0:
        torch.set_num_threads(a.torch_threads)
    if a.episodes < 1:
        p.error("--episodes must be >= 1")
    try:
        cfg, nets = load_policies(a.checkpoint)
    except CheckpointError as e:
        print(f"error: {e}", file=sys.stderr)
        raise SystemExit(2)
    if a.episodes_file:
        load_episodes(a.episodes_file)  # fail early with a clear message
    recorder = None
    if a.record:
        from plex_ma.viz.record import EpisodeRecorder

        recorder = EpisodeRecorder(a.record)
    results = run_episodes(cfg, nets, a.split, a.episodes, a.scenes, a.num_envs, a.episodes_file, recorder)
    summary = summarize(results)
    print(format_table(summary, f"{cfg.method} on {a.scenes or cfg.scenes}/{a.split} ({a.checkpoint})"))
    if a.json:
        Path(a.json).parent.mkdir(parents=True, exist_ok=True)
        Path(a.json).write_text(json.dumps({**summary, "method": cfg.method, "checkpoint": str(a.checkpoint),
                                            "split": a.split, "scenes": a.scenes or cfg.scenes,
                                            "per_episode": results}, indent=1))
    return summary


if __name__ == "__main__":
    main(sys.argv[1:])
