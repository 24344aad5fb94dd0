"""The one action validator (plex_ma.envs.actions): its rules, and the same words from every
env view for the same bad navigation action."""

from __future__ import annotations

import gymnasium
import numpy as np
import pytest

import plex_ma  # noqa: F401  (registers the gymnasium env)
from plex_ma.envs import plex_nav_v0
from plex_ma.envs.actions import InvalidAction, discrete, real
from plex_ma.envs.vector import PlexVectorEnv, PointNavVectorEnv

from .env_helpers import SMALL

NAMES = "0..3 (STOP, MOVE_FORWARD, TURN_LEFT, TURN_RIGHT)"


@pytest.mark.parametrize("x, shape, out", [
    (np.array([0, 3, 2]), (3,), [0, 3, 2]),
    ([1.0, 2.0], (2,), [1, 2]),  # whole-valued floats pass
    (np.int8(2), (), 2),
    (3, (), 3),
])
def test_discrete_accepts_whole_numbers_in_range(x, shape, out):
    a = discrete(x, 4, "a", shape)
    assert a.dtype == np.int64 and a.shape == shape and a.tolist() == out


@pytest.mark.parametrize("x, shape, kw, problem", [
    (np.array([0, 4]), (2,), {}, r"out of range: entry\(s\) \[1\] got \[4\]"),
    (np.array([0, -1]), (2,), {"per": "world"}, r"world\(s\) \[1\] got \[-1\]"),
    (np.array([1, 1]), (3,), {}, r"shape \(2,\)"),
    ([0.5, 1.0], (2,), {}, "non-integer values"),
    ([np.nan, 1.0], (2,), {}, "non-integer values"),
    (np.array([True, False]), (2,), {}, "dtype bool"),
    (True, (), {}, "the bool True"),
    ("1", (), {}, "a str"),
    ({"action": 1}, (), {}, "a dict"),
    (1.0, (), {"integers_only": True}, "got the float 1.0"),
    (2.5, (), {}, "the non-integer value 2.5"),
    (5, (), {}, "5 is out of range"),
])
def test_discrete_names_the_problem(x, shape, kw, problem):
    with pytest.raises(InvalidAction, match=problem) as e:
        discrete(x, 4, "executor: action", shape, **kw)
    assert str(e.value).startswith("executor: action must be ")


def test_real_wants_finite_numbers_of_the_shape():
    np.testing.assert_array_equal(real([[1, 2]], "s", (1, 2)), [[1.0, 2.0]])
    for x, problem in [([[1, 2, 3]], "shape"), ([[np.inf, 0]], "infinite"), ([["a", "b"]], "real numbers"),
                       ([[1j, 0]], "real numbers")]:
        with pytest.raises(InvalidAction, match=problem):
            real(x, "s", (1, 2))


def test_every_view_rejects_an_out_of_range_navigation_action_in_the_same_words():
    """Action 4 for the executor or the flat agent: the same expectation in every view, and the
    view still works afterwards."""
    messages = {}
    aec = plex_nav_v0.env(**SMALL)
    aec.reset(seed=0)
    aec.step({"stop": 0, "subgoal": np.array([1.0, 0.0], np.float32)})
    with pytest.raises(InvalidAction) as e:
        aec.step({"action": 4, "eli": np.zeros(128, np.float32)})
    messages["plex_nav_v0"] = str(e.value)

    venv = PlexVectorEnv(2, seed=0, **SMALL)
    venv.reset()
    venv.step(stop=np.zeros(2, np.int64), subgoal=np.tile([1.0, 0.0], (2, 1)))
    with pytest.raises(InvalidAction) as e:
        venv.step(action=np.array([1, 4]), eli=np.zeros((2, 128), np.float32))
    messages["PlexVectorEnv"] = str(e.value)

    flat = PointNavVectorEnv(2, seed=0, **SMALL)
    flat.reset()
    with pytest.raises(InvalidAction) as e:
        flat.step(np.array([1, 4]))
    messages["PointNavVectorEnv"] = str(e.value)

    gym = gymnasium.make("plex_ma/PointNav-v0", **SMALL)
    gym.reset(seed=0)
    with pytest.raises(InvalidAction) as e:
        gym.step(4)
    messages["PointNav-v0"] = str(e.value)

    vec = gymnasium.make_vec("plex_ma/PointNav-v0", num_envs=2, vectorization_mode="vector_entry_point", **SMALL)
    vec.reset(seed=0)
    with pytest.raises(InvalidAction) as e:
        vec.step(np.array([1, 4]))
    messages["make_vec"] = str(e.value)

    for view, m in messages.items():
        assert NAMES in m, (view, m)
    gym.step(1)
    vec.step(np.array([1, 1]))
    flat.step(np.array([1, 1]))
