"""PLEX navigation (``plex_nav_v0``): planner and executor in a two-agent PettingZoo AEC env.

```python
from plex_ma.envs import plex_nav_v0
env = plex_nav_v0.env(resolution=128)
```

| | |
|---|---|
| Agents | `possible_agents = ["planner", "executor"]` |
| Turn order | planner, then the executor for up to `n_ex` actions, then the planner again |
| Planner action | `Dict(stop=Discrete(2), subgoal=Box([0, -pi], [rho_max, pi]))` |
| Planner observation | `Dict(ego_map=Box(0, 1, (6, 32, 32)), goal=Box((2,)), eli=Box((128,)))` |
| Executor action | `Dict(action=Discrete(4), eli=Box((128,)))` |
| Executor observation | `Dict(rgb=Box(0, 255, (H, W, 3), uint8), depth=Box(0, 1, (H, W, 1)), subgoal=Box((2,)))` |
| Render modes | `human` (a live window), `rgb_array` (top-down map, path, goal, current sub-goal) |
| `is_parallelizable` | False (`parallel_env()` is the turn-based Parallel view; see "Parallel API") |

Two cooperating agents navigate to a PointGoal in an indoor scene (the PLEX paper's
hierarchy). The **planner** sees a 32x32 egocentric top-down map (0.5 m cells; channel 0
obstacles, channel 1 explored free space, channels 2-5 the obstacles of each cell's four
0.25 m quarters; row 0 ahead of the agent, built only from depth and the noisy pose),
the end goal as (distance m, direction rad) from GPS+compass, and the Executor Latent
Information (ELI) that the executor sent with the last action of its previous turn. It
either stops the episode (`stop=1`) or proposes a sub-goal (distance, direction)
relative to the agent; the sub-goal is then fixed in the world and moved to
the nearest navigable point if needed. The **executor** sees RGB-D and the sub-goal
vector (recomputed after every step) and acts: 0 STOP, 1 MOVE_FORWARD 0.25 m,
2 TURN_LEFT 10 deg, 3 TURN_RIGHT 10 deg, sending a 128-value ELI with every action. Its
STOP only hands control back to the planner; so does its `n_ex`-th action.

Angles are radians, counter-clockwise, 0 = the agent's heading.

## Rewards

Written into `rewards` for both agents on every executor action, and summed by PettingZoo
into `_cumulative_rewards` until that agent's next turn, so `last()` gives the planner
everything it earned during the executor's turn.

| agent | on every executor action | extra |
|---|---|---|
| executor | decrease of geodesic distance to the sub-goal - 0.01 slack - 0.01 on collision (+ `executor_collision_reward`, 0 by default) | +1.0 for STOP within 0.5 m (geodesic) of a sub-goal that was farther than 0.5 m when it was set; `executor_stop_penalty` (0 by default) for a STOP farther than that |
| planner | decrease of geodesic distance to the end goal - 0.01 slack - 0.01 on collision | +10 when its stop is a success |

A sub-goal set within 0.5 m of the agent (a short or snapped proposal) earns no STOP bonus,
as Habitat never starts an episode at its goal: otherwise an executor learns to STOP at
once on every sub-goal, farming the bonus from the planner's exploration noise.

The planner's return over an episode is thus the flat agent's episode reward (Table 1 of
the paper). A success is a planner stop with the geodesic distance to the goal below
0.2 m; SPL is S * l / max(l, p).

## Episode end

A planner stop terminates both agents; 500 executor actions truncate both. Each agent then
takes one dead step (`step(None)`), as PettingZoo requires; a step after that raises
`InvalidAction` (call `reset()`).

## Infos

`infos[agent]` is the same for both agents and has the same keys from `reset` to the
end, every value a Python number, so trainers that build a fixed spec from the first
infos (TorchRL's `PettingZooWrapper`) can read every step:

| key | type | meaning |
|---|---|---|
| `scene_index` | int | the scene, as an index into `env.unwrapped.scene_ids` |
| `episode_id` | int | the episode's id in its episode file (0 for sampled training episodes) |
| `geodesic_distance` | float | start to goal (m) |
| `distance_to_goal` | float | now (m, geodesic) |
| `collisions` | int | blocked moves so far |
| `steps` | int | executor actions so far |
| `success` | float | 1.0 after a successful stop, else 0.0 (0.0 until the episode ends) |
| `spl` | float | the episode's SPL once it has ended, else 0.0 |

The scene's string id is `env.unwrapped.scene_id` (also `env.scene_id` through the
PettingZoo wrappers), and `env.unwrapped.episode` is the current episode (start, goal,
ids).

## Rendering

`render_mode="rgb_array"`: `render()` returns the top-down view, an (H, W, 3) uint8
array: walls and furniture, the path so far, the goal, the agent, and the current
sub-goal (as proposed and as snapped). `render_mode="human"`: the same view in a
matplotlib window, redrawn after every `reset` and `step` at `metadata["render_fps"]`
(10) frames per second; `render()` returns None. Without a display or without
matplotlib, the human mode gives one `UserWarning` and shows nothing; the env runs on
unchanged (`pettingzoo.test.render_test` passes headless).

## Arguments

| argument | default | meaning |
|---|---|---|
| `resolution` | 128 | RGB-D image size in pixels (square, 8-1024) |
| `n_ex` | 10 | executor actions per turn at most |
| `max_steps` | 500 | executor actions before truncation |
| `rho_max` | 4.0 | largest sub-goal distance (m) |
| `eli` | True | False: the ablation; the planner always sees zeros |
| `scenes` | "procgen" | scene source: "procgen", "r2v", "open-room", a mix "A+B" (e.g. "procgen+r2v"), or a directory of floor plans |
| `split` | "train" | "train", "val" or "test" (procgen val/test cycle through the shipped episode files; other sources sample) |
| `num_scenes` | None | scenes in the split (None: the source's default; procgen 72 train / 16 val / 16 test) |
| `episodes_file` | None | a fixed episode file to cycle through (None: procgen val/test use the split's shipped file, everything else is sampled) |
| `pose_noise` | (0.0, 0.0) | GPS+compass Gaussian noise std (m, rad) |
| `slack_reward`, `collision_reward`, `success_reward`, `subgoal_reward` | -0.01, -0.01, 10, 1 | reward weights |
| `success_distance`, `subgoal_radius` | 0.2, 0.5 | metres |
| `executor_stop_penalty`, `executor_collision_reward` | 0.0, 0.0 | the executor's extra rewards for a STOP outside `subgoal_radius` and for a blocked move (each <= 0) |
| `render_mode` | None | "human" or "rgb_array" (see Rendering) |

## Parallel API

```python
env = plex_nav_v0.parallel_env(resolution=64)                      # the native spaces
env = plex_nav_v0.compat_parallel_env(mask="info", resolution=64)   # Box/Discrete, see compat_env
obs, infos = env.reset(seed=0)
obs, rewards, terminations, truncations, infos = env.step({"planner": ..., "executor": ...})
```

Both are turn-based Parallel views (`plex_ma.envs.parallel.TurnParallelEnv`): each
parallel step is one AEC step, and only the action of the agent whose turn it is is
used; the other agent's action is ignored and may be left out of the dict.
`infos[agent]["acting"]` is True for the agent whose action the step used (False for
both after `reset`), so a trainer keeps that agent's transition and drops the other's:
its action changed nothing. `rewards` are what each agent earned in that step; the
planner earns during the executor's steps, so add them to its last kept transition
(`examples/train_ippo_parallel.py` does). After the step that ends the episode `agents`
is empty (the dead steps are taken inside); call `reset()`.

| view | agent | observation | action | mask |
|---|---|---|---|---|
| `parallel_env()` | planner | `Dict(ego_map, goal, eli)` as above | `Dict(stop=Discrete(2), subgoal=Box(2))` | none |
| | executor | `Dict(rgb, depth, subgoal)` as above | `Dict(action=Discrete(4), eli=Box(128))` | none |
| `compat_parallel_env()` | planner | `Box(6148)` (ego map, goal; + the ELI, 6276, with `eli=True`) or its Dict (`flatten=False`) | `Discrete(33)` | `mask=`: in the observation (`"obs"`), in `infos` (`"info"`) or none |
| | executor | `Box(4100)` (RGB-D 32x32, sub-goal) or its Dict (`flatten=False`) | `Discrete(4)`; `Dict(action=Discrete(4), eli=Box(128))` with `eli=True` | the same |
| `compat_parallel_env(pad=True)` | both | one `Box(6148)` | one `Discrete(33)`, the executor's 4-32 masked | `"obs"` or `"info"` |

`compat_parallel_env(**kwargs)` takes `compat_env`'s arguments (`plex_ma.envs.compat`
documents the layouts). PettingZoo's `parallel_api_test` passes on both views;
`tests/test_parallel.py` also checks whole episodes for determinism under a seed,
`acting` against the AEC turn order, and that the other agent's action changes nothing.

## Why `is_parallelizable` is False, and `max_cycles_test`

The agents do not act round-robin: the executor acts up to `n_ex` times per planner
decision, and only one of them acts at any moment, so the parallel API (every agent acts
each step) does not describe it. The turn-based views above present it anyway, as
PettingZoo's `turn_based_aec_to_parallel` also does (that one names the agent whose
turn comes *next* in `infos[agent]["active_agent"]`, not the one whose action was used).
`pettingzoo.test.max_cycles_test` does not apply: it needs a `max_cycles` argument with
round-robin cycles, while this env's length is bounded by `max_steps` executor actions.

## SuperSuit wrappers

The observation and action spaces are `Dict` spaces, so most SuperSuit wrappers, which
expect `Box` or `Discrete` spaces (`color_reduction_v0`, `resize_v1`,
`frame_stack_v1`, `normalize_obs_v0`, `pad_action_space_v0`, ...), do not apply to the
native env. Reward and timing wrappers do: `clip_reward_v0`, `sticky_actions_v0` and
`frame_skip_v0` (the last two repeat an agent's action, which only makes sense for the
executor; `frame_skip_v0`, written for round-robin games, also replays the planner's
previous action when the executor's turn ends during a skip). `compat_env()` gives a
Box/Discrete view for generic trainers; its docstring (`plex_ma.envs.compat`) lists
every SuperSuit wrapper and what it does here.

## Version history

* v0: initial release.
* v0, infos and rendering: infos hold numbers only, with the same keys from `reset` on
  (`scene_index`; the scene's name is `env.unwrapped.scene_id`; `success` and `spl` read
  0.0 until the end), and the `human` render mode. Observations, actions, rewards and
  episodes are unchanged, so results stay comparable and the name stays `plex_nav_v0`.
* v0, Parallel views: `parallel_env()`, `compat_parallel_env()`, and `compat_env`'s
  options `mask`, `pad`, `flatten` and `eli`. `compat_env()` now gives each agent its own
  spaces (`pad=True` gives the former shared `Discrete(33)` layout); the native env is
  unchanged.
"""

from .compat import compat_env, compat_parallel_env
from .parallel import TurnParallelEnv
from .plex_nav import AGENTS, env, raw_env


def parallel_env(**kwargs) -> TurnParallelEnv:
    """``env(**kwargs)`` as the turn-based Parallel env (see "Parallel API" above)."""
    return TurnParallelEnv(env(**kwargs))


__all__ = ["AGENTS", "compat_env", "compat_parallel_env", "env", "parallel_env", "raw_env"]
