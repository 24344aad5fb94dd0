"""Benchmarks: ``python -m plex_ma.bench {sim,env,turns,gymvec,geodesic,train,record,adam,order} [options] [--json]``.

``train`` times a short training (``--preset``, ``--method``, ``--steps``) end to end and
reports steps/s, the shares of wall time in simulation, inference and the update, the
networks' FLOPs per step, this machine's matmul GFLOP/s and the update's efficiency
(its FLOP/s over that matmul figure).

``sim``, ``env``, ``turns``, ``geodesic`` and ``gymvec``, the environment benches, are in
:mod:`plex_ma.bench_envs`, whose docstring describes them (``--help`` shows it here).

``order`` checks that the order of imports does not change the env's speed. It runs
``--rounds`` rounds of fresh child processes, one per module in ``--first`` (default
``plex_ma``, ``torch`` and ``numba``), each importing that module before plex_ma, in the
environment the bench was started with (without the ``OMP_WAIT_POLICY`` that ``python -m
plex_ma.bench`` chooses for itself); the order of the children rotates from round to round,
so that the machine's drift falls on all of them. Each child
times, best of ``--blocks`` blocks: ``single``, one ``gymnasium.make("plex_ma/PointNav-v0")``
env (an SB3- or RLlib-style loop); ``vector``, ``PointNavVectorEnv`` at ``--num-envs``
worlds (numba's threads share out the worlds); ``torch_env``, the single env with a
forward pass of a small CNN (SB3's NatureCNN) on each observation, torch at its default
threads (``--no-torch-env`` leaves it out). Each rate comes per second of wall time and
(``_cpu``) per second of the process's CPU time, which another process's load inflates
less. It reports numba's threading layer, the children's ``OMP_WAIT_POLICY`` after
``import plex_ma`` (a plain import leaves it, and torch's OpenMP runtime, alone), and a digest
of the vector env's last observations (the same in every child: the kernels give the same
results whatever the order). ``ratio`` is each child's median over the ``plex_ma``-first
child's.
``torch_env`` also times torch, as the children's environment sets it up: at its defaults
its OpenMP threads spin between operations, which on a busy machine slows it many times
over; ``OMP_WAIT_POLICY=PASSIVE python -m plex_ma.bench order`` times it waiting passively,
as plex_ma's own commands run it.

``record`` times the cost of the rerun recordings made during training: the same short
training (``--preset``, ``--updates`` executor updates, fresh run dirs) once without
recording and once with ``--record-interval``, after a warm-up run, and each
``record_training_episode`` call on its own. It prints the measured slowdown at that
interval and the one expected at ``--default-interval`` (the steady-state cost of one
recording over the training time of that many updates; the goal is at most 5 %).
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import os
import subprocess
import sys
import tempfile
import time

import gymnasium
import numba
import numpy as np
import torch

import plex_ma
import plex_ma.viz as vr
from plex_ma import bench_envs
from plex_ma.bench_envs import bench_env, bench_geodesic, bench_gymvec, bench_sim, bench_turns, machine
from plex_ma.cli import Parser, fail, integer, probability
from plex_ma.config import CNN_MIN_RESOLUTION, DEVICE_HELP, ENV_FIELDS, TrainConfig, preset_defaults, replace, setting, validate
from plex_ma.envs.sim import EpisodeFileError, SceneError
from plex_ma.envs.sim.core import MAX_RESOLUTION, MIN_RESOLUTION
from plex_ma.envs.vector import PointNavVectorEnv
from plex_ma.flops import matmul_gflops, model_flops_per_step
from plex_ma.trainers.device import describe
from plex_ma.trainers import make_trainer
from plex_ma.trainers.base import build_policies


# A child of ``bench order``: imports ``argv[1]`` before plex_ma, then times the envs.
_ORDER_CHILD = """
import importlib, sys
importlib.import_module(sys.argv[1])
import plex_ma
from plex_ma.bench import order_child
order_child(*sys.argv[2:])
"""


def order_child(steps: str, num_envs: str, resolution: str, blocks: str, torch_env: str) -> None:
    """One child of ``bench order`` (run after its first import): prints one JSON line."""
    steps, num_envs, resolution, blocks = int(steps), int(num_envs), int(resolution), int(blocks)
    cfg = dict(resolution=resolution, num_scenes=4, max_steps=200)
    rng = np.random.default_rng(0)
    env = gymnasium.make("plex_ma/PointNav-v0", **cfg)
    env.reset(seed=0)
    venv = PointNavVectorEnv(num_envs, seed=0, **cfg)
    venv.reset()
    net = torch.nn.Sequential(  # SB3's NatureCNN on RGB-D
        torch.nn.Conv2d(4, 32, 8, 4), torch.nn.ReLU(), torch.nn.Conv2d(32, 64, 4, 2), torch.nn.ReLU(),
        torch.nn.Conv2d(64, 64, 3, 1), torch.nn.ReLU(), torch.nn.Flatten(), torch.nn.LazyLinear(512))

    def single(n: int, with_torch: bool = False) -> None:
        for a in rng.integers(1, 4, n):
            obs, _, term, trunc, _ = env.step(int(a))
            if term or trunc:
                obs, _ = env.reset()
            if with_torch:
                x = np.concatenate([obs["rgb"] / np.float32(255), obs["depth"]], -1)
                with torch.no_grad():
                    net(torch.from_numpy(x).permute(2, 0, 1)[None])

    def vector(n: int) -> None:
        for a in rng.integers(1, 4, (n, num_envs)):
            venv.step(a)

    runs: dict[str, list[float]] = {}

    def timed(name: str, steps_done: int, fn, *args) -> None:
        t, c = time.perf_counter(), time.process_time()
        fn(*args)
        runs.setdefault(name, []).append(steps_done / (time.perf_counter() - t))
        runs.setdefault(name + "_cpu", []).append(steps_done / max(time.process_time() - c, 1e-9))

    single(20)  # compiled kernels loaded
    vector(5)
    calls = max(1, steps // num_envs)
    for _ in range(blocks):  # the envs alone first: no torch thread is awake yet
        timed("single", steps, single, steps)
        timed("vector", calls * num_envs, vector, calls)
    if torch_env == "1":
        single(5, True)
        for _ in range(blocks):
            timed("torch_env", max(1, steps // 2), single, max(1, steps // 2), True)
    digest = hashlib.sha256()
    for v in venv.step(np.ones(num_envs, np.int64))[0].values():
        digest.update(np.ascontiguousarray(v).tobytes())
    print(json.dumps({"threading_layer": numba.threading_layer(), "digest": digest.hexdigest()[:16],
                      "torch_threads": torch.get_num_threads(), "wait_policy": os.environ.get("OMP_WAIT_POLICY"),
                      **{k: max(v) for k, v in runs.items()}}))


def bench_order(first: tuple[str, ...] = ("plex_ma", "torch", "numba"), rounds: int = 3, steps: int = 300,
                num_envs: int = 16, resolution: int = 64, blocks: int = 3, torch_env: bool = True,
                timeout: float = 300.0) -> dict:
    """Env steps/s with different modules imported before plex_ma, each in fresh child
    processes, alternately (see the module docstring)."""
    measures = ("single", "vector") + (("torch_env",) if torch_env else ())
    measures += tuple(m + "_cpu" for m in measures)
    env = dict(os.environ)
    if plex_ma._set_wait_policy:  # the caller's environment, not the one this command chose
        env.pop("OMP_WAIT_POLICY", None)
    results: dict[str, list[dict]] = {m: [] for m in first}
    for r in range(rounds):
        for m in first[r % len(first):] + first[:r % len(first)]:
            out = subprocess.run([sys.executable, "-c", _ORDER_CHILD, m, str(steps), str(num_envs), str(resolution),
                                  str(blocks), str(int(torch_env))], capture_output=True, text=True, env=env,
                                 timeout=timeout)
            if out.returncode != 0:
                raise RuntimeError(f"bench order: the child importing {m} first failed:\n{out.stderr[-2000:]}")
            results[m].append(json.loads(out.stdout.strip().splitlines()[-1]))
    median = {m: {k: float(np.median([x[k] for x in rs])) for k in measures} for m, rs in results.items()}
    ref = median[first[0]]
    return {"benchmark": "order", "first": list(first), "rounds": rounds, "steps": steps, "num_envs": num_envs,
            "resolution": resolution, "steps_per_second": median,
            "ratio": {m: {k: v[k] / ref[k] for k in measures} for m, v in median.items()},
            "threading_layer": {m: sorted({x["threading_layer"] for x in rs}) for m, rs in results.items()},
            "wait_policy": {m: sorted({str(x["wait_policy"]) for x in rs}) for m, rs in results.items()},
            "identical": len({x["digest"] for rs in results.values() for x in rs}) == 1,
            "runs": results, "machine": machine()}


def bench_record(preset: str = "cpu", updates: int = 20, record_interval: int = 10, default_interval: int | None = None,
                 seed: int = 0, method: str = "plex-gru") -> dict:
    """Training time with and without recordings (see the module docstring)."""
    if default_interval is None:
        default_interval = TrainConfig().record_interval or 50
    base = preset_defaults(preset, method)
    calls: list[float] = []
    calls_cpu: list[float] = []
    sizes: list[int] = []
    def timed(trainer, *args, **kwargs):
        t, c = time.perf_counter(), time.process_time()
        out = vr.record_training_episode(trainer, *args, raise_errors=True, **kwargs)
        calls.append(time.perf_counter() - t)
        calls_cpu.append(time.process_time() - c)
        sizes.append(out.stat().st_size)
        return out

    def run(n_updates: int, interval: int) -> tuple[float, float]:
        with tempfile.TemporaryDirectory(prefix="bench_record_") as d:
            cfg = dataclasses.replace(base, total_steps=n_updates * base.num_envs * base.rollout_steps, run_dir=d,
                                      record_interval=interval, progress=False, seed=seed,
                                      checkpoint_interval=10**9)
            trainer = make_trainer(cfg, record=timed)
            t, c = time.perf_counter(), time.process_time()
            trainer.train()
            dt, dc = time.perf_counter() - t, time.process_time() - c
            trainer.close()
        return dt, dc

    run(1, 0)  # warm-up: compiled kernels, torch
    t_off, c_off = run(updates, 0)
    t_on, c_on = run(updates, record_interval)
    per_update, per_update_cpu = t_off / updates, c_off / updates

    def steady(xs):  # the first recording also builds the val scenes once per run
        return float(np.median(xs[1:])) if len(xs) > 1 else (xs[0] if xs else float("nan"))

    return {"benchmark": "record", "preset": preset, "method": method, "updates": updates,
            "env_steps_per_update": base.num_envs * base.rollout_steps, "record_interval": record_interval,
            "seconds_without_recording": t_off, "seconds_with_recording": t_on, "recordings": len(calls),
            "measured_overhead": t_on / t_off - 1.0, "seconds_per_update": per_update,
            "seconds_per_recording": calls, "seconds_per_recording_steady": steady(calls),
            "cpu_seconds_without_recording": c_off, "cpu_seconds_with_recording": c_on,
            "measured_cpu_overhead": c_on / c_off - 1.0, "cpu_seconds_per_recording": calls_cpu,
            "recording_bytes": sizes, "default_interval": default_interval,
            "expected_overhead_at_default_interval": steady(calls) / (default_interval * per_update),
            "expected_cpu_overhead_at_default_interval": steady(calls_cpu) / (default_interval * per_update_cpu),
            "machine": machine()}


def bench_train(preset: str = "cpu", method: str = "plex-gru", steps: int = 8192, num_envs: int | None = None,
                resolution: int | None = None, seed: int = 0, overrides: dict[str, str] | None = None,
                device: str = "auto") -> dict:
    """End-to-end training throughput of a short run (``python -m plex_ma.bench train``).

    Reports steps/s, the shares of wall time in simulation, inference and the update (and,
    for PLEX, each agent's learning within the update: the two run side by side), the
    models' FLOPs per step, this machine's matmul GFLOP/s with the same torch threads, and
    the update's efficiency: the update's FLOPs (3x forward per sample per epoch) over its
    wall time, divided by the matmul figure. ``overrides`` sets further TrainConfig fields
    from strings (``{"num_minibatches": "4"}``); an unknown field raises ValueError.
    """
    cfg = preset_defaults(preset, method)
    over = {"total_steps": steps, "progress": False, "seed": seed, "checkpoint_interval": 10**9, "device": device}
    if num_envs:
        over["num_envs"] = num_envs
    if resolution:
        over["resolution"] = resolution
    fields = ({f.name for f in dataclasses.fields(cfg)} - {"env"}) | ENV_FIELDS
    for key, text in (overrides or {}).items():
        if key not in fields:
            raise ValueError(f"--set: TrainConfig and its env have no field {key!r}")
        current = setting(cfg, key)
        if isinstance(current, bool):
            if text.lower() not in ("true", "false", "1", "0"):
                raise ValueError(f"--set {key}: expected true or false, got {text!r}")
            over[key] = text.lower() in ("true", "1")
        elif isinstance(current, (int, float)):
            try:
                over[key] = type(current)(text)
            except ValueError:
                raise ValueError(f"--set {key}: expected a {type(current).__name__}, got {text!r}") from None
        else:
            over[key] = text
    with tempfile.TemporaryDirectory() as d:
        cfg = validate(replace(cfg, run_dir=d, **over))
        trainer = make_trainer(cfg, log=True)
        result = trainer.train()
        trainer.close()
    flops = {k: model_flops_per_step(m.cpu()) for k, m in trainer.nets.items()}
    worker = "executor" if "executor" in flops else "policy"
    if cfg.torch_threads:
        torch.set_num_threads(cfg.torch_threads)
    peak = matmul_gflops(device=trainer.device)
    update_s = result["perf/share_update"] * steps / result["perf/fps"]
    # forward + backward ~ 3x the forward FLOPs, per stored transition and epoch
    n_worker = trainer.updates[worker] * cfg.num_envs * cfg.rollout_steps
    n_planner = trainer.updates.get("planner", 0) * cfg.n_pl * cfg.num_envs
    update_flops = 3 * cfg.ppo_epochs * (n_worker * flops[worker] + n_planner * flops.get("planner", 0.0))
    achieved = update_flops / max(update_s, 1e-9) / 1e9
    return {"benchmark": "train", "method": method, "preset": preset, "num_envs": cfg.num_envs,
            "resolution": cfg.env.resolution, "steps": steps, "steps_per_second": result["perf/fps"],
            "share_sim": result["perf/share_sim"], "share_inference": result["perf/share_inference"],
            "share_update": result["perf/share_update"], "share_other": result["perf/share_other"],
            # PLEX: each agent's learning inside the update (side by side, so they may overlap)
            "share_learn": {k[len("perf/share_learn_"):]: v for k, v in result.items() if k.startswith("perf/share_learn_")},
            "model_flops_per_step": flops,
            "matmul_gflops": peak, "update_gflops": achieved, "update_efficiency": achieved / peak,
            "torch_threads": torch.get_num_threads(), **describe(trainer.device), "overrides": dict(overrides or {})}


def bench_adam(preset: str = "cpu", steps: int = 20, rounds: int = 5, threads: int = 1) -> dict:
    """Milliseconds per Adam step over each PLEX network's parameters, for torch's three
    implementations (per-tensor loop, foreach, fused), timed in alternating rounds."""


    torch.set_num_threads(threads)
    out = {"preset": preset, "threads": threads}
    for name, net in build_policies(preset_defaults(preset)).items():
        for q in net.parameters():
            q.grad = torch.randn_like(q)
        opts = {impl: torch.optim.Adam(net.parameters(), lr=1e-6, eps=1e-5, **kw)
                for impl, kw in (("loop", {"foreach": False}), ("foreach", {"foreach": True}), ("fused", {"fused": True}))}
        times = {impl: [] for impl in opts}
        for o in opts.values():
            o.step()  # state allocated before timing
        for _ in range(rounds):
            for impl, o in opts.items():
                t = time.perf_counter()
                for _ in range(steps):
                    o.step()
                times[impl].append((time.perf_counter() - t) / steps * 1e3)
        out[f"{name}_params"] = sum(q.numel() for q in net.parameters())
        for impl, ts in times.items():
            out[f"{name}_{impl}_ms"] = float(np.median(ts))
    return out


def _run(p: argparse.ArgumentParser, a: argparse.Namespace) -> dict:
    """The benchmark the command line asks for."""
    if a.what == "adam":
        out = bench_adam(a.preset, a.steps, a.rounds, a.threads)
        out["machine"] = machine()
    elif a.what == "train":
        overrides = {}
        for item in a.set:
            key, sep, value = item.partition("=")
            if not sep:
                p.error(f"--set expects FIELD=VALUE, got {item!r}")
            overrides[key.strip()] = value.strip()
        try:
            out = bench_train(a.preset, a.method, a.steps, a.num_envs, a.resolution, a.seed, overrides, a.device)
        except ValueError as e:
            p.error(str(e))
        out["machine"] = machine()
    elif a.what == "sim":
        out = bench_sim(a.num_envs, a.resolution, a.steps, a.seed, a.scenes, a.num_scenes)
    elif a.what == "gymvec":
        out = bench_gymvec(a.num_envs, a.resolution, a.steps, a.seed, a.scenes, a.num_scenes, rounds=a.rounds,
                           warmup=a.warmup, stop_prob=a.stop_prob, max_steps=a.max_steps)
    elif a.what == "turns":
        out = bench_turns(a.resolution, a.turns, a.seed, a.scenes, a.num_scenes, rounds=a.rounds, warmup=a.warmup,
                          planner_stop_prob=a.planner_stop_prob, executor_stop_prob=a.executor_stop_prob)
    elif a.what == "geodesic":
        out = bench_geodesic(a.queries, a.seed, a.scenes, a.num_scenes, astar_queries=a.astar_queries)
    elif a.what == "order":
        out = bench_order(tuple(a.first), a.rounds, a.steps, a.num_envs, a.resolution, a.blocks,
                          torch_env=not a.no_torch_env)
    elif a.what == "record":
        out = bench_record(a.preset, a.updates, a.record_interval, a.default_interval, a.seed, a.method)
    else:
        out = bench_env(a.num_envs, a.resolution, a.steps, a.seed, a.scenes, aec_turns=a.aec_turns,
                        planner_stop_prob=a.planner_stop_prob, executor_stop_prob=a.executor_stop_prob,
                        num_scenes=a.num_scenes, rounds=a.rounds, warmup=a.warmup)
    return out


def _help() -> str:
    """This module's docstring with, in place of its paragraph that points to
    :mod:`plex_ma.bench_envs`, that module's paragraphs: the ``--help`` text."""
    paras = __doc__.split("\n\n")
    i = next(k for k, para in enumerate(paras) if ":mod:`plex_ma.bench_envs`" in para)
    return "\n\n".join(paras[:i] + bench_envs.__doc__.strip().split("\n\n")[1:] + paras[i + 1:])


_POSITIVE, _AT_LEAST_0 = integer(1), integer(0)


def _common(sp, steps: int, steps_help: str) -> None:
    """The options every batched environment bench shares."""
    sp.add_argument("--num-envs", type=_POSITIVE, default=64, help="worlds stepped per call")
    sp.add_argument("--resolution", type=integer(MIN_RESOLUTION, MAX_RESOLUTION), default=128,
                    help="square image size in pixels")
    sp.add_argument("--steps", type=_POSITIVE, default=steps, help=steps_help)
    sp.add_argument("--seed", type=_AT_LEAST_0, default=0)
    sp.add_argument("--scenes", default="procgen", help="scene source")
    sp.add_argument("--num-scenes", type=_POSITIVE, default=None,
                    help="training scenes (default: all of the source's)")
    sp.add_argument("--json", action="store_true", help="print one JSON object")


def _add_env_benches(sub) -> None:
    """The environment benches' subcommands."""
    ps = sub.add_parser("sim", help="raw batched simulator throughput")
    _common(ps, 300, "batched steps to time")
    pe = sub.add_parser("env", help="AEC env turns/s, vector env steps/s and their ratio to the raw simulator")
    _common(pe, 200, "vector env calls to time (the raw simulator gets as many)")
    pe.add_argument("--rounds", type=_POSITIVE, default=10, help="alternate the vector env and the raw simulator this "
                    "many times (both timed in each round)")
    pe.add_argument("--warmup", type=_AT_LEAST_0, default=20, help="untimed calls of each before timing")
    pe.add_argument("--aec-turns", type=_POSITIVE, default=2000, help="AEC turns to time")
    pe.add_argument("--planner-stop-prob", type=probability, default=0.01, help="chance that a planner action is STOP")
    pe.add_argument("--executor-stop-prob", type=probability, default=0.1, help="chance that an executor action is STOP")
    h = "one world: env() and compat_env() turns/s against the raw one-world simulator, alternating"
    pn = sub.add_parser("turns", help=h, description=h)
    pn.add_argument("--resolution", type=integer(MIN_RESOLUTION, MAX_RESOLUTION), default=128,
                    help="square image size in pixels")
    pn.add_argument("--turns", type=_POSITIVE, default=1000, help="turns (simulator steps) of each per round")
    pn.add_argument("--rounds", type=_POSITIVE, default=5, help="rounds; each times all three, first one rotating")
    pn.add_argument("--warmup", type=_AT_LEAST_0, default=100, help="untimed turns of each before timing")
    pn.add_argument("--seed", type=_AT_LEAST_0, default=0)
    pn.add_argument("--scenes", default="procgen", help="scene source")
    pn.add_argument("--num-scenes", type=_POSITIVE, default=None, help="training scenes (default: all of the source's)")
    pn.add_argument("--planner-stop-prob", type=probability, default=0.01, help="chance that a planner action is STOP")
    pn.add_argument("--executor-stop-prob", type=probability, default=0.1, help="chance that an executor action is STOP")
    pn.add_argument("--json", action="store_true", help="print one JSON object")
    h = "make_vec's batched PointNav vector env against SyncVectorEnv of single envs (default: 16 worlds at 64 px)"
    pv = sub.add_parser("gymvec", help=h, description=h)
    _common(pv, 300, "vector steps to time (each env gets as many)")
    pv.set_defaults(num_envs=16, resolution=64)
    pv.add_argument("--rounds", type=_POSITIVE, default=10, help="alternate the two envs this many times")
    pv.add_argument("--warmup", type=_AT_LEAST_0, default=20, help="untimed steps of each before timing")
    pv.add_argument("--stop-prob", type=probability, default=0.0, help="chance that an action is STOP (ends the episode)")
    pv.add_argument("--max-steps", type=_POSITIVE, default=500, help="actions before an episode truncates")
    pg = sub.add_parser("geodesic", help="sub-goal distance queries: corner graphs against A*, one thread")
    pg.add_argument("--queries", type=_POSITIVE, default=4000, help="queries to time")
    pg.add_argument("--astar-queries", type=_POSITIVE, default=500, help="of those, how many A* answers too")
    pg.add_argument("--seed", type=_AT_LEAST_0, default=0)
    pg.add_argument("--scenes", default="procgen", help="scene source")
    pg.add_argument("--num-scenes", type=_POSITIVE, default=None, help="training scenes (default: the source's)")
    pg.add_argument("--json", action="store_true", help="print one JSON object")


def _add_other_benches(sub) -> None:
    """The subcommands of the import-order, recording, training and optimiser benches."""
    po = sub.add_parser("order", help="env steps/s with torch or numba imported before plex_ma, in fresh processes")
    po.add_argument("--first", nargs="+", default=["plex_ma", "torch", "numba"],
                    help="modules to import before plex_ma, one child each (the first is the reference)")
    po.add_argument("--rounds", type=_POSITIVE, default=3, help="children per module, in rotating order")
    po.add_argument("--steps", type=_POSITIVE, default=300, help="single-env steps per timed block")
    po.add_argument("--num-envs", type=_POSITIVE, default=16, help="worlds of the vector env")
    po.add_argument("--resolution", type=integer(CNN_MIN_RESOLUTION, MAX_RESOLUTION), default=64,
                    help=f"square image size in pixels (at least {CNN_MIN_RESOLUTION}, for the CNN)")
    po.add_argument("--blocks", type=_POSITIVE, default=3, help="timed blocks per child (the best counts)")
    po.add_argument("--no-torch-env", action="store_true", help="leave out the env + CNN loop")
    po.add_argument("--json", action="store_true", help="print one JSON object")
    pr = sub.add_parser("record", help="training time with and without rerun recordings (the overhead)")
    pr.add_argument("--preset", default="cpu", help="training preset")
    pr.add_argument("--method", default="plex-gru", help="training method")
    pr.add_argument("--updates", type=_POSITIVE, default=20, help="executor updates per timed training")
    pr.add_argument("--record-interval", type=_POSITIVE, default=10, help="updates between recordings in the timed run")
    pr.add_argument("--default-interval", type=_POSITIVE, default=None,
                    help="interval to extrapolate to (default: TrainConfig.record_interval)")
    pr.add_argument("--seed", type=_AT_LEAST_0, default=0)
    pr.add_argument("--json", action="store_true", help="print one JSON object")
    pt = sub.add_parser("train", help="end-to-end training steps/s, time shares, FLOPs and update efficiency")
    pt.add_argument("--preset", default="cpu", help="training preset")
    pt.add_argument("--method", default="plex-gru", help="training method")
    pt.add_argument("--steps", type=_POSITIVE, default=8192, help="environment steps to train for")
    pt.add_argument("--num-envs", type=_POSITIVE, default=None, help="worlds (default: the preset's)")
    pt.add_argument("--resolution", type=integer(CNN_MIN_RESOLUTION, MAX_RESOLUTION), default=None,
                    help="image size (default: the preset's)")
    pt.add_argument("--seed", type=_AT_LEAST_0, default=0)
    pt.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                    help="override a TrainConfig field, e.g. --set num_minibatches=4 (repeatable)")
    pt.add_argument("--device", default="auto", help=DEVICE_HELP)
    pt.add_argument("--json", action="store_true", help="print one JSON object")
    pa = sub.add_parser("adam", help="ms per Adam step over the PLEX networks: per-tensor loop, foreach, fused")
    pa.add_argument("--preset", default="cpu", help="training preset (the networks' sizes)")
    pa.add_argument("--steps", type=_POSITIVE, default=20, help="steps per timed round")
    pa.add_argument("--rounds", type=_POSITIVE, default=5, help="alternate the three implementations this many times")
    pa.add_argument("--threads", type=_POSITIVE, default=1, help="torch threads")
    pa.add_argument("--json", action="store_true", help="print one JSON object")


def main(argv: list[str] | None = None) -> None:
    p = Parser(prog="python -m plex_ma.bench", description=_help(),
               formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="what", required=True)
    _add_env_benches(sub)
    _add_other_benches(sub)
    a = p.parse_args(argv)
    try:
        out = _run(p, a)
    except (SceneError, EpisodeFileError) as e:  # a bad --scenes: one line, no traceback
        fail(e)
    if a.json:
        print(json.dumps(out))
    else:
        for k, v in out.items():
            print(f"{k:>34}: {v:,.3f}" if isinstance(v, float) else f"{k:>34}: {v}")
        if a.what == "record":
            print(f"\nrecording overhead (wall time / CPU time): {100 * out['measured_overhead']:+.1f} % / "
                  f"{100 * out['measured_cpu_overhead']:+.1f} % measured with a recording every "
                  f"{out['record_interval']} updates; {100 * out['expected_overhead_at_default_interval']:.1f} % / "
                  f"{100 * out['expected_cpu_overhead_at_default_interval']:.1f} % expected at the default interval "
                  f"({out['default_interval']} updates)")

if __name__ == "__main__":
    main()
