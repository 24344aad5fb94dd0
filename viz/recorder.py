"""Rerun recordings of PLEX episodes: :class:`EpisodeRecorder` (its stream helpers and the
``.rrd`` plumbing are in :mod:`plex_ma.viz.rerun_io`).

:class:`EpisodeRecorder` follows one world (``world=0`` by default) of a
:class:`~plex_ma.envs.vector.PlexVectorEnv` (or of a flat
:class:`~plex_ma.envs.vector.PointNavVectorEnv`) and logs what happens there through
rerun-sdk into an ``.rrd`` file, on the ``step`` timeline (executor actions since the
episode began; a planner decision is logged at the step count it was taken at, before the
executor's next action), under the entity paths of :data:`plex_ma.viz.layout.ENTITY_TABLE`.
``rerun FILE.rrd`` opens it.

**One recording per episode, one file.** Every recorded episode is its own rerun
recording (application id ``plex_ma``, named e.g. ``episode 2: procgen-val-00002 #2``),
so all episodes use the same entity paths and each one's ``step`` timeline starts at 0;
the viewer lists them in its recordings panel. Several episodes are written to temporary
files and merged into the one output file with the ``rerun rrd merge`` of the CLI that
ships with rerun-sdk (:func:`merge_rrd`). Each recording carries the default blueprint
(:func:`~plex_ma.viz.layout.default_blueprint`). Only complete episodes are kept (an
episode cut short by :meth:`EpisodeRecorder.end` is dropped unless nothing else was
recorded).

Rows are buffered and sent as columns (``send_columns``) at the end of each episode (or
every ``flush_every`` steps), which costs a small fraction of logging every entity at
every step. :meth:`EpisodeRecorder.topdown` draws a recorded episode with
``topdown_view`` (map, path, goal, sub-goal, pose) for a PNG.

``spawn=True`` also streams every recording live to a Rerun viewer (``rr.spawn``: starts
one if none listens on port 9876); it needs a display.
"""

from __future__ import annotations

import shutil
import tempfile
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import ClassVar

import numpy as np
import rerun as rr

from plex_ma.envs.sim.topdown import topdown_view
from plex_ma.envs.spaces import EGO_CELL, EGO_SIZE
from plex_ma.envs.vector import PlexVectorEnv, PointNavVectorEnv

from .layout import (AGENT, APPLICATION_ID, COLLISION, GOAL, PALETTE, PATH, START, SUBGOAL, SUBGOAL_RAW, TIMELINE,
                     default_blueprint, ego_map_rgb, ego_pixel, eli_projection_matrix, pca_2d, time_colours)
from .rerun_io import (_cumulative, _Episode, _put_rerun_on_path, _send, jpeg, merge_rrd, rerun_executable,
                       send_training_scalars, tensor_column)


class EpisodeRecorder:
    """Record the episodes of one world of a vector env into ``path`` (see the module docstring).

    Args:
        path: the ``.rrd`` file to write (its directory is created).
        world: which world of the env to follow.
        max_episodes: stop recording after this many complete episodes (None: all). The
            default keeps ``evaluate --record`` files small: world 0's first 10 episodes.
        images: log the RGB, depth and ego map images (most of a recording's size).
        jpeg_quality: store RGB images as JPEG of this quality (None: raw pixels).
        spawn: also stream live to a Rerun viewer (``rr.spawn``; needs a display).
        name: prefix of the recordings' names (e.g. ``update 50``).
        flush_every: executor steps buffered before they are sent (1 with ``spawn``).
        max_image_size: subsample RGB and depth images larger than this (by a whole stride).

    The protocol (:func:`plex_ma.trainers.evaluation.run_episodes` drives it): ``begin(env)`` after
    ``env.reset()``, ``step(env, res, rows=rows)`` after a planner step,
    ``step(env, res, eli=eli)`` after an executor step (``res`` the ``PlexVecStep``; for a
    ``PointNavVectorEnv`` the tuple its ``step`` returns), and ``end()`` once, which
    writes the file. ``episodes`` then lists what was recorded.
    """

    def __init__(self, path: str | Path, world: int = 0, max_episodes: int | None = 10, images: bool = True,
                 jpeg_quality: int | None = None, spawn: bool = False, name: str | None = None,
                 flush_every: int | None = None, max_image_size: int | None = None):
        self.path = Path(path)
        self.world = int(world)
        self.max_episodes = max_episodes
        self.images = images
        self.jpeg_quality = jpeg_quality
        self.spawn = spawn
        self.name = name
        self.flush_every = flush_every if flush_every is not None else (1 if spawn else 100)
        self.max_image_size = max_image_size
        self._stride = 1
        self.episodes: list[dict] = []
        self._ep: _Episode | None = None
        self._done: list[_Episode] = []
        self._count = 0
        self._env = None
        self._plex = False
        self._tmpdir: Path | None = None
        self._proj = eli_projection_matrix()
        self._spawned = False
        self._train_rec: _Episode | None = None
        self._pending_train: list[dict] = []
        self._blueprint = default_blueprint()

    @property
    def began(self) -> bool:
        """Whether :meth:`begin` has been called (an env is being followed)."""
        return self._env is not None

    # ------------------------------------------------------------------ protocol
    def begin(self, env: PlexVectorEnv | PointNavVectorEnv) -> None:
        """Start following ``env``'s world (call after ``env.reset()``)."""
        if self._env is not None:
            raise RuntimeError("EpisodeRecorder.begin() called twice; use one recorder per run")
        if not isinstance(env, (PlexVectorEnv, PointNavVectorEnv)):
            raise TypeError(f"EpisodeRecorder follows a PlexVectorEnv or a PointNavVectorEnv, not {type(env).__name__}")
        if not 0 <= self.world < env.num_envs:
            raise ValueError(f"world {self.world} is not in an env of {env.num_envs} worlds")
        self._env = env
        self._plex = isinstance(env, PlexVectorEnv)
        self._make_tmpdir()
        self._start_episode()

    def step(self, env, res, rows=None, eli=None) -> None:
        """Log what the last ``env.step`` did in the followed world."""
        ep = self._ep
        if ep is None or env is not self._env:
            return
        w = self.world
        if not self._plex:
            self._flat_step(ep, res)
            return
        acted = int(res.acted[w])
        if acted < 0:
            return
        ended_rows = np.flatnonzero(res.terminated | res.truncated)
        ended = w in ended_rows
        j = int(np.searchsorted(ended_rows, w))
        info = res.episode_infos[j] if ended else None
        if acted == 0:  # the planner
            self._planner_step(ep, res, ended, info)
        else:
            self._executor_step(ep, res, eli, ended, info, res.final_pose[j] if ended else None, j)
        if ended:
            self._finish(ep, info, stopped=acted == 0)
        elif ep.unsent >= self.flush_every:
            self._flush(ep)

    def end(self) -> list[dict]:
        """Close the recordings and write the file; returns ``episodes``."""
        keep = list(self._done)
        if self._ep is not None:
            self._flush(self._ep)
            self._close_stream(self._ep)
            if not keep:  # nothing complete: keep what there is rather than nothing
                keep.append(self._ep)
                self.episodes.append(self._summary(self._ep))
            self._ep = None
        if self._pending_train and self._env is None:  # training scalars only
            self._make_tmpdir()
            self._training_stream()
        if self._train_rec is not None:
            self._close_stream(self._train_rec)
            keep.append(self._train_rec)
            self._train_rec = None
        # rerun keeps a dropped stream's native state until orphaned recordings are cleaned up
        # (as rr.init does); without this, what each recording logged stays in memory for the
        # rest of a training run
        rr.bindings.flush_and_cleanup_orphaned_recordings()
        if self._tmpdir is None:
            return self.episodes
        files = [e.file for e in keep if e.file.exists()]
        try:
            if len(files) == 1:
                files[0].replace(self.path)
            elif files:
                merge_rrd(files, self.path)
        finally:
            shutil.rmtree(self._tmpdir, ignore_errors=True)
            self._tmpdir = None
        return self.episodes

    # ------------------------------------------------------------------ training scalars
    def log_training_scalars(self, step: int, metrics: dict) -> None:
        """Log ``metrics`` (name -> number) as ``train/<name>`` at ``train_step = step``.

        They go into the episode being recorded; before ``begin`` they wait for the first
        episode; after the last one they go into a recording named ``training``."""
        self.log_training_history([{**metrics, "step": int(step)}])

    def log_training_history(self, records: list[dict]) -> None:
        """Log many metric lines at once (dicts with ``step``, as in ``metrics.jsonl``)."""
        if self._env is None:
            self._pending_train.extend(records)
            return
        rec = self._ep.rec if self._ep is not None else self._training_stream()
        send_training_scalars(rec, records)

    def _training_stream(self) -> rr.RecordingStream:
        if self._train_rec is None:
            self._train_rec = self._open("training")
        return self._train_rec.rec

    # ------------------------------------------------------------------ streams
    def _make_tmpdir(self) -> None:
        if self._tmpdir is None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._tmpdir = Path(tempfile.mkdtemp(prefix=f".{self.path.name}.", dir=self.path.parent))

    def _open(self, name: str, blueprint=None) -> _Episode:
        n = self._count
        self._count += 1
        rec = rr.RecordingStream(APPLICATION_ID, recording_id=f"{self.path.stem}-{n:04d}-{uuid.uuid4().hex[:12]}")
        rec.set_log_time_enabled(False)
        rec.set_log_tick_enabled(False)
        file = self._tmpdir / f"part_{n:04d}.rrd"
        if self.spawn:
            if not self._spawned:
                _put_rerun_on_path()
                rec.spawn(connect=False)
                self._spawned = True
            rec.set_sinks(rr.FileSink(str(file)), rr.GrpcSink(), default_blueprint=blueprint or self._blueprint)
        else:
            rec.save(file, default_blueprint=blueprint or self._blueprint)
        full = f"{self.name}: {name}" if self.name else name
        rec.send_recording_name(full)
        if self._pending_train:
            send_training_scalars(rec, self._pending_train)
        return _Episode(rec, file, n, full)

    @staticmethod
    def _close_stream(ep: _Episode) -> None:
        ep.rec.flush()
        ep.rec.disconnect()
        ep.rec = None  # with no reference left, end() frees the stream

    # ------------------------------------------------------------------ episodes
    def _start_episode(self) -> None:
        if self.max_episodes is not None and len(self._done) >= self.max_episodes:
            self._ep = None
            return
        env, w = self._env, self.world
        view = env.world(w, images=self.images)
        episode, grid = view.episode, view.grid
        (ox, oy), (h, wd) = grid.origin, grid.shape
        m = 0.5
        extent = (ox - m, ox + wd * grid.cell_size + m, oy - m, oy + h * grid.cell_size + m)
        ep = self._open(f"episode {len(self._done)}: {episode.scene_id} #{episode.episode_id}",
                        default_blueprint(extent))
        self._ep = ep
        rec = ep.rec
        ep.description = (f"**scene** `{episode.scene_id}`, **episode** {episode.episode_id}, "
                          f"**geodesic distance** {episode.geodesic_distance:.2f} m, "
                          f"**agent** {'PLEX (planner + executor)' if self._plex else 'flat PointNav'}")
        rec.log("episode", rr.TextDocument(ep.description, media_type="text/markdown"), static=True)
        ep.grid, ep.goal = grid, np.asarray(episode.goal_position)
        r = view.resolution
        self._stride = max(1, -(-r // self.max_image_size)) if self.max_image_size else 1
        self._log_static(rec, ep.grid, episode, len(range(0, r, self._stride)))
        pos = view.position
        ep.path.append((float(pos[0]), float(pos[1])))
        ep.heading = view.heading
        ep.add("agent", (pos, ep.heading))
        ep.add("scalar:metrics/distance_to_goal", view.distance_to_goal)
        ep.add("scalar:metrics/collisions", 0.0)
        if self.images:
            ep.add("images", (view.rgb, view.depth))
        if self._plex and view.turn == 0:
            self._add_ego_map(ep, env.ego_map(w))
        if self.flush_every <= 1:
            self._flush(ep)

    def _log_static(self, rec: rr.RecordingStream, grid, episode, resolution: int) -> None:
        """What does not change during an episode: the map, start and goal, and the styles
        (colours, sizes, image formats) of the entities logged as columns later."""
        ppm = 20.0  # map pixels per metre
        img = topdown_view(grid, px_per_m=ppm)
        h_m = grid.shape[0] * grid.cell_size
        log = lambda path, *a: rec.log(path, *a, static=True)  # noqa: E731
        log("world", rr.Transform3D(scale=[1.0, -1.0, 1.0]))
        log("world/map", rr.Transform3D(translation=[grid.origin[0], grid.origin[1] + h_m, 0.0],
                                        scale=[1.0 / ppm, -1.0 / ppm, 1.0]))
        log("world/map", rr.Image(img))
        log("world/start", rr.Points2D([episode.start_position], radii=0.15, colors=[START], labels=["start"]))
        log("world/goal", rr.Points2D([episode.goal_position], radii=0.2, colors=[GOAL], labels=["goal"]))
        log("world/agent", rr.Points2D.from_fields(radii=0.15, colors=[AGENT]))
        log("world/agent/heading", rr.Arrows2D.from_fields(radii=0.04, colors=[AGENT]))
        log("world/path", rr.LineStrips2D.from_fields(radii=0.04, colors=[PATH]))
        log("world/collisions", rr.Points2D.from_fields(radii=0.07, colors=[COLLISION]))
        log("metrics/distance_to_goal", rr.SeriesLines(names="distance to goal (m)", colors=[GOAL]))
        log("metrics/collisions", rr.SeriesLines(names="collisions", colors=[COLLISION]))
        log("metrics/success", rr.SeriesPoints(names="success", colors=[AGENT]))
        log("metrics/spl", rr.SeriesPoints(names="SPL", colors=[PATH]))
        if self.images:
            if not self.jpeg_quality:
                log("executor/rgb", rr.Image.from_fields(format=rr.components.ImageFormat(
                    width=resolution, height=resolution, color_model="RGB", channel_datatype="U8")))
            log("executor/depth", rr.DepthImage.from_fields(format=rr.components.ImageFormat(
                width=resolution, height=resolution, channel_datatype="U16"), meter=1000.0))
        if self._plex:
            log("world/subgoal", rr.Points2D.from_fields(radii=0.12, colors=[SUBGOAL]))
            log("world/subgoal_raw", rr.Points2D.from_fields(radii=0.08, colors=[SUBGOAL_RAW]))
            log("world/subgoals", rr.Points2D.from_fields(radii=0.08))
            log("world/subgoals_raw", rr.Points2D.from_fields(radii=0.05))
            log("world/subgoal_line", rr.LineStrips2D.from_fields(radii=0.02, colors=[SUBGOAL]))
            log("reward/planner", rr.SeriesLines(names="planner", colors=[PATH]))
            log("reward/executor", rr.SeriesLines(names="executor", colors=[SUBGOAL]))
            log("planner/subgoal_index", rr.SeriesLines(names="sub-goal index", colors=[SUBGOAL_RAW]))
            if self.images:
                s = 32
                log("planner/ego_map", rr.Image.from_fields(format=rr.components.ImageFormat(
                    width=s, height=s, color_model="RGB", channel_datatype="U8")))
                log("planner/ego_map/agent", rr.Points2D([[s / 2, s / 2]], radii=0.8, colors=[AGENT]))
                log("planner/ego_map/goal", rr.Points2D.from_fields(radii=0.8, colors=[GOAL]))
                log("planner/ego_map/subgoal", rr.Points2D.from_fields(radii=0.8, colors=[SUBGOAL]))
        else:
            log("reward/agent", rr.SeriesLines(names="agent", colors=[PATH]))

    def _add_ego_map(self, ep: _Episode, ego: np.ndarray) -> None:
        if not self.images:
            return
        polar = self._env.world(self.world, images=False).goal_polar
        ep.add("ego", (np.array(ego, np.float32), ego_pixel(polar, ego.shape[-1], EGO_CELL)))

    def _planner_step(self, ep: _Episode, res, ended: bool, info) -> None:
        w = self.world
        r = float(res.rewards[w, 0])
        ep.returns[0] += r
        if ended:  # the planner chose STOP
            ep.add("scalar:reward/planner", r)
            ep.add("events", (f"step {ep.t}: planner STOP, {info['distance_to_goal']:.2f} m from the goal", "INFO"))
            return
        view = self._env.world(w, images=False)
        sg, raw = view.subgoal, view.subgoal_raw
        ep.k += 1
        ep.subgoals.append((float(sg[0]), float(sg[1])))
        ep.subgoals_raw.append((float(raw[0]), float(raw[1])))
        ep.add("subgoals", len(ep.subgoals))
        pos = view.position
        ep.add("subgoal_line", np.stack([pos, sg]).astype(np.float32))
        if self.images:
            ep.add("ego_subgoal", ego_pixel(view.subgoal_raw_polar, EGO_SIZE, EGO_CELL))
        d = float(np.hypot(*(raw - pos)))
        snap = float(np.hypot(*(raw - sg)))
        ep.add("events", (f"step {ep.t}: sub-goal #{ep.k} at ({sg[0]:.2f}, {sg[1]:.2f}), {d:.2f} m from the agent"
                          + (f", snapped {snap:.2f} m from the proposed ({raw[0]:.2f}, {raw[1]:.2f})"
                             if snap > 1e-3 else ""), "INFO"))

    def _moved(self, ep: _Episode, info, final_pose) -> tuple[np.ndarray, float, int]:
        """After an action: log the pose, path, distance and collisions; returns them.

        ``info`` and ``final_pose`` (x, y, heading) are those of the episode if it ended in
        this action (None otherwise): the env has then already reset the world."""
        ep.t += 1
        if info is not None:
            pos, heading = np.array(final_pose[:2], np.float64), float(final_pose[2])
            dist, coll = float(info["distance_to_goal"]), int(info["collisions"])
        else:
            view = self._env.world(self.world, images=False)
            pos, heading, dist, coll = view.position, view.heading, view.distance_to_goal, view.collisions
        ep.path.append((float(pos[0]), float(pos[1])))
        ep.heading = heading
        ep.add("agent", (pos, heading))
        ep.add("scalar:metrics/distance_to_goal", dist)
        ep.add("scalar:metrics/collisions", float(coll))
        if coll != ep.collisions:
            ep.collision_points.append((float(pos[0]), float(pos[1])))
            ep.collisions = coll
            ep.add("collisions", len(ep.collision_points))
        ep.unsent += 1
        return pos, dist, coll

    def _executor_step(self, ep: _Episode, res, eli, ended: bool, info, final_pose, j: int) -> None:
        """Log an executor step; ``j`` is the followed world's row among the ended ones."""
        w = self.world
        pos, _, _ = self._moved(ep, info, final_pose)
        if ended:
            rgb, depth = res.final_executor_obs["rgb"][j], res.final_executor_obs["depth"][j]
        else:
            rgb, depth = res.executor_obs["rgb"][w], res.executor_obs["depth"][w]
        r_pl, r_ex = float(res.rewards[w, 0]), float(res.rewards[w, 1])
        ep.returns += (r_pl, r_ex)
        ep.add("scalar:reward/planner", r_pl)
        ep.add("scalar:reward/executor", r_ex)
        ep.add("scalar:planner/subgoal_index", float(ep.k))
        if ep.k >= 0:
            ep.add("subgoal_line", None if res.executor_turn_end[w] else
                   np.stack([pos, np.asarray(ep.subgoals[-1])]).astype(np.float32))
        if self.images:
            ep.add("images", (np.array(rgb), np.array(depth)))
        if eli is not None:
            ep.elis.append(np.asarray(eli, np.float32)[w].copy())
            ep.eli_k.append(ep.k)
            ep.add("eli", len(ep.elis))
        if res.executor_stopped[w]:
            d_sub = float(np.hypot(*(pos - np.asarray(ep.subgoals[-1])))) if ep.k >= 0 else float("nan")
            reached = getattr(res, "executor_reached", None)
            note = "" if reached is None else (" (reached)" if reached[w] else " (not reached)")
            ep.add("events", (f"step {ep.t}: executor STOP for sub-goal #{ep.k}, {d_sub:.2f} m from it{note}",
                              "INFO"))
        if not ended and int(res.turn[w]) == 0:
            self._add_ego_map(ep, res.planner_obs["ego_map"][w])

    def _flat_step(self, ep: _Episode, res) -> None:
        obs, rew, term, trunc, infos = res
        w = self.world
        ended_rows = np.flatnonzero(np.asarray(term) | np.asarray(trunc))
        ended = w in ended_rows
        j = int(np.searchsorted(ended_rows, w))
        info = infos[j] if ended else None
        self._moved(ep, info, self._env.final_pose[j] if ended else None)
        r = float(rew[w])
        ep.returns[0] += r
        ep.add("scalar:reward/agent", r)
        if self.images and not ended:  # the flat env keeps no final images of an ended episode
            ep.add("images", (np.array(obs["rgb"][w]), np.array(obs["depth"][w])))
        if ended:
            self._finish(ep, info, stopped=bool(np.asarray(term)[w]))
        elif ep.unsent >= self.flush_every:
            self._flush(ep)

    def _finish(self, ep: _Episode, info: dict, stopped: bool) -> None:
        success, spl = float(info["success"]), float(info["spl"])
        ep.add("scalar:metrics/success", success)
        ep.add("scalar:metrics/spl", spl)
        how = "stopped" if stopped else "truncated"
        ep.add("events", ((f"step {ep.t}: episode {how}: success {success:.0f}, SPL {spl:.3f}, "
                           f"{info['distance_to_goal']:.2f} m from the goal, {info['collisions']} collisions"),
                          "INFO" if success else "WARN"))
        self._flush(ep)
        rec = ep.rec
        if ep.elis:
            x = np.stack(ep.elis)
            rec.log("eli/episode", rr.Tensor(x, dim_names=["step", "eli"]), static=True)
            if len(x) >= 2:
                rec.log("eli/pca", rr.Points2D(pca_2d(x), colors=time_colours(len(x)),
                                               radii=rr.Radius.ui_points(3.0)), static=True)
        ep.finished = True
        ep.result = {"success": success, "spl": spl, "distance_to_goal": float(info["distance_to_goal"]),
                     "collisions": int(info["collisions"]), "steps": int(info["steps"]), "ended_by": how}
        rec.log("episode", rr.TextDocument(
            ep.description + f"\n\n**result**: {how} after {ep.t} steps, success {success:.0f}, SPL {spl:.3f}, "
            f"{ep.k + 1} sub-goals, {ep.result['collisions']} collisions", media_type="text/markdown"), static=True)
        self._close_stream(ep)
        self._done.append(ep)
        self.episodes.append(self._summary(ep))
        self._start_episode()

    def _summary(self, ep: _Episode) -> dict:
        out = {"recording": ep.name, "steps": ep.t, "subgoals": ep.k + 1, "finished": ep.finished, **ep.result}
        if self._plex:
            out["return_planner"], out["return_executor"] = float(ep.returns[0]), float(ep.returns[1])
        else:
            out["return"] = float(ep.returns[0])
        return out

    def topdown(self, index: int = -1, px_per_m: float = 40.0) -> np.ndarray:
        """The top-down picture (``topdown_view``) of recorded episode ``index``: the map,
        the whole path, the goal, the last sub-goal (raw and snapped) and the final pose."""
        eps = self._done + ([self._ep] if self._ep is not None else [])
        ep = eps[index]
        last = ep.path[-1]
        return topdown_view(ep.grid, path=np.asarray(ep.path), goal=ep.goal,
                            subgoal=ep.subgoals[-1] if ep.subgoals else None,
                            subgoal_raw=ep.subgoals_raw[-1] if ep.subgoals_raw else None,
                            agent_pose=(last[0], last[1], ep.heading), px_per_m=px_per_m)

    # ------------------------------------------------------------------ sending
    def _flush(self, ep: _Episode) -> None:
        """Send the buffered rows as columns: per row kind, its sender in ``_SENDERS``."""
        rows, ep.rows, ep.unsent = ep.rows, {}, 0
        for key, items in rows.items():
            kind, _, entity = key.partition(":")
            times = np.array([t for t, _ in items], np.int64)
            self._SENDERS[kind](self, ep, times, [v for _, v in items], entity)

    # Each sender takes (episode, times, values, entity) with ``entity`` the part of the
    # row key after ``:`` (only scalars name their entity there).
    def _send_scalars(self, ep: _Episode, times, vals, entity: str) -> None:
        _send(ep.rec, entity, times, rr.Scalars.columns(scalars=np.asarray(vals, np.float64)))

    def _send_agent(self, ep: _Episode, times, vals, entity: str) -> None:
        pos = np.array([p for p, _ in vals], np.float32)
        h = np.array([a for _, a in vals])
        _send(ep.rec, "world/agent", times, rr.Points2D.columns(positions=pos))
        _send(ep.rec, "world/agent/heading", times, rr.Arrows2D.columns(
            origins=pos, vectors=0.5 * np.stack([np.cos(h), np.sin(h)], 1).astype(np.float32)))
        # the path so far: every row repeats the path up to its step
        path = np.asarray(ep.path, np.float32)
        first = len(ep.path) - len(vals)  # each row added one point to the path
        _send(ep.rec, "world/path", times, rr.LineStrips2D.columns(
            strips=[path[: first + i + 1] for i in range(len(vals))]))

    def _send_images(self, ep: _Episode, times, vals, entity: str) -> None:
        k = self._stride
        rgb = np.ascontiguousarray(np.stack([a for a, _ in vals])[:, ::k, ::k])
        depth = np.stack([d for _, d in vals])[:, ::k, ::k, 0]
        if self.jpeg_quality:
            blobs = [jpeg(im, int(self.jpeg_quality)) for im in rgb]
            _send(ep.rec, "executor/rgb", times, rr.EncodedImage.columns(blob=blobs,
                                                                         media_type=["image/jpeg"] * len(blobs)))
        else:
            _send(ep.rec, "executor/rgb", times, rr.Image.columns(buffer=rgb.reshape(len(rgb), -1)))
        mm = np.round(depth * 10000.0).astype(np.uint16)  # depth is metres / 10 -> millimetres
        _send(ep.rec, "executor/depth", times, rr.DepthImage.columns(buffer=mm.reshape(len(mm), -1).view(np.uint8)))

    def _send_ego(self, ep: _Episode, times, vals, entity: str) -> None:
        ego = ego_map_rgb(np.stack([a for a, _ in vals]))
        _send(ep.rec, "planner/ego_map", times, rr.Image.columns(buffer=ego.reshape(len(ego), -1)))
        _send(ep.rec, "planner/ego_map/goal", times, rr.Points2D.columns(positions=np.stack([g for _, g in vals])))

    def _send_ego_subgoal(self, ep: _Episode, times, vals, entity: str) -> None:
        _send(ep.rec, "planner/ego_map/subgoal", times, rr.Points2D.columns(positions=np.stack(vals)))

    def _send_subgoals(self, ep: _Episode, times, vals, entity: str) -> None:
        counts = [int(c) for c in vals]
        _send(ep.rec, "world/subgoal", times, rr.Points2D.columns(
            positions=np.asarray([ep.subgoals[c - 1] for c in counts], np.float32),
            labels=[f"#{c - 1}" for c in counts]))
        _send(ep.rec, "world/subgoal_raw", times, rr.Points2D.columns(
            positions=np.asarray([ep.subgoals_raw[c - 1] for c in counts], np.float32)))
        n = max(counts)
        colours = PALETTE[np.arange(n) % len(PALETTE)]
        _send(ep.rec, "world/subgoals", times, _cumulative(ep.subgoals[:n], counts, colors=colours))
        _send(ep.rec, "world/subgoals_raw", times, _cumulative(ep.subgoals_raw[:n], counts, colors=colours))

    def _send_subgoal_line(self, ep: _Episode, times, vals, entity: str) -> None:
        strips = [s for s in vals if s is not None]
        _send(ep.rec, "world/subgoal_line", times, rr.LineStrips2D.columns(strips=strips).partition(
            [0 if s is None else 1 for s in vals]))

    def _send_collisions(self, ep: _Episode, times, vals, entity: str) -> None:
        counts = [int(c) for c in vals]
        _send(ep.rec, "world/collisions", times, _cumulative(ep.collision_points[:max(counts)], counts))

    def _send_eli(self, ep: _Episode, times, vals, entity: str) -> None:
        rec = ep.rec
        counts = [int(c) for c in vals]
        n = max(counts)
        x = np.stack(ep.elis[:n])
        rows_x = x[np.asarray(counts) - 1]
        try:
            _send(rec, "eli/tensor", times, [tensor_column(rows_x, "eli")])
        except Exception:  # an arrow layout this code does not know: one call per step
            for t, e in zip(times, rows_x):
                rec.set_time(TIMELINE, sequence=int(t))
                rec.log("eli/tensor", rr.Tensor(e, dim_names=["eli"]))
            rec.reset_time()
        colours = PALETTE[np.maximum(np.asarray(ep.eli_k[:n]), 0) % len(PALETTE)]
        pts = x @ self._proj
        idx = np.concatenate([np.arange(c) for c in counts])
        last = np.concatenate([np.arange(c) == c - 1 for c in counts])
        _send(rec, "eli/projection", times, rr.Points2D.columns(  # radii in UI points (negative)
            positions=pts[idx], colors=colours[idx], radii=np.where(last, -6.0, -2.5).astype(np.float32),
        ).partition(counts))

    def _send_events(self, ep: _Episode, times, vals, entity: str) -> None:
        _send(ep.rec, "events", times, rr.TextLog.columns(text=[s for s, _ in vals], level=[lv for _, lv in vals]))

    _SENDERS: ClassVar[dict[str, Callable]] = {
        "scalar": _send_scalars, "agent": _send_agent, "images": _send_images, "ego": _send_ego,
        "ego_subgoal": _send_ego_subgoal, "subgoals": _send_subgoals, "subgoal_line": _send_subgoal_line,
        "collisions": _send_collisions, "eli": _send_eli, "events": _send_events,
    }


__all__ = ["EpisodeRecorder", "jpeg", "merge_rrd", "rerun_executable", "send_training_scalars", "tensor_column"]
