"""plex_nav_v0: PettingZoo's own tests, then what they cannot see (turn order, rewards,
ELI, sub-goals, success, SPL, infos, pickling) and bad input."""

from __future__ import annotations

import math
import pickle

import numpy as np
import pytest
from pettingzoo.test import api_test, performance_benchmark, render_test, seed_test

from plex_ma.envs import plex_nav_v0
from plex_ma.envs.actions import InvalidAction
from plex_ma.envs.rules import PLANNER, OneStep, PlexConfig, PlexWorlds
from plex_ma.envs.sim import Episode

from .env_helpers import (SMALL, assert_same_state, drive, executor_action, line_episode, planner_action,
                          state_snapshot)

pytestmark = pytest.mark.filterwarnings("ignore::UserWarning")


# ---------------------------------------------------------------- PettingZoo's tests
@pytest.mark.parametrize("config", [
    dict(SMALL),
    dict(SMALL, eli=False),
    dict(SMALL, resolution=128),
    dict(SMALL, n_ex=2, max_steps=6),  # episodes that truncate
    dict(SMALL, pose_noise=(0.05, 0.02)),
], ids=["64px", "eli_off", "128px", "truncating", "noisy_pose"])
def test_api(config):
    api_test(plex_nav_v0.env(**config), num_cycles=1000)
    api_test(plex_nav_v0.raw_env(**config), num_cycles=200)


@pytest.mark.parametrize("config", [dict(SMALL), dict(SMALL, pose_noise=(0.05, 0.02))], ids=["exact", "noisy_pose"])
def test_seed(config):
    seed_test(lambda: plex_nav_v0.env(**config), num_cycles=300)


def test_render(headless):
    assert plex_nav_v0.raw_env.metadata["render_modes"] == ["human", "rgb_array"]
    render_test(lambda render_mode=None: plex_nav_v0.env(render_mode=render_mode, **SMALL))
    render_test(lambda render_mode=None: plex_nav_v0.raw_env(render_mode=render_mode, **SMALL))
    e = plex_nav_v0.env(render_mode="rgb_array", **SMALL)
    e.reset(seed=0)
    img = e.render()
    assert img.ndim == 3 and img.shape[2] == 3 and img.dtype == np.uint8 and img.std() > 0


def test_human_mode_headless_warns_once_and_runs_on(headless):
    with pytest.warns(UserWarning, match="render_mode='human' shows nothing here: no display") as got:
        for seed in range(2):  # two envs, two episodes each: still one warning
            env = plex_nav_v0.env(render_mode="human", **SMALL)
            for _ in range(2):
                env.reset(seed=seed)
                drive(env, [1] * 3)
                assert env.render() is None
            env.close()
    assert len([w for w in got if "render_mode='human'" in str(w.message)]) == 1
    assert env.unwrapped._viewer.shown == 0


def test_human_mode_draws_each_step_in_the_window(monkeypatch):
    # The window itself needs a display; matplotlib's Agg canvas stands in for it here.
    pytest.importorskip("matplotlib")
    import matplotlib
    import matplotlib.pyplot as plt

    from plex_ma.envs import viewer

    monkeypatch.setattr(viewer, "display_problem", lambda: None)
    backend = matplotlib.get_backend()
    plt.switch_backend("agg")
    try:
        env = plex_nav_v0.env(render_mode="human", **SMALL)
        env.unwrapped._viewer.period = 0.0
        ref = plex_nav_v0.env(render_mode="rgb_array", **SMALL)
        for e in (env, ref):
            e.reset(seed=4)
        assert env.unwrapped._viewer.shown == 1  # reset draws
        for e in (env, ref):
            drive(e, [1, 2])
        v = env.unwrapped._viewer
        assert v.shown == 1 + 1 + 2  # and so does every step (planner, executor, executor)
        np.testing.assert_array_equal(np.asarray(v._image.get_array()), ref.render())
        assert env.render() is None and v.shown == 5
        num = v._fig.number
        env.close()
        assert not plt.fignum_exists(num)
    finally:
        plt.switch_backend(backend)


def test_performance_benchmark(capsys):
    performance_benchmark(plex_nav_v0.env(**SMALL))  # runs ~5 s and only prints
    assert "turns per second" in capsys.readouterr().out


def test_max_cycles_test_does_not_apply():
    # The docstring says why pettingzoo.test.max_cycles_test is not run: no max_cycles
    # argument (length is bounded by max_steps executor actions) and no round-robin cycles.
    assert "max_cycles_test" in plex_nav_v0.__doc__
    with pytest.raises(TypeError):
        plex_nav_v0.env(max_cycles=10, **SMALL)


# ---------------------------------------------------------------- episode end
def test_truncation_after_max_steps_when_planner_never_stops():
    env = plex_nav_v0.env(**SMALL)
    env.reset(seed=3)
    rng = np.random.default_rng(0)
    executor_actions = 0
    planner_turns = 0
    while not (env.truncations["planner"] or env.terminations["planner"]):
        if env.agent_selection == "planner":
            planner_turns += 1
            env.step(planner_action(0, rng.uniform(0.5, 4.0), rng.uniform(-3, 3)))
        else:
            env.step(executor_action(int(rng.integers(1, 4))))  # never STOP
            executor_actions += 1
    assert executor_actions == 500
    assert planner_turns == 50  # n_ex = 10 actions per turn, none cut short by STOP
    assert env.truncations == {"planner": True, "executor": True}
    assert env.terminations == {"planner": False, "executor": False}
    for a in ("planner", "executor"):
        assert env.infos[a]["steps"] == 500 and env.infos[a]["success"] == 0.0 and env.infos[a]["spl"] == 0.0
    # Then one dead step each, and the episode is over.
    dead = []
    while env.agents:
        _, _, term, trunc, _ = env.last()
        assert trunc and not term
        dead.append(env.agent_selection)
        env.step(None)
    assert sorted(dead) == ["executor", "planner"]
    with pytest.raises(InvalidAction, match="after the episode ended"):
        env.step(None)


def test_planner_stop_terminates_both():
    env = plex_nav_v0.env(**SMALL)
    env.reset(seed=1)
    env.step(planner_action(0, 2.0, 0.5))
    env.step(executor_action(1))
    env.step(executor_action(0))
    assert env.agent_selection == "planner"
    env.step(planner_action(1))
    assert env.terminations == {"planner": True, "executor": True}
    assert env.truncations == {"planner": False, "executor": False}
    env.step(None)
    env.step(None)
    assert env.agents == []


# ---------------------------------------------------------------- turn order and rewards
def test_turn_order_and_accumulated_rewards():
    """An executor turn lasts at most n_ex actions and ends at STOP; last() gives each
    agent the sum of the per-step rewards it got since it last acted."""
    n_ex = 4
    env = plex_nav_v0.env(n_ex=n_ex, max_steps=300, **SMALL)
    rng = np.random.default_rng(7)
    turns_ended_by_stop = turns_ended_by_limit = 0
    planner_rewards_seen = []
    for episode in range(4):
        env.reset(seed=episode)
        pending = {"planner": 0.0, "executor": 0.0}  # sum of env.rewards since the agent last acted
        run = 0  # executor actions in the current turn
        last_exec_action = None
        for agent in env.agent_iter():
            obs, reward, term, trunc, info = env.last()
            assert reward == pytest.approx(pending[agent], abs=1e-5), agent
            pending[agent] = 0.0
            if agent == "planner":
                planner_rewards_seen.append(reward)
                if run:
                    # The executor handed back control: by STOP, or after n_ex actions.
                    assert run <= n_ex
                    if last_exec_action == 0:
                        turns_ended_by_stop += 1
                    else:
                        assert run == n_ex
                        turns_ended_by_limit += 1
                run = 0
            if term or trunc:
                action = None
            elif agent == "planner":
                action = planner_action(int(rng.random() < 0.05), rng.uniform(0.5, 4), rng.uniform(-3, 3))
            else:
                last_exec_action = 0 if rng.random() < 0.25 else int(rng.integers(1, 4))
                action = executor_action(last_exec_action)
                run += 1
                assert run <= n_ex
            env.step(action)
            for a, r in env.rewards.items():
                pending[a] += r
    assert turns_ended_by_stop > 3 and turns_ended_by_limit > 3
    # The planner earns during the executor's turn: its last() rewards are not all zero.
    assert sum(abs(r) > 1e-6 for r in planner_rewards_seen) > 10


def test_planner_reward_is_sum_over_executor_turn():
    env = plex_nav_v0.env(**SMALL)
    env.reset(seed=11)
    env.step(planner_action(0, 3.0, 0.0))
    total = env.rewards["planner"]
    per_step = []
    while env.agent_selection == "executor":
        env.step(executor_action(1))
        per_step.append(env.rewards["planner"])
    total += sum(per_step)
    assert len(per_step) == 10
    assert all(r != 0.0 for r in per_step)  # slack at least
    assert env.last()[1] == pytest.approx(total, abs=1e-5)
    assert env._cumulative_rewards["planner"] == pytest.approx(total, abs=1e-5)


def test_rewards_match_the_rules():
    env = plex_nav_v0.env(**SMALL)
    env.reset(seed=0)
    raw = env.unwrapped
    ep = line_episode(raw, 2.0)
    env.reset(options={"episode": ep})
    w = raw.worlds
    env.step(planner_action(0, 1.0, 0.0))
    d_goal, d_sub = w.sim.distance_to_goal[0], w.subgoal_dist[0]
    env.step(executor_action(1))  # forward 0.25 m along a free corridor, towards both
    assert env.rewards["planner"] == pytest.approx(d_goal - w.sim.distance_to_goal[0] - 0.01, abs=1e-5)
    assert env.rewards["executor"] == pytest.approx(d_sub - w.subgoal_dist[0] - 0.01, abs=1e-5)
    assert d_goal - w.sim.distance_to_goal[0] == pytest.approx(0.25, abs=0.02)
    for _ in range(3):
        env.step(executor_action(1))
    assert w.subgoal_dist[0] < 0.5
    env.step(executor_action(0))  # STOP within 0.5 m of the sub-goal: +1, and the turn ends
    assert env.rewards["executor"] == pytest.approx(1.0 - 0.01, abs=0.02)
    assert env.agent_selection == "planner"
    # A sub-goal set within reach earns no bonus: a STOP on the spot is not a reach.
    env.step(planner_action(0, 0.3, 0.0))
    assert w.subgoal_dist[0] < 0.5
    env.step(executor_action(0))
    assert env.rewards["executor"] == pytest.approx(-0.01, abs=1e-6)
    assert env.agent_selection == "planner"


@pytest.mark.parametrize("config", [
    dict(SMALL, pose_noise=(0.05, 0.02)),
    dict(SMALL, n_ex=3, max_steps=40, eli=False, subgoal_radius=1.0, success_distance=1.0,
         executor_stop_penalty=-0.5, executor_collision_reward=-0.2),
], ids=["noisy_pose", "penalties_truncating"])
def test_one_world_step_is_the_batched_step(config):
    """``PlexWorlds.step_one`` (the AEC env's, with its scalar path for the executor) does what
    ``step`` does with the action as one row: the same results and state, bit for bit, for the
    common action types and for those it hands to ``step`` (a float, a 0-d array, a list)."""
    cfg = PlexConfig(**config)
    one, batched = PlexWorlds(cfg, 1, seed=5), PlexWorlds(cfg, 1, seed=5)
    rng = np.random.default_rng(0)
    state = ("turn", "turn_steps", "subgoal", "subgoal_raw", "subgoal_dist", "subgoal_dist0", "eli",
             "planner_decisions", "steps", "collisions", "done", "success", "spl")
    for t in range(600):
        if t == 0 or one.done[0]:
            one.reset_rows([0])
            batched.reset_rows([0])
        if one.turn[0] == PLANNER:
            stop = int(rng.random() < 0.03)
            sg = np.array([rng.uniform(0, 4), rng.uniform(-np.pi, np.pi)], (np.float32, np.float64)[t % 2])
            kw = dict(stop=(stop, np.int64(stop), np.array(stop), float(stop))[t % 4], subgoal=sg)
        else:
            a = int(rng.integers(0, 4))
            eli = rng.normal(size=128).astype((np.float32, np.float64)[t % 2])
            kw = dict(action=(a, np.int8(a), np.array(a), float(a))[t % 4], eli=eli if t % 5 else list(eli))
        got = one.step_one(**kw)
        want = OneStep.of(batched.step(**{k: np.asarray(v)[None] for k, v in kw.items()}))
        assert got == want and all(type(x) is type(y) for x, y in zip(got, want))
        for name in state:
            np.testing.assert_array_equal(getattr(one, name), getattr(batched, name), err_msg=name)
        for name in ("pos", "heading", "est_pose", "distance_to_goal", "rgb", "depth", "amap"):
            np.testing.assert_array_equal(getattr(one.sim, name), getattr(batched.sim, name), err_msg=name)


def test_subgoal_distance_is_the_geodesic_after_every_action():
    """The rules skip the A* search when the agent did not move; the kept value must be
    what a fresh search gives (turns, STOP, moves blocked by walls)."""
    env = plex_nav_v0.env(max_steps=200, **SMALL)
    env.reset(seed=6)
    w = env.unwrapped.worlds
    rng = np.random.default_rng(1)
    blocked = 0
    while env.agents and not env.truncations["planner"]:
        if env.agent_selection == "planner":
            env.step(planner_action(0, rng.uniform(0.5, 4), rng.uniform(-3, 3)))
        else:
            a = int(rng.choice(4, p=[0.1, 0.5, 0.2, 0.2]))
            before = w.sim.pos[0].copy()
            env.step(executor_action(a))
            blocked += a == 1 and np.array_equal(before, w.sim.pos[0])
        if env.agent_selection == "executor" or w.turn_steps[0] > 0:
            fresh = w.sim.geodesic(0, w.sim.pos[0], w.subgoal[0])  # a fresh A* (or straight line)
            assert w.subgoal_dist[0] == pytest.approx(fresh, rel=0, abs=1e-4)
    assert w.steps[0] == 200


# ---------------------------------------------------------------- ELI and sub-goal
@pytest.mark.parametrize("eli", [True, False])
def test_eli_reaches_the_planner(eli):
    env = plex_nav_v0.env(eli=eli, n_ex=3, **SMALL)
    env.reset(seed=2)
    rng = np.random.default_rng(0)
    assert np.all(env.observe("planner")["eli"] == 0)
    for turn in range(6):
        assert env.agent_selection == "planner"
        env.step(planner_action(0, 2.0, rng.uniform(-3, 3)))
        sent = None
        while env.agent_selection == "executor":
            sent = rng.normal(size=128) * 10
            env.step(executor_action(int(rng.integers(0, 4)), sent))
        seen = env.observe("planner")["eli"]
        assert seen.dtype == np.float32 and seen.shape == (128,)
        if eli:
            np.testing.assert_array_equal(seen, sent.astype(np.float32))
        else:
            assert np.all(seen == 0)


def test_subgoal_vector_follows_the_executor():
    env = plex_nav_v0.env(**SMALL)
    env.reset(seed=0)
    raw = env.unwrapped
    env.reset(options={"episode": line_episode(raw, 2.0)})
    env.step(planner_action(0, 2.0, 0.0))  # straight ahead, on a free line
    w = raw.worlds
    np.testing.assert_allclose(w.subgoal_raw[0], ep_goal := np.array(raw.worlds.sim.goal[0]), atol=1e-6)
    v0 = env.observe("executor")["subgoal"]
    assert v0 == pytest.approx([2.0, 0.0], abs=1e-3)
    env.step(executor_action(1))
    v1 = env.observe("executor")["subgoal"]
    assert v1 == pytest.approx([1.75, 0.0], abs=1e-3)
    env.step(executor_action(2))  # turn left 10 deg: the sub-goal is now 10 deg to the right
    v2 = env.observe("executor")["subgoal"]
    assert v2 == pytest.approx([1.75, -math.radians(10)], abs=1e-3)
    env.step(executor_action(3))
    env.step(executor_action(1))
    v3 = env.observe("executor")["subgoal"]
    assert v3 == pytest.approx([1.5, 0.0], abs=1e-3)
    # The sub-goal is fixed in the world: the planner's goal vector agrees with it here.
    assert env.observe("executor")["subgoal"][0] == pytest.approx(np.hypot(*(ep_goal - w.sim.pos[0])), abs=1e-4)


# ---------------------------------------------------------------- success and SPL
def _episode_near_goal(raw, offset: float) -> Episode:
    ep = line_episode(raw, offset, clearance=0.2, episode_id=901)
    return ep


@pytest.mark.parametrize("offset,success", [(0.1, True), (0.3, False)])
def test_success_only_by_planner_stop_within_0_2_m(offset, success):
    env = plex_nav_v0.env(**SMALL)
    env.reset(seed=0)
    raw = env.unwrapped
    env.reset(options={"episode": _episode_near_goal(raw, offset)})
    assert env.infos["planner"]["distance_to_goal"] == pytest.approx(offset, abs=0.02)
    # The executor's STOP near the goal does not end the episode.
    env.step(planner_action(0, 0.5, 0.0))
    env.step(executor_action(0))
    assert env.agent_selection == "planner" and not any(env.terminations.values())
    env.step(planner_action(1))
    assert env.terminations == {"planner": True, "executor": True}
    info = env.infos["planner"]
    assert info["success"] == float(success)
    assert env.rewards["planner"] == pytest.approx(10.0 if success else 0.0)
    assert info["spl"] == (pytest.approx(1.0) if success else 0.0)


def test_spl_hand_computed():
    env = plex_nav_v0.env(**SMALL)
    env.reset(seed=0)
    raw = env.unwrapped
    ep = line_episode(raw, 1.0, behind=0.5)
    l = ep.geodesic_distance
    assert l == pytest.approx(1.0, abs=0.05)
    # Straight there: path 1.0 m.
    env.reset(options={"episode": ep})
    drive(env, [1] * 4)
    if env.agent_selection == "executor":
        env.step(executor_action(0))
    env.step(planner_action(1))
    assert env.infos["planner"]["success"] == 1.0
    assert env.infos["planner"]["spl"] == pytest.approx(l / max(l, 1.0), abs=1e-6)
    # A detour: turn around (18 x 10 deg), 0.5 m back, turn around, 1.5 m forward: path 2.0 m.
    env.reset(options={"episode": ep})
    drive(env, [2] * 18 + [1] * 2 + [2] * 18 + [1] * 6)
    assert raw.worlds.collisions[0] == 0
    if env.agent_selection == "executor":
        env.step(executor_action(0))
    env.step(planner_action(1))
    info = env.infos["executor"]
    assert info["success"] == 1.0 and info["steps"] == 45
    assert info["spl"] == pytest.approx(l / 2.0, abs=1e-5)
    # Stopping short fails: SPL 0.
    env.reset(options={"episode": ep})
    drive(env, [1] * 2)
    if env.agent_selection == "executor":
        env.step(executor_action(0))
    env.step(planner_action(1))
    assert env.infos["planner"]["success"] == 0.0 and env.infos["planner"]["spl"] == 0.0


# ---------------------------------------------------------------- infos, spaces, pickling
INFO_KEYS = ["scene_index", "episode_id", "geodesic_distance", "distance_to_goal", "collisions", "steps",
             "success", "spl"]


def test_infos_from_reset_on():
    env = plex_nav_v0.env(**SMALL)
    env.reset(seed=5)
    for a in env.agents:
        info = env.infos[a]
        assert list(info) == INFO_KEYS
        assert env.scene_ids[info["scene_index"]] == env.scene_id == env.unwrapped.episode.scene_id
        assert env.scene_id.startswith("procgen-train-")
        assert 1.0 <= info["geodesic_distance"] <= 30.0
        assert info["distance_to_goal"] == pytest.approx(info["geodesic_distance"], abs=1e-6)
        assert info["steps"] == 0 and info["collisions"] == 0
        assert info["success"] == 0.0 and info["spl"] == 0.0
    env.step(planner_action(0, 1.0, 0.0))
    env.step(executor_action(1))
    assert env.infos["planner"]["steps"] == 1 and env.infos["executor"]["steps"] == 1
    assert env.infos["planner"] == env.infos["executor"]


def _numbers_only(info: dict) -> bool:
    return all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in info.values())


@pytest.mark.parametrize("factory", [plex_nav_v0.env, plex_nav_v0.raw_env, plex_nav_v0.compat_env],
                         ids=["env", "raw_env", "compat_env"])
def test_info_keys_are_fixed_and_numeric_through_episodes(factory):
    # Trainers such as TorchRL build a fixed spec from the first infos and then write every
    # step's values into it: keys may not come or go, and strings cannot be tensors.
    env = factory(n_ex=3, max_steps=12, **SMALL)
    rng = np.random.default_rng(0)
    seen = {"reset": 0, "mid": 0, "end": 0}
    for seed in range(12):
        env.reset(seed=seed)
        for agent in env.agent_iter(200):
            for a in env.agents:
                assert list(env.infos[a]) == INFO_KEYS and _numbers_only(env.infos[a]), env.infos[a]
            obs, _, term, trunc, info = env.last()
            stage = "reset" if info["steps"] == 0 and agent == "planner" else "end" if term or trunc else "mid"
            seen[stage] += 1
            if stage == "end":
                assert info["success"] in (0.0, 1.0) and 0.0 <= info["spl"] <= info["success"]
            else:
                assert info["success"] == 0.0 and info["spl"] == 0.0
            if term or trunc:
                env.step(None)
            elif factory is plex_nav_v0.compat_env:
                env.step(0 if agent == "planner" and rng.random() < 0.1 else int(rng.integers(1, 4)))
            elif agent == "planner":
                env.step(planner_action(int(rng.random() < 0.1), rng.uniform(0.5, 3.0), rng.uniform(-3, 3)))
            else:
                env.step(executor_action(int(rng.integers(0, 4))))
    assert min(seen["reset"], seen["mid"], seen["end"]) >= 12, seen


def test_spaces_are_the_same_objects():
    env = plex_nav_v0.env(**SMALL)
    for a in env.possible_agents:
        assert env.observation_space(a) is env.observation_space(a)
        assert env.action_space(a) is env.action_space(a)
    env.reset(seed=0)
    for a in env.possible_agents:
        assert env.observation_space(a) is env.observation_space(a)
        assert env.observation_space(a).contains(env.observe(a))


@pytest.mark.parametrize("factory", [plex_nav_v0.env, plex_nav_v0.raw_env], ids=["env", "raw_env"])
def test_pickle_round_trip(factory):
    env = factory(n_ex=3, eli=False, **SMALL)
    env.reset(seed=4)
    copy = pickle.loads(pickle.dumps(env))
    assert copy.unwrapped.config == env.unwrapped.config
    copy.reset(seed=4)
    env.reset(seed=4)
    for _ in range(8):
        agent = env.agent_selection
        assert copy.agent_selection == agent
        for k, v in env.observe(agent).items():
            np.testing.assert_array_equal(copy.observe(agent)[k], v)
        act = planner_action(0, 2.0, 0.3) if agent == "planner" else executor_action(1)
        env.step(act)
        copy.step(act)
        assert copy.rewards == env.rewards


# ---------------------------------------------------------------- bad input
Z = np.zeros(128, np.float32)
BAD_PLANNER = {
    "missing key": ({"stop": 0}, "missing"),
    "unexpected key": ({"stop": 0, "subgoal": [1, 0], "extra": 1}, "unexpected"),
    "subgoal shape": ({"stop": 0, "subgoal": [1.0, 0.0, 0.0]}, "shape"),
    "stop shape": ({"stop": [0, 0], "subgoal": [1.0, 0.0]}, "scalar"),
    "ragged subgoal": ({"stop": 0, "subgoal": [1.0, [2.0, 3.0]]}, "ragged"),
    "subgoal dtype": ({"stop": 0, "subgoal": np.array(["a", "b"])}, "real numbers"),
    "complex subgoal": ({"stop": 0, "subgoal": np.array([1 + 1j, 0])}, "real numbers"),
    "stop dtype": ({"stop": "0", "subgoal": [1.0, 0.0]}, "integer"),
    "stop not whole": ({"stop": 0.5, "subgoal": [1.0, 0.0]}, "integer"),
    "stop None": ({"stop": None, "subgoal": [1.0, 0.0]}, "None"),
    "NaN subgoal": ({"stop": 0, "subgoal": [np.nan, 0.0]}, "NaN"),
    "inf subgoal": ({"stop": 0, "subgoal": [1.0, np.inf]}, "infinite"),
    "NaN stop": ({"stop": np.nan, "subgoal": [1.0, 0.0]}, "integer"),
    "distance too far": ({"stop": 0, "subgoal": [4.5, 0.0]}, r"\[0, 4.0\]"),
    "negative distance": ({"stop": 0, "subgoal": [-0.1, 0.0]}, r"\[0, 4.0\]"),
    "direction out of range": ({"stop": 0, "subgoal": [1.0, 3.5]}, "pi"),
    "stop out of range": ({"stop": 2, "subgoal": [1.0, 0.0]}, "0..1"),
    "executor's format": ({"action": 1, "eli": Z}, "other agent"),
    "plain int": (1, "expected a dict"),
    "None while alive": (None, "alive"),
}
BAD_EXECUTOR = {
    "missing key": ({"action": 1}, "missing"),
    "eli shape": ({"action": 1, "eli": np.zeros(127)}, "shape"),
    "action shape": ({"action": [1, 1], "eli": Z}, "scalar"),
    "action not whole": ({"action": 1.5, "eli": Z}, "integer"),
    "action dtype": ({"action": "1", "eli": Z}, "integer"),
    "eli dtype": ({"action": 1, "eli": np.array(["x"] * 128)}, "real numbers"),
    "NaN eli": ({"action": 1, "eli": np.full(128, np.nan)}, "NaN"),
    "inf eli": ({"action": 1, "eli": np.r_[np.zeros(127), -np.inf]}, "infinite"),
    "NaN action": ({"action": float("nan"), "eli": Z}, "integer"),
    "action out of range": ({"action": 4, "eli": Z}, "0..3"),
    "negative action": ({"action": -1, "eli": Z}, "0..3"),
    "planner's format": ({"stop": 0, "subgoal": [1.0, 0.0]}, "other agent"),
    "plain int": (1, "expected a dict"),
    "None while alive": (None, "alive"),
}
FACTORIES = {"env": plex_nav_v0.env, "raw_env": plex_nav_v0.raw_env}


@pytest.fixture(scope="module", params=list(FACTORIES))
def bad_input_env(request):
    return FACTORIES[request.param](**SMALL)


def _reject(env, action, match):
    before = state_snapshot(env)
    with pytest.raises(InvalidAction, match=match):
        env.step(action)
    assert_same_state(before, state_snapshot(env))


@pytest.mark.parametrize("case", list(BAD_PLANNER))
def test_bad_planner_action(bad_input_env, case):
    env = bad_input_env
    env.reset(seed=0)
    action, match = BAD_PLANNER[case]
    _reject(env, action, match)
    env.step(planner_action(0, 1.0, 0.0))  # the next valid action works
    assert env.agent_selection == "executor"
    assert env.unwrapped.worlds.planner_decisions[0] == 1


@pytest.mark.parametrize("case", list(BAD_EXECUTOR))
def test_bad_executor_action(bad_input_env, case):
    env = bad_input_env
    env.reset(seed=0)
    env.step(planner_action(0, 2.0, 0.0))
    action, match = BAD_EXECUTOR[case]
    _reject(env, action, match)
    env.step(executor_action(2))
    assert env.unwrapped.worlds.steps[0] == 1


def test_bad_actions_are_value_errors():
    assert issubclass(InvalidAction, ValueError)


def test_actions_after_the_end(bad_input_env):
    env = bad_input_env
    env.reset(seed=0)
    env.step(planner_action(1))
    _reject(env, planner_action(0, 1.0, 0.0), "only valid action is None")  # a dead agent's step
    env.step(None)
    env.step(None)
    with pytest.raises(InvalidAction, match="after the episode ended"):
        env.step(None)
    with pytest.raises(InvalidAction, match="after the episode ended"):
        env.step(planner_action(0, 1.0, 0.0))
    env.reset(seed=1)
    env.step(planner_action(0, 1.0, 0.0))
    assert env.agent_selection == "executor"
