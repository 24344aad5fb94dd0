"""``plex_nav_v0.compat_env()``: a Box/Discrete view of ``plex_nav_v0`` for generic trainers.

```python
from plex_ma.envs import plex_nav_v0
env = plex_nav_v0.compat_env(resolution=64)              # each agent its own spaces, mask in the observation
env = plex_nav_v0.compat_env(pad=True, mask="info")      # one padded layout for both, mask in infos
```

Generic PettingZoo trainers want ``Box`` or ``Discrete`` spaces, not the native env's
mixed ``Dict`` actions (a stop flag with a continuous sub-goal). This view gives the
planner a ``Discrete`` choice of sub-goals and offers the rest in the layout a trainer
asks for, through its options; ``compat_parallel_env()`` (same arguments) is its
turn-based Parallel view (``plex_nav_v0``'s "Parallel API").

| | |
|---|---|
| Agents | `["planner", "executor"]`, same turn order, rewards and infos as `plex_nav_v0` |
| Planner action | `Discrete(K)`, `K = 1 + len(subgoal_distances) * subgoal_directions` (33 by default) |
| Executor action | `Discrete(4)`; with `eli=True` `Dict(action=Discrete(4), eli=Box(128))`; with `pad=True` `Discrete(K)` |
| Observation | `flatten=True`: one float32 vector each (planner 6,148, executor 4,100 by default); `flatten=False`: the native Dicts; `pad=True`: both zero-padded to one length |
| Mask | `mask="obs"`: `Dict(observation=..., action_mask=Box(0, 1, (n,), int8))`; `"info"`: `infos[agent]["action_mask"]`; `"none"`: no mask |

| option | default | meaning |
|---|---|---|
| `mask` | `"obs"` | where each agent's action mask goes: `"obs"` (PettingZoo's convention), `"info"`, `"none"` |
| `pad` | False | True: one observation Box and one `Discrete(K)` for both agents, the executor's 4..K-1 masked (for trainers that need identical spaces, e.g. Tianshou); needs `flatten=True`, `eli=False` and a mask |
| `flatten` | True | False: the native Dict observations, images whole for a CNN (`image_size` unused) |
| `eli` | False | True: the executor's action carries the 128-float ELI and the planner's observation holds the last one; needs `mask="none"` (gymnasium samples a Dict action with a dict of masks, and nothing is masked without `pad`) |
| `image_size` | 32 | side of the executor's downsampled RGB-D in the flat vector |
| `subgoal_distances`, `subgoal_directions` | `rho_max * (1, 2, 3, 4) / 4`, 8 | the planner's sub-goal grid |

Every other argument is ``plex_nav_v0.env``'s. A bad option raises one ``ValueError``
naming it.

**observation** (``flatten=True``, float32): a one-hot agent id (`[1, 0]` planner, `[0, 1]`
executor), then the agent's own features (then zero padding with ``pad=True``):

* planner: the ego map flattened in (channel, row, column) order (6 x 32 x 32 in [0, 1]),
  then the goal vector (distance m, direction rad), then with ``eli=True`` the ELI its
  executor sent last (128 values).
* executor: RGB scaled to [0, 1] and depth, downsampled to `image_size` x `image_size`
  (block mean when the resolution is a multiple of it, nearest pixel otherwise) and
  flattened channel-first (R, G, B, depth planes), then the sub-goal vector (distance m,
  direction rad). Reshape `obs[2:2 + 4 * S * S]` to `(4, S, S)` to get the image back.

**action_mask** (int8, one entry per Discrete action of the agent): 1 for the actions the
agent may use. It is the same for every step of an agent: all ones, except with
``pad=True``, where the executor may use only the first 4 of K.

**actions**:

* planner: `0` stops the episode; `1 + i * subgoal_directions + j` proposes the sub-goal at
  distance `subgoal_distances[i]` (default `rho_max * (1, 2, 3, 4) / 4` = 1, 2, 3, 4 m) in
  direction `2 pi j / subgoal_directions`, wrapped to [-pi, pi) (default 8 directions, 0 =
  straight ahead, counter-clockwise).
* executor: `0` STOP, `1` MOVE_FORWARD, `2` TURN_LEFT, `3` TURN_RIGHT, sending a zero ELI
  (the channel is off, ``eli=False``); with ``eli=True`` the native
  ``{"action": move, "eli": 128 floats}``, which the native env checks.

An action outside the agent's range, one that the mask forbids (an executor action above
3 with ``pad=True``), a non-integer, or a step after the episode ended raises
:class:`~plex_ma.envs.actions.InvalidAction` naming the problem; nothing is changed.

`compat_env()` pickles (it rebuilds from its arguments, like ``EzPickle``).

## How it is built

1. ``plex_nav_v0.env(eli=False, ...)``: the native env with order enforcing.
2. :class:`CompatEnv` (ours) over it, the env the user gets. It maps each agent's Dict
   observation to its flat vector with the one-hot id in front (``flatten=True``;
   ``agent_indicator_v0`` is not used: it appends the id at the end, scaled to the
   space's largest bound, the 100 m goal distance), zero-padded to the longer one's length
   with ``pad=True`` (the executor's, by default); and each Discrete choice to the native
   Dict action (planner ``Discrete(K)``, executor ``Discrete(4)``, or its native Dict with
   ``eli=True``). These are the layouts SuperSuit's ``observation_lambda_v0``,
   ``pad_observations_v0``, ``action_lambda_v1`` and ``pad_action_space_v0`` would give
   (the padded spaces are the ones they build), done in one place instead of through
   four wrappers that each read the episode's state through every level below them.
   It puts the mask where ``mask`` says and checks every Discrete action against it before
   it reaches the native env (SuperSuit has no action-mask wrapper, and its
   ``pad_action_space_v0`` would silently map an executor action above 3 to 0, STOP). It
   is an AEC env of its own, not a wrapper: ``env.unwrapped`` is the compat env itself,
   so every way of asking for the spaces (``observation_space(agent)``,
   ``action_space(agent)``, the ``observation_spaces`` / ``action_spaces`` dicts, the
   same on ``unwrapped``) gives the compat spaces, which trainers that read
   ``unwrapped.observation_spaces`` (skrl, RLlib) need. The native env is
   ``env.native``.

## SuperSuit on the native ``plex_nav_v0``

The native spaces are ``Dict`` spaces, so most SuperSuit wrappers, which expect ``Box`` or
``Discrete`` spaces, do not apply to it: ``color_reduction_v0``, ``resize_v1``,
``frame_stack_v1``, ``normalize_obs_v0``, ``dtype_v0``, ``flatten_v0``, ``reshape_v0``,
``pad_observations_v0``, ``pad_action_space_v0`` and ``agent_indicator_v0`` fail when
they are built; ``clip_actions_v0``, ``max_observation_v0`` and ``delay_observations_v0``
fail on the first step; ``black_death_v3`` needs a parallelizable env. Three wrappers work
(pass PettingZoo's ``api_test``): ``clip_reward_v0``; ``sticky_actions_v0``, which
repeats an agent's previous action with a probability (each agent its own, planner
included); and ``frame_skip_v0``, which repeats the acting agent's action up to N times,
but which was written for round-robin games: when the executor's turn ends during a
skip it also replays the planner's previous action.

On ``compat_env()`` the same three work, and the observation wrappers still do not:
with ``mask="obs"`` PettingZoo's action-mask convention makes each observation a ``Dict`` of
``observation`` and ``action_mask``, which ``frame_stack_v1``, ``normalize_obs_v0``,
``dtype_v0``, ``agent_indicator_v0`` and the like refuse; ``delay_observations_v0``
accepts it but delays the mask too, so an agent is shown the other agent's mask (and
its actions are then rejected). Stack or normalise the ``observation`` vector in the
trainer. ``tests/test_compat.py`` checks every claim of this section.
"""

from __future__ import annotations

import functools

import numba
import numpy as np
from gymnasium import spaces
from pettingzoo import AECEnv
from supersuit.utils.action_transforms.homogenize_ops import homogenize_spaces

from .plex_nav import EPISODE_STATE, env as native_env
from .actions import InvalidAction, discrete
from .parallel import TurnParallelEnv
from .rules import ELI_DIM
from .sim.core import ACTION_NAMES, wrap_angle
from .spaces import MAX_GOAL_DISTANCE

AGENT_IDS = {"planner": 0, "executor": 1}


MASK_PLACES = ("obs", "info", "none")


def compat_env(image_size: int = 32, subgoal_distances=None, subgoal_directions: int = 8, mask: str = "obs",
               pad: bool = False, flatten: bool = True, **config):
    """``plex_nav_v0`` with Discrete planner actions, flat Box observations and an action
    mask, in the layout a trainer asks for (see the module docstring).

    Args:
        image_size: side of the executor's downsampled RGB-D (at most ``resolution``;
            used when ``flatten``).
        subgoal_distances: the planner's sub-goal distances in metres, each in
            (0, rho_max] (default: ``rho_max * (1, 2, 3, 4) / 4``).
        subgoal_directions: number of evenly spaced sub-goal directions (default 8).
        mask: where the action mask goes: ``"obs"`` (``Dict(observation, action_mask)``,
            PettingZoo's convention), ``"info"`` (``infos[agent]["action_mask"]``) or
            ``"none"``.
        pad: one observation Box and one ``Discrete(K)`` for both agents (the executor's
            actions 4..K-1 masked); False keeps each agent's own spaces.
        flatten: each observation as one float32 vector; False keeps the native Dict
            observations (images whole, for a CNN).
        **config: arguments of ``plex_nav_v0.env``. ``eli`` defaults to False here; with
            ``eli=True`` the executor's action is ``Dict(action=Discrete(4), eli=Box(128))``.
    """
    build_args = dict(image_size=image_size, subgoal_distances=subgoal_distances,
                      subgoal_directions=subgoal_directions, mask=mask, pad=pad, flatten=flatten, **config)
    if mask not in MASK_PLACES:
        raise ValueError(f"compat_env: mask={mask!r} must be one of {', '.join(map(repr, MASK_PLACES))}")
    for name, value in (("pad", pad), ("flatten", flatten), ("eli", config.get("eli", False))):
        if not isinstance(value, (bool, np.bool_)):
            raise ValueError(f"compat_env: {name}={value!r} must be True or False")
    config["eli"] = eli = bool(config.get("eli", False))
    if pad and (eli or not flatten or mask == "none"):
        raise ValueError("compat_env: pad=True gives both agents one flat observation and one Discrete(K) with "
                         "the executor's extra actions masked, so it needs flatten=True, eli=False and a mask; got "
                         f"flatten={flatten!r}, eli={eli!r}, mask={mask!r}")
    if eli and mask != "none":
        raise ValueError(f"compat_env: eli=True needs mask='none', got mask={mask!r}: the executor's action is then "
                         "Dict(action, eli), which an array mask cannot describe (gymnasium samples a Dict with a "
                         "dict of masks), and without pad no action is masked")
    base = native_env(**config)
    cfg = base.unwrapped.config
    if not isinstance(image_size, (int, np.integer)) or not 1 <= image_size <= cfg.resolution:
        raise ValueError(f"compat_env: image_size={image_size!r} must be an integer in [1, resolution="
                         f"{cfg.resolution}]")
    if not isinstance(subgoal_directions, (int, np.integer)) or subgoal_directions < 1:
        raise ValueError(f"compat_env: subgoal_directions={subgoal_directions!r} must be a positive integer")
    if subgoal_distances is None:
        subgoal_distances = tuple(cfg.rho_max * k / 4 for k in (1, 2, 3, 4))
    try:
        dists = tuple(float(d) for d in subgoal_distances)
    except (TypeError, ValueError):
        raise ValueError(f"compat_env: subgoal_distances={subgoal_distances!r} must be numbers") from None
    if not dists or not all(0 < d <= cfg.rho_max for d in dists):
        raise ValueError(f"compat_env: subgoal_distances={subgoal_distances!r} must be non-empty and each in "
                         f"(0, rho_max={cfg.rho_max}]")
    grid = subgoal_grid(dists, int(subgoal_directions))
    return CompatEnv(base, build_args, mask, grid, int(image_size) if flatten else None, pad, eli)


def compat_parallel_env(**kwargs):
    """:func:`compat_env` (same arguments) as the turn-based Parallel env, with
    ``infos[agent]["acting"]`` (see :mod:`plex_ma.envs.parallel`)."""
    return TurnParallelEnv(compat_env(**kwargs))


def subgoal_grid(distances, directions: int) -> np.ndarray:
    """(len(distances) * directions, 2) polar sub-goals; row ``i * directions + j`` is
    (distances[i], 2 pi j / directions wrapped to [-pi, pi))."""
    th = wrap_angle(2 * np.pi * np.arange(directions) / directions)
    return np.array([(d, t) for d in distances for t in th], np.float32)


# ---------------------------------------------------------------- observations
def _downsample(img: np.ndarray, size: int) -> np.ndarray:
    """(R, R, C) -> (size, size, C) float32: block mean if R is a multiple, else nearest."""
    r = img.shape[0]
    if r % size == 0:
        k = r // size
        return img.reshape(size, k, size, k, img.shape[2]).mean(axis=(1, 3), dtype=np.float32)
    idx = ((np.arange(size) + 0.5) * r / size).astype(np.int64)
    return img[idx][:, idx].astype(np.float32)


def _flat_image(rgb: np.ndarray, depth: np.ndarray, out: np.ndarray) -> None:
    """``out`` (4, S, S) float32: RGB scaled to [0, 1] and depth, downsampled to S x S
    (:func:`_downsample`), channel first."""
    r, size = rgb.shape[0], out.shape[1]
    if r % size == 0 and r // size < 8:
        _block_means(rgb, depth, r // size, out)
        return
    out[:3] = (_downsample(rgb, size) / np.float32(255.0)).transpose(2, 0, 1)
    out[3] = _downsample(depth, size)[:, :, 0]


@numba.njit(cache=True)
def _block_means(rgb, depth, k, out):
    """:func:`_flat_image` for k = R / S < 8, bit for bit (``tests/test_compat.py``): numpy's
    float32 mean adds runs that short in order (its pairwise summation starts at 8), each
    block row's sum in float32, then the rows' sums, and divides by the count in float64;
    the RGB means are then divided by 255 in float32. RGB values are whole numbers, whose
    float32 sums are exact in any order, so they are summed as integers in the order that
    reads memory straight through; depth is summed in numpy's order. Compiled loops: numpy's
    buffered strided reduction takes several times as long."""
    s = rgb.shape[0] // k
    n = np.float64(k * k)
    rows = rgb.reshape(rgb.shape[0], -1)  # (R, 3R): an image row's values in memory order
    col = np.empty(rows.shape[1], np.int32)  # a block row's k image rows, summed
    blocks = np.zeros((3, s, s), np.int32)
    for a in range(s):
        col[:] = 0
        for i in range(k):
            for e in range(rows.shape[1]):
                col[e] += rows[a * k + i, e]
        pixels = col.reshape(s, k, 3)
        for b in range(s):
            for j in range(k):
                for ch in range(3):
                    blocks[ch, a, b] += pixels[b, j, ch]
    for ch in range(3):
        for a in range(s):
            for b in range(s):
                out[ch, a, b] = np.float32(blocks[ch, a, b] / n) / np.float32(255.0)
    d = depth.reshape(depth.shape[0], -1)
    total = np.empty(s, np.float32)
    for a in range(s):
        total[:] = 0
        for i in range(k):
            for b in range(s):
                row = np.float32(0.0)
                for j in range(k):
                    row += d[a * k + i, b * k + j]
                total[b] += row
        for b in range(s):
            out[3, a, b] = np.float32(total[b] / n)


def _flat_obs(obs: dict, agent: str, image_size: int, eli: bool, length: int) -> np.ndarray:
    """An agent's native observation as its flat vector (the module docstring's layout) of
    ``length`` values, zero beyond the agent's own (``pad=True``)."""
    out = np.empty(length, np.float32)
    if agent == "planner":
        ego = obs["ego_map"].ravel()
        n = 2 + len(ego)
        out[:2] = (1.0, 0.0)
        out[2:n] = ego
        out[n:n + 2] = obs["goal"]
        n += 2
        if eli:
            out[n:n + ELI_DIM] = obs["eli"]
            n += ELI_DIM
    else:
        n = 2 + 4 * image_size * image_size
        out[:2] = (0.0, 1.0)
        _flat_image(obs["rgb"], obs["depth"], out[2:n].reshape(4, image_size, image_size))
        out[n:n + 2] = obs["subgoal"]
        n += 2
    out[n:] = 0.0
    return out


def _flat_space(obs_space, agent: str, image_size: int, eli: bool) -> spaces.Box:
    polar_lo, polar_hi = [0.0, -np.pi], [MAX_GOAL_DISTANCE, np.pi]
    if agent == "planner":
        n = int(np.prod(obs_space["ego_map"].shape))
    else:
        n = 4 * image_size * image_size
    m = ELI_DIM if agent == "planner" and eli else 0
    low = np.concatenate([[0.0, 0.0], np.zeros(n), polar_lo, np.full(m, -np.inf)]).astype(np.float32)
    high = np.concatenate([[1.0, 1.0], np.ones(n), polar_hi, np.full(m, np.inf)]).astype(np.float32)
    return spaces.Box(low, high, dtype=np.float32)


# ---------------------------------------------------------------- actions
_ZERO_ELI = np.zeros(ELI_DIM, np.float32)  # the executor's ELI with the channel off, shared
_ZERO_ELI.flags.writeable = False


def _native_action(action, agent: str, grid: np.ndarray, eli: bool):
    """A checked compat action as the native env's Dict action."""
    if agent == "executor" and eli:
        return action  # already the native Dict(action, eli); the native env checks it
    a = int(action)
    if agent == "planner":
        if a == 0:
            return {"stop": 1, "subgoal": np.zeros(2, np.float32)}
        return {"stop": 0, "subgoal": grid[a - 1].copy()}
    return {"action": a, "eli": _ZERO_ELI}


def _action_space(act_space, agent: str, k: int, eli: bool) -> spaces.Space:
    if agent == "planner":
        return spaces.Discrete(k)
    return act_space if eli else spaces.Discrete(len(ACTION_NAMES))


class CompatEnv(AECEnv):
    """The compat view: an AEC env in its own right over the native env (``plex_nav_v0.env()``,
    the steps of the module docstring). It maps each observation to its flat layout and
    each Discrete action to the native one, puts each agent's action mask where ``mask``
    says, and rejects masked or malformed actions with :class:`InvalidAction` before they
    reach the native env.

    Every way of asking for its spaces gives the compat spaces: ``observation_space(agent)``
    and ``action_space(agent)``, the ``observation_spaces`` and ``action_spaces`` dicts,
    and the same on ``unwrapped``, which is this env itself (trainers such as skrl and
    RLlib read the spaces there). The native env under it is :attr:`native`; its
    attributes (``config``, ``worlds``, ``scene_id`` ...) are also read through this one."""

    def __init__(self, base: AECEnv, build_args: dict, mask: str, grid: np.ndarray, image_size: int | None,
                 pad: bool, eli: bool):
        super().__init__()
        self.env = base
        self._native = base.unwrapped
        self._build_args = dict(build_args)
        self.mask = mask
        self._grid = grid
        self._image_size = image_size  # None: the native Dict observations (flatten=False)
        self._eli = eli
        agents = base.possible_agents
        self.possible_agents = list(agents)
        self.metadata = base.metadata
        self.render_mode = base.render_mode
        obs_spaces = {a: base.observation_space(a) for a in agents}
        if image_size is not None:
            obs_spaces = {a: _flat_space(space, a, image_size, eli) for a, space in obs_spaces.items()}
        self._act_spaces = {a: _action_space(base.action_space(a), a, 1 + len(grid), eli) for a in agents}
        if pad:  # one space for both agents, the one SuperSuit's pad_observations_v0 / pad_action_space_v0 build
            obs_spaces = dict.fromkeys(agents, homogenize_spaces(list(obs_spaces.values())))
            self._act_spaces = dict.fromkeys(agents, homogenize_spaces(list(self._act_spaces.values())))
        self._lengths = {a: space.shape[0] for a, space in obs_spaces.items()} if image_size is not None else None
        self.num_actions = int(self._act_spaces["planner"].n)
        self._masks = {}
        for a in agents:
            space = self._act_spaces[a]
            m = np.zeros(space.n if isinstance(space, spaces.Discrete) else 0, np.int8)
            m[:self.num_actions if a == "planner" else len(ACTION_NAMES)] = 1
            self._masks[a] = m
        self._obs_spaces = obs_spaces
        if mask == "obs":
            self._obs_spaces = {a: spaces.Dict({"observation": obs_spaces[a],
                                                "action_mask": spaces.Box(0, 1, self._masks[a].shape, np.int8)})
                                for a in agents}

    def __getattr__(self, name: str):
        # The episode's state (agents, agent_selection, rewards, ...) is the native env's,
        # read there at once instead of through its order-enforcing wrapper.
        if name in EPISODE_STATE:
            return self._state(name)
        # the native env's other attributes, read through
        if name == "env" or (name.startswith("_") and name != "_cumulative_rewards"):
            raise AttributeError(name)
        return getattr(self.env, name)

    def _state(self, name: str):
        """The native env's ``name``; before ``reset`` the AttributeError of PettingZoo's
        order enforcing."""
        if not self.env._has_reset and name != "_cumulative_rewards":
            raise AttributeError(f"{name} cannot be accessed before reset")
        return getattr(self._native, name)

    def __reduce__(self):
        return (functools.partial(compat_env, **self._build_args), ())

    def __str__(self) -> str:
        return f"compat<{self.env.unwrapped}>"

    @property
    def native(self) -> AECEnv:
        """The native ``plex_nav_v0`` env (``raw_env``) under the compat view."""
        return self.env.unwrapped

    def observation_space(self, agent):
        return self._obs_spaces[agent]

    def action_space(self, agent):
        return self._act_spaces[agent]

    @property
    def observation_spaces(self) -> dict:
        return dict(self._obs_spaces)

    @property
    def action_spaces(self) -> dict:
        return dict(self._act_spaces)

    @property
    def infos(self) -> dict:
        """The native infos; with ``mask="info"`` each also holds the agent's ``action_mask``."""
        infos = self._state("infos")
        if self.mask != "info":
            return infos
        return {a: {**info, "action_mask": self._masks[a].copy()} for a, info in infos.items()}

    def action_mask(self, agent) -> np.ndarray:
        return self._masks[agent].copy()

    def observe(self, agent):
        obs = self.env.observe(agent)  # before reset, order enforcing's error
        if self._image_size is not None:
            obs = _flat_obs(obs, agent, self._image_size, self._eli, self._lengths[agent])
        if self.mask == "obs":
            return {"observation": obs, "action_mask": self._masks[agent].copy()}
        return obs

    def last(self, observe: bool = True):
        # after the reset, the native env's state read there at once (AECEnv.last's five
        # reads would each go through __getattr__)
        if not self.env._has_reset:
            return super().last(observe)  # order enforcing's AttributeError
        native = self._native
        agent = native.agent_selection
        return (self.observe(agent) if observe else None, native._cumulative_rewards[agent],
                native.terminations[agent], native.truncations[agent], self.infos[agent])

    def reset(self, seed=None, options=None) -> None:
        self.env.reset(seed=seed, options=options)

    def state(self):
        return self.env.state()

    def render(self):
        return self.env.render()

    def close(self) -> None:
        self.env.close()

    def step(self, action) -> None:
        agent = self.agent_selection  # before reset, order enforcing's AttributeError
        native = self._native
        if not native.agents:
            raise InvalidAction("step() called after the episode ended; call reset()")
        if native.terminations[agent] or native.truncations[agent]:
            if action is not None:
                raise InvalidAction(f"{agent}: the episode has ended; the only valid action is None (dead step)")
        else:
            if isinstance(self._act_spaces[agent], spaces.Discrete):
                action = self._check(agent, action)
            action = _native_action(action, agent, self._grid, self._eli)
        self.env.step(action)

    def _check(self, agent: str, action) -> int:
        k = self._act_spaces[agent].n
        if action is None:
            raise InvalidAction(f"{agent}: action is None but the {agent} is alive; expected an integer in 0..{k - 1}")
        if isinstance(action, np.ndarray) and action.shape == (1,):
            action = action.reshape(())
        a = int(discrete(action, k, f"{agent}: action", (), integers_only=True))
        if not self._masks[agent][a]:
            where = {"obs": "observation['action_mask']", "info": "infos[agent]['action_mask']"}[self.mask]
            raise InvalidAction(f"{agent}: action {a} is masked out; the {agent}'s actions are "
                                f"0..{int(self._masks[agent].sum()) - 1} ({', '.join(ACTION_NAMES)}); see {where}")
        return a

