"""The turn-based Parallel views (``plex_nav_v0.parallel_env``, ``compat_parallel_env``) and
the compat view's options: PettingZoo's ``parallel_api_test``, whole-episode determinism,
``infos[agent]["acting"]`` against the AEC turn order, the unused action of the other
agent, masks where each option puts them, the ELI through the compat view, bad input."""

from __future__ import annotations

import numpy as np
import pytest
from gymnasium import spaces
from pettingzoo.test import parallel_api_test

from plex_ma.envs import plex_nav_v0
from plex_ma.envs.actions import InvalidAction
from plex_ma.envs.parallel import TurnParallelEnv

pytestmark = pytest.mark.filterwarnings("ignore::UserWarning")

S = dict(resolution=32, num_scenes=2, max_steps=30)
OPTIONS = [dict(), dict(mask="info"), dict(mask="none"), dict(pad=True), dict(pad=True, mask="info"),
           dict(flatten=False), dict(eli=True, mask="none"), dict(eli=True, mask="none", flatten=False)]
OPTION_IDS = ["default", "mask-info", "mask-none", "pad", "pad-mask-info", "dict-obs", "eli", "eli-dict-obs"]


def views():
    """(id, factory) for the native Parallel view and every compat option."""
    out = [("native", lambda **k: plex_nav_v0.parallel_env(**S, **k))]
    for name, opts in zip(OPTION_IDS, OPTIONS):
        out.append((f"compat-{name}", lambda _o=opts, **k: plex_nav_v0.compat_parallel_env(**S, **_o, **k)))
    return out


VIEWS = views()


def mask_of(env, obs, infos, agent):
    """Where the view put the agent's mask, or None."""
    if isinstance(obs[agent], dict) and "action_mask" in obs[agent]:
        return obs[agent]["action_mask"]
    return infos[agent].get("action_mask")


def random_actions(env, obs, infos, rng) -> dict:
    """A valid action for every live agent, drawn from ``rng`` (masks respected)."""
    out = {}
    for a in env.agents:
        space = env.action_space(a)
        m = mask_of(env, obs, infos, a)
        if isinstance(space, spaces.Discrete):
            out[a] = int(rng.choice(np.flatnonzero(m))) if m is not None else int(rng.integers(space.n))
        elif a == "planner":  # the native Dict(stop, subgoal)
            out[a] = {"stop": int(rng.random() < 0.1), "subgoal": np.array([rng.uniform(0.2, 4.0),
                                                                            rng.uniform(-3, 3)], np.float32)}
        else:  # Dict(action, eli)
            out[a] = {"action": int(rng.integers(4)), "eli": rng.normal(size=128).astype(np.float32)}
    return out


def flat(x) -> list:
    """Nested dicts of arrays and numbers as a flat list of (key path, value) for comparing."""
    if isinstance(x, dict):
        return [(k,) + p for k in sorted(x) for p in flat(x[k])]
    if isinstance(x, (list, tuple)):
        return [(i,) + p for i, v in enumerate(x) for p in flat(v)]
    return [(np.asarray(x).tolist(),)]


def run_episodes(env, seed: int, episodes: int, other_seed: int | None = None, only_acting: bool = False):
    """Every output of ``episodes`` whole episodes: reset with ``seed`` once, then plain
    resets. The acting agent's actions come from one rng; the other agent's from
    ``other_seed``'s rng (or are left out with ``only_acting``)."""
    rng = np.random.default_rng(seed)
    other = np.random.default_rng(seed if other_seed is None else other_seed)
    record = []
    obs, infos = env.reset(seed=seed)
    record.append(flat([obs, infos]))
    done = 0
    while done < episodes:
        turn = env.aec_env.agent_selection
        mine = random_actions(env, obs, infos, rng)
        theirs = random_actions(env, obs, infos, other)
        actions = {turn: mine[turn]} if only_acting else {a: mine[a] if a == turn else theirs[a] for a in env.agents}
        out = env.step(actions)
        obs, infos = out[0], out[4]
        record.append(flat(list(out)))
        if not env.agents:
            done += 1
            obs, infos = env.reset()
            record.append(flat([obs, infos]))
    return record


# ---------------------------------------------------------------- PettingZoo's test and determinism
@pytest.mark.parametrize("name, factory", VIEWS, ids=[n for n, _ in VIEWS])
def test_parallel_api(name, factory):
    env = factory()
    assert isinstance(env, TurnParallelEnv) and env.possible_agents == ["planner", "executor"]
    if name == "compat-pad-mask-info":
        # the test reads masks from observations only, so it samples padded executor actions
        with pytest.raises(InvalidAction, match="masked out"):
            parallel_api_test(env, num_cycles=300)
        return
    parallel_api_test(env, num_cycles=300)


@pytest.mark.parametrize("name, factory", VIEWS, ids=[n for n, _ in VIEWS])
def test_seed_over_whole_episodes(name, factory):
    # PettingZoo's parallel_seed_test stops after the first step; this runs 4 episodes.
    a = run_episodes(factory(), seed=7, episodes=4)
    b = run_episodes(factory(), seed=7, episodes=4)
    assert len(a) > 4 * 3 and a == b
    assert run_episodes(factory(), seed=8, episodes=4) != a


# ---------------------------------------------------------------- who acted
@pytest.mark.parametrize("compat", [False, True], ids=["native", "compat"])
def test_acting_follows_the_aec_turn_order(compat):
    """Step the AEC env and the Parallel view side by side with the same actions: at every
    step ``acting`` is True exactly for the AEC env's ``agent_selection`` before the step,
    and observations, rewards and flags are the AEC env's."""
    make = plex_nav_v0.compat_env if compat else plex_nav_v0.env
    kw = dict(S, n_ex=3)
    aec, par = make(**kw), TurnParallelEnv(make(**kw))
    aec.reset(seed=3)
    obs, infos = par.reset(seed=3)
    assert all(info["acting"] is False for info in infos.values())
    rng = np.random.default_rng(0)
    turns, episodes = [], 0
    while episodes < 3:
        turn = aec.agent_selection
        actions = random_actions(par, obs, infos, rng)
        aec.step(actions[turn])
        obs, rew, term, trunc, infos = par.step(actions)
        turns.append(turn)
        assert {a for a, i in infos.items() if i["acting"]} == {turn}
        for a in obs:
            assert flat(obs[a]) == flat(aec.observe(a))
            assert rew[a] == aec.rewards[a] and term[a] == aec.terminations[a] and trunc[a] == aec.truncations[a]
        if not par.agents:
            while aec.agents:
                aec.step(None)
            episodes += 1
            aec.reset()
            obs, infos = par.reset()
    # the turn order: a planner decision, then up to n_ex executor actions
    runs = "".join("p" if t == "planner" else "e" for t in turns).split("p")
    assert turns[0] == "planner" and max(len(r) for r in runs) <= 3 and any(len(r) > 0 for r in runs)


@pytest.mark.parametrize("name, factory", [VIEWS[0], VIEWS[1], VIEWS[7]], ids=["native", "compat", "compat-eli"])
def test_the_other_agents_action_changes_nothing(name, factory):
    """Dropping the non-acting agent's transitions loses nothing: whatever that agent
    sends, or if it sends nothing, every episode is the same."""
    base = run_episodes(factory(), seed=5, episodes=3, other_seed=100)
    assert run_episodes(factory(), seed=5, episodes=3, other_seed=200) == base
    assert run_episodes(factory(), seed=5, episodes=3, only_acting=True) == base


# ---------------------------------------------------------------- the compat options
def test_mask_in_infos_and_observation_without_it():
    env = plex_nav_v0.compat_parallel_env(mask="info", **S)
    obs, infos = env.reset(seed=0)
    assert isinstance(env.observation_space("planner"), spaces.Box)
    assert env.observation_space("planner").contains(obs["planner"])
    np.testing.assert_array_equal(infos["planner"]["action_mask"], np.ones(33, np.int8))
    np.testing.assert_array_equal(infos["executor"]["action_mask"], np.ones(4, np.int8))
    obs, _, _, _, infos = env.step({"planner": 5, "executor": 0})
    assert infos["planner"]["acting"] and "action_mask" in infos["executor"]
    # the AEC view carries it too, and its last() shows it
    aec = plex_nav_v0.compat_env(mask="info", pad=True, **S)
    aec.reset(seed=0)
    np.testing.assert_array_equal(aec.last()[4]["action_mask"], np.ones(33, np.int8))
    aec.step(5)
    np.testing.assert_array_equal(aec.last()[4]["action_mask"], np.r_[np.ones(4), np.zeros(29)].astype(np.int8))
    with pytest.raises(InvalidAction, match=r"masked out.*infos\[agent\]\['action_mask'\]"):
        aec.step(7)


def test_unpadded_spaces_are_each_agents_own():
    env = plex_nav_v0.compat_env(mask="none", **S)
    assert env.action_space("planner") == spaces.Discrete(33) and env.action_space("executor") == spaces.Discrete(4)
    assert env.observation_space("planner").shape == (2 + 6 * 32 * 32 + 2,)
    assert env.observation_space("executor").shape == (2 + 4 * 32 * 32 + 2,)
    env.reset(seed=0)
    env.step(9)
    with pytest.raises(InvalidAction, match="out of range"):
        env.step(4)


def test_dict_observations_are_the_native_ones():
    env = plex_nav_v0.compat_env(flatten=False, mask="info", **S)
    env.reset(seed=1)
    env.step(3)
    native = env.native.observe("executor")
    o = env.observe("executor")
    assert set(o) == {"rgb", "depth", "subgoal"} and o["rgb"].dtype == np.uint8 and o["rgb"].shape == (32, 32, 3)
    assert flat(o) == flat(native) and env.observation_space("executor") == env.native.observation_space("executor")


def test_eli_reaches_the_planner_through_the_compat_view():
    env = plex_nav_v0.compat_parallel_env(eli=True, mask="none", n_ex=2, **S)
    assert env.action_space("executor") == env.unwrapped.native.action_space("executor")
    assert env.observation_space("planner").shape == (2 + 6 * 32 * 32 + 2 + 128,)
    obs, _ = env.reset(seed=0)
    np.testing.assert_array_equal(obs["planner"][-128:], np.zeros(128))
    msg = np.linspace(-1, 1, 128).astype(np.float32)
    env.step({"planner": 9})
    env.step({"executor": {"action": 2, "eli": -msg}})
    obs, *_ = env.step({"executor": {"action": 2, "eli": msg}})  # its n_ex-th action: the planner's turn
    assert env.aec_env.agent_selection == "planner"
    np.testing.assert_allclose(obs["planner"][-128:], msg)
    env.step({"planner": 9})
    with pytest.raises(InvalidAction, match="expected a dict"):
        env.step({"executor": 1})  # with the ELI the executor's action is Dict(action, eli)


@pytest.mark.parametrize("kwargs, match", [
    (dict(mask="bogus"), "mask='bogus' must be one of 'obs', 'info', 'none'"),
    (dict(pad="yes"), "pad='yes' must be True or False"),
    (dict(flatten=None), "flatten=None must be True or False"),
    (dict(pad=True, flatten=False), "pad=True .* needs flatten=True"),
    (dict(pad=True, mask="none"), "pad=True .* and a mask"),
    (dict(pad=True, eli=True, mask="none"), "pad=True .* eli=False"),
    (dict(eli=True), "eli=True needs mask='none'"),
])
def test_bad_options(kwargs, match):
    with pytest.raises(ValueError, match=match):
        plex_nav_v0.compat_env(**S, **kwargs)


def test_bad_parallel_steps():
    env = plex_nav_v0.parallel_env(**S)
    with pytest.raises(InvalidAction, match="after the episode ended"):
        env.step({})
    env.reset(seed=0)
    with pytest.raises(InvalidAction, match="no action for the planner, whose turn it is"):
        env.step({"executor": {"action": 1, "eli": np.zeros(128, np.float32)}})
    with pytest.raises(InvalidAction, match="not live agents"):
        env.step({"planner": {"stop": 1, "subgoal": np.zeros(2, np.float32)}, "pilot": 0})
    with pytest.raises(InvalidAction, match="must be a dict"):
        env.step([1])
    *_, infos = env.step({"planner": {"stop": 1, "subgoal": np.zeros(2, np.float32)}})
    assert infos["planner"]["acting"] and not infos["executor"]["acting"] and env.agents == []
    with pytest.raises(InvalidAction, match="after the episode ended"):
        env.step({"planner": {"stop": 1, "subgoal": np.zeros(2, np.float32)}})


def test_compat_docstring_lists_every_option_with_its_default():
    import inspect
    import re

    from plex_ma.envs import compat

    rows = re.findall(r"^\| (`\w+`(?:, `\w+`)*) \| ([^|]+) \|", compat.__doc__, re.M)
    documented = {}
    for names, default in rows:
        for n in re.findall(r"`(\w+)`", names):
            documented[n] = default.strip()
    params = inspect.signature(compat.compat_env).parameters
    options = {n for n, p in params.items() if p.kind is p.POSITIONAL_OR_KEYWORD} | {"eli"}
    assert options <= set(documented), options - set(documented)
    for n in ("mask", "pad", "flatten", "image_size"):
        assert documented[n].strip("`\"") == str(params[n].default).strip("'"), n
