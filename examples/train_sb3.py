"""Train the flat PointNav task (``plex_ma/PointNav-v0``) with Stable-Baselines3's PPO.

    pip install stable-baselines3        # tested with 2.9.2; not a dependency of plex-ma
    python examples/train_sb3.py --total-timesteps 20000

The observation is a ``Dict`` (``rgb``, ``depth``, ``pointgoal``), so the policy is SB3's
``MultiInputPolicy``: its ``CombinedExtractor`` gives each key its own extractor and joins
them. What it does with each key depends on how the key is encoded:

* ``rgb``, ``uint8`` in [0, 255] with 3 channels: an image. SB3 moves the channels first
  (``VecTransposeImage``), divides by 255 and runs its NatureCNN.
* ``depth``, ``float32`` in [0, 1] with 1 channel: not an image to SB3 (its images are
  ``uint8`` in [0, 255]), so it is flattened into a plain vector (4,096 values at 64 px)
  and joined with the CNN features as it is: no convolution sees it.
  ``--depth-as-image`` encodes it as an image instead (:class:`DepthAsImage`: depth x 255
  rounded to ``uint8``, about 4 cm steps of the 10 m range), which gives depth a NatureCNN
  of its own.
* ``pointgoal``, 2 floats (distance m, direction rad): flattened.

NatureCNN needs images of at least 36 px. The example prints each iteration's episodes and
mean return.
"""

from __future__ import annotations

import argparse
import time

import gymnasium
import numpy as np

import plex_ma  # noqa: F401  (registers plex_ma/PointNav-v0)
from stable_baselines3 import PPO
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.env_util import make_vec_env


class DepthAsImage(gymnasium.ObservationWrapper):
    """``depth`` as a ``uint8`` image (depth x 255, rounded), which SB3 runs through a CNN."""

    def __init__(self, env: gymnasium.Env):
        super().__init__(env)
        spaces = dict(env.observation_space.spaces)
        spaces["depth"] = gymnasium.spaces.Box(0, 255, spaces["depth"].shape, np.uint8)
        self.observation_space = gymnasium.spaces.Dict(spaces)

    def observation(self, obs: dict) -> dict:
        return {**obs, "depth": np.rint(obs["depth"] * 255).astype(np.uint8)}


class EpisodeLog(BaseCallback):
    """Prints, after each rollout, the episodes that ended in it and their mean return."""

    def __init__(self):
        super().__init__()
        self.returns: list[float] = []
        self.lines: list[str] = []
        self._t = time.perf_counter()

    def _on_step(self) -> bool:
        for info in self.locals["infos"]:
            if "episode" in info:
                self.returns.append(float(info["episode"]["r"]))
        return True

    def _on_rollout_end(self) -> None:
        dt = time.perf_counter() - self._t
        mean = float(np.mean(self.returns)) if self.returns else float("nan")
        line = (f"{self.num_timesteps} steps, {len(self.returns)} episodes, mean return {mean:.3f} "
                f"({self.model.n_steps * self.model.n_envs / max(dt, 1e-9):.0f} steps/s)")
        print(line, flush=True)
        self.lines.append(line)
        self.returns, self._t = [], time.perf_counter()


def make_env(args: argparse.Namespace):
    env = gymnasium.make("plex_ma/PointNav-v0", resolution=args.resolution, num_scenes=args.num_scenes,
                         max_steps=args.max_steps)
    return DepthAsImage(env) if args.depth_as_image else env


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--total-timesteps", type=int, default=20_000)
    p.add_argument("--num-envs", type=int, default=2, help="envs in SB3's DummyVecEnv")
    p.add_argument("--n-steps", type=int, default=256, help="steps per env per rollout")
    p.add_argument("--resolution", type=int, default=64, help="image size (at least 36 for NatureCNN)")
    p.add_argument("--num-scenes", type=int, default=8)
    p.add_argument("--max-steps", type=int, default=500)
    p.add_argument("--depth-as-image", action="store_true", help="depth as a uint8 image with its own CNN")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    vec = make_vec_env(lambda: make_env(args), n_envs=args.num_envs, seed=args.seed)
    model = PPO("MultiInputPolicy", vec, n_steps=args.n_steps, batch_size=64, n_epochs=2, seed=args.seed,
                device="cpu", verbose=0)
    log = EpisodeLog()
    model.learn(total_timesteps=args.total_timesteps, callback=log)
    extractors = {k: type(m).__name__ for k, m in model.policy.features_extractor.extractors.items()}
    print(f"feature extractors: {extractors}")
    vec.close()
    return {"model": model, "lines": log.lines, "extractors": extractors}


if __name__ == "__main__":
    main()
