"""``gymnasium.make_vec("plex_ma/PointNav-v0", num_envs=N, **config)``: the flat task as a
:class:`gymnasium.vector.VectorEnv` over the batched simulator.

``PointNav-v0`` registers :class:`PointNavGymVectorEnv` as its ``vector_entry_point``, so
``make_vec`` builds it when ``vectorization_mode`` is ``"vector_entry_point"`` or left out
(``"sync"`` and ``"async"`` still build gymnasium's vectorizers over N single envs, and
are the modes that take ``wrappers=``). All N worlds step in one simulator call, with
the same rules as the single env (:class:`~plex_ma.envs.rules.PointNavWorlds`).

* Spaces: ``single_observation_space`` is the single env's ``Dict(rgb, depth,
  pointgoal)`` and ``observation_space`` its batch (arrays with a leading N axis);
  ``single_action_space`` is ``Discrete(4)`` and ``action_space`` ``MultiDiscrete([4] * N)``.
* Autoreset: ``metadata["autoreset_mode"]`` is ``AutoresetMode.NEXT_STEP``, the default of
  gymnasium's ``SyncVectorEnv``. The step in which a world's episode ends returns its last
  observation, the reward, ``terminated`` or ``truncated`` and the ended episode's info
  (``success``, ``spl``). The next step ignores that world's action and resets it: the new
  episode's first observation, reward 0, both flags False, the new episode's info.
* Infos: a dict of arrays, one entry per world, with a boolean ``_key`` mask beside each
  key, as gymnasium's vector envs build them: the single env's keys
  (:data:`~plex_ma.envs.rules.INFO_KEYS`), integers as int64, the others float64.
* Seeding: ``reset(seed=s)`` seeds world i as ``reset(seed=s + i)`` seeds a single env
  (a list gives one seed per world; None keeps a world's generator, or seeds it at random
  on the first reset). With the same seeds and actions the observations, rewards, flags
  and infos equal those of ``SyncVectorEnv`` over N ``PointNav-v0`` envs, which the tests
  check. Two cases draw differently from the single envs: GPS+compass noise
  (``pose_noise`` > 0) comes from one generator shared by the worlds, and fixed episodes
  (``episodes_file``, the default for val and test) are dealt out in turn to the worlds
  from one shared cycle, so that N worlds run N different episodes where N single envs
  would each run the file from its start.
* ``reset(options=...)``: ``reset_mask`` (bool array (N,)) resets only those worlds, as
  in ``SyncVectorEnv``; ``episodes`` (a list of :class:`~plex_ma.envs.sim.Episode`, one per
  world reset) starts given episodes.
* Actions: an integer array of shape (N,) with values in 0..3 (numpy, a list, or a CPU
  tensor); anything else raises :class:`~plex_ma.envs.actions.InvalidAction` naming the
  problem, before any world moves.
* ``copy`` (default True): return copies of the image arrays; with ``copy=False`` they are
  the simulator's buffers, overwritten by the next ``step``.
* ``render_mode="rgb_array"``: ``render()`` returns a tuple of N top-down views (the single
  env's, with each world's path), as ``SyncVectorEnv.render`` does. ``"human"`` is not
  offered: use the single env for a live window.

Arguments: ``num_envs``, ``render_mode``, ``copy`` and those of
:class:`~plex_ma.envs.rules.NavConfig`.

Speed: ``python -m plex_ma.bench gymvec`` times it against ``SyncVectorEnv`` over N single
envs (docs/performance.md). The per-step Python of the single envs is what it saves; episode
resets (drawing an episode and its goal's distance field, a few ms each) and rendering
cost both the same, so short episodes and large images narrow the gap.
"""

from __future__ import annotations

from typing import Any

import gymnasium
import numpy as np
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from .actions import discrete
from .rules import INFO_KEYS, NavConfig, PointNavWorlds, make_config
from .sim.core import ACTION_NAMES, NUM_ACTIONS
from .sim.topdown import topdown_view
from .spaces import pointnav_observation_space

# dtypes of the batched infos: those gymnasium's vector envs give the single env's
# Python ints (int64) and floats (float64).
_INFO_DTYPES = {k: np.int64 if k in ("scene_index", "episode_id", "collisions", "steps") else np.float64
                for k in INFO_KEYS}


class PointNavGymVectorEnv(VectorEnv):
    """N flat PointNav worlds as a gymnasium vector env (see the module docstring)."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10, "autoreset_mode": AutoresetMode.NEXT_STEP}

    def __init__(self, num_envs: int = 1, render_mode: str | None = None, copy: bool = True, **config):
        if isinstance(num_envs, bool) or not isinstance(num_envs, (int, np.integer)) or num_envs < 1:
            raise ValueError(f"num_envs must be a positive integer, got {num_envs!r}")
        if render_mode == "human":
            raise ValueError("render_mode='human' is not offered by the vector env; use 'rgb_array' "
                             "(render() returns one top-down view per world) or the single env for a window")
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.metadata = dict(self.metadata)
        self.render_mode = render_mode
        self.copy = bool(copy)
        self.config: NavConfig = make_config(NavConfig, config)
        self.num_envs = int(num_envs)
        self.worlds = PointNavWorlds(self.config, self.num_envs)
        self.single_observation_space = pointnav_observation_space(self.config)
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.single_action_space = gymnasium.spaces.Discrete(NUM_ACTIONS)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        n = self.num_envs
        self._autoreset = np.zeros(n, np.bool_)
        self._episode_id = np.zeros(n, np.int64)
        self._geodesic = np.zeros(n, np.float64)
        self._all_rows = np.arange(n)
        self._all_mask = np.ones(n, np.bool_)
        self._paths: list[list[np.ndarray]] = [[] for _ in range(n)]
        self._started = False

    # ------------------------------------------------------------------ API
    def reset(self, *, seed: int | list[int | None] | None = None, options: dict[str, Any] | None = None):
        n = self.num_envs
        seeds = self._seeds(seed)
        if isinstance(seed, (int, np.integer)):
            super().reset(seed=int(seed))
        options = dict(options or {})
        mask = options.pop("reset_mask", None)
        episodes = options.pop("episodes", None)
        if options:
            raise ValueError(f"unknown reset option(s) {sorted(options)}; known: 'reset_mask', 'episodes'")
        if mask is None:
            mask = self._all_mask
        else:
            if not isinstance(mask, np.ndarray) or mask.dtype != np.bool_ or mask.shape != (n,):
                raise ValueError(f"options['reset_mask'] must be a bool numpy array of shape ({n},), got "
                                 f"{type(mask).__name__}{f' {mask.dtype} {mask.shape}' if hasattr(mask, 'shape') else ''}")
            if not mask.any():
                raise ValueError("options['reset_mask'] must reset at least one world")
            if not self._started and not mask.all():
                raise ValueError("the first reset() must reset every world (no reset_mask, or an all-True one)")
        rows = np.flatnonzero(mask)
        if episodes is not None and len(episodes) != len(rows):
            raise ValueError(f"options['episodes'] must hold one episode per world reset ({len(rows)}), "
                             f"got {len(episodes)}")
        self._seed_worlds(seeds, rows)
        self._reset_rows(rows, None if episodes is None else list(episodes))
        self._autoreset[rows] = False
        self._started = True
        return self._obs(), self._infos(mask)

    def step(self, actions):
        if not self._started:
            raise RuntimeError("step() called before reset(); call reset() first")
        a = self._check_actions(actions)
        w = self.worlds
        resetting = np.flatnonzero(self._autoreset)
        # Worlds whose episode ended in the last step are done: they do not move here
        # (reward 0, both flags False) and start their next episode below.
        rew, term, trunc = w.step(a)
        if self.render_mode is not None:
            for i in np.flatnonzero(~self._autoreset):
                self._paths[i].append(w.sim.pos[i].copy())
        if len(resetting):
            self._reset_rows(resetting)
        self._autoreset = term | trunc
        return self._obs(), rew.astype(np.float64), term, trunc, self._infos(self._all_mask)

    def render(self) -> tuple[np.ndarray, ...] | None:
        """``rgb_array``: one top-down view per world (its path, the goal, the agent)."""
        if self.render_mode != "rgb_array":
            return None
        if not self._started:
            raise RuntimeError("render() called before reset(); call reset() first")
        sim = self.worlds.sim
        return tuple(topdown_view(sim.bank.grids[int(sim.scene_idx[i])], path=np.array(self._paths[i]),
                                  goal=sim.goal[i], agent_pose=(sim.pos[i, 0], sim.pos[i, 1], sim.heading[i]))
                     for i in range(self.num_envs))

    @property
    def scene_ids(self) -> list[str]:
        """The scenes of this env's split, in ``scene_index`` order."""
        return list(self.worlds.bank.scene_ids)

    @property
    def episodes(self) -> list:
        """The current :class:`~plex_ma.envs.sim.Episode` of every world."""
        return list(self.worlds.sim.episodes)

    def __repr__(self) -> str:
        return f"PointNavGymVectorEnv(num_envs={self.num_envs}, resolution={self.config.resolution})"

    # ------------------------------------------------------------------ internals
    def _seeds(self, seed) -> list[int | None]:
        n = self.num_envs
        if seed is None:
            return [None] * n
        if isinstance(seed, (int, np.integer)) and not isinstance(seed, bool):
            return [int(seed) + i for i in range(n)]
        if isinstance(seed, (list, tuple)):
            if len(seed) != n:
                raise ValueError(f"a list of seeds must have one per world ({n}), got {len(seed)}")
            for s in seed:
                if s is not None and (isinstance(s, bool) or not isinstance(s, (int, np.integer))):
                    raise ValueError(f"seeds must be integers or None, got {s!r}")
            return [None if s is None else int(s) for s in seed]
        raise ValueError(f"seed must be an integer, a list of {n} integers or None, got {seed!r}")

    def _seed_worlds(self, seeds: list[int | None], rows: np.ndarray) -> None:
        """Seed each world of ``rows`` as ``PointNav-v0.reset(seed=s)`` seeds its one world
        (:meth:`~plex_ma.envs.rules._Worlds.seed` with one world: the episode generator is
        the first child of ``SeedSequence(s)``, the pose noise the second). A None seed
        keeps the world's generator, except on the first reset, which seeds it at random."""
        w = self.worlds
        seeded = False
        for i in rows:
            s = seeds[i]
            if s is None and self._started:
                continue
            ss = np.random.SeedSequence(s)
            w.rngs[i] = np.random.default_rng(ss.spawn(1)[0])
            if not seeded:  # the shared pose-noise generator follows the first world reseeded
                w.sim.rng = np.random.default_rng(ss.spawn(1)[0])
                seeded = True
        if any(seeds[i] is not None for i in rows):
            w._next_fixed = 0

    def _reset_rows(self, rows: np.ndarray, episodes: list | None = None) -> None:
        w = self.worlds
        w.reset_rows(rows, episodes)
        for i in rows:
            ep = w.sim.episodes[i]
            self._episode_id[i] = int(ep.episode_id)
            self._geodesic[i] = float(ep.geodesic_distance)
            if self.render_mode is not None:
                self._paths[i] = [w.sim.pos[i].copy()]

    def _check_actions(self, actions) -> np.ndarray:
        return discrete(actions, NUM_ACTIONS, "actions", (self.num_envs,), ACTION_NAMES, per="world")

    def _obs(self) -> dict:
        w = self.worlds
        rgb, depth = w.sim.rgb, w.sim.depth
        if self.copy:
            rgb, depth = rgb.copy(), depth.copy()
        return {"rgb": rgb, "depth": depth, "pointgoal": w.goal_vector(self._all_rows)}

    def _infos(self, mask: np.ndarray) -> dict:
        w = self.worlds
        values = {"scene_index": w.sim.scene_idx, "episode_id": self._episode_id, "geodesic_distance": self._geodesic,
                  "distance_to_goal": w.sim.distance_to_goal, "collisions": w.collisions, "steps": w.steps,
                  "success": w.success, "spl": w.spl}
        everyone = mask.all()
        out = {}
        for k in INFO_KEYS:
            v = values[k].astype(_INFO_DTYPES[k])  # a copy
            if not everyone:
                v[~mask] = 0
            out[k] = v
            out[f"_{k}"] = mask.copy()
        return out


__all__ = ["PointNavGymVectorEnv"]
