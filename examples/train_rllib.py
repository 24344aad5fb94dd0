"""Train PLEX's two agents with RLlib's multi-agent PPO (new API stack), on the native
``plex_nav_v0.env()`` or on ``plex_nav_v0.compat_env()``.

    pip install "ray[rllib]"            # tested with ray 2.60.0 (it pins gymnasium 1.2.2); not a dependency
    python examples/train_rllib.py --view compat_env --iterations 10

``ray.rllib.env.wrappers.pettingzoo_env.PettingZooEnv`` takes the AEC env as it is: each
step it returns the observation of the agent whose turn is next, and takes that agent's
action. Each agent gets its own policy (``planner``, ``executor``). What each view needs:

* ``env()``: the observations are ``Dict`` spaces, for which RLlib has no default encoder
  ("No default encoder config for obs space=Dict(...)"). The ``FlattenObservations``
  env-to-module connector (``multi_agent=True``) flattens each agent's Dict into one
  vector; the default PPO module (an MLP) then builds. Its Dict actions (a stop flag and
  a continuous sub-goal; an action and the 128-float ELI) get RLlib's default
  distributions.
* ``compat_env(pad=True)``: one ``Discrete(33)`` action space; the observation is
  ``Dict(action_mask, observation)``, and the executor may only use actions 0-3 (the env
  rejects the others: "action 20 is masked out"). Flattening the Dict would hide the mask
  from the policy, so instead :class:`MaskedPPOModule` (RLlib's action-masking example
  module, reading the compat env's ``observation`` key) puts -inf on the masked logits
  before sampling, in training and in inference.

Reward credit comes with the wrapper: with each agent's next observation it hands over
what ``last()`` gives, the rewards the agent earned since its previous turn, so the
planner's decision is credited with everything its executor turn earned (the TorchRL and
Tianshou examples rebuild this by hand).
"""

from __future__ import annotations

import argparse

import gymnasium as gym

from plex_ma.envs import plex_nav_v0
from ray.rllib.algorithms.ppo import PPOConfig
from ray.rllib.connectors.env_to_module import FlattenObservations
from ray.rllib.core.columns import Columns
from ray.rllib.core.rl_module.multi_rl_module import MultiRLModuleSpec
from ray.rllib.core.rl_module.rl_module import RLModuleSpec
from ray.rllib.env.wrappers.pettingzoo_env import PettingZooEnv
from ray.rllib.examples.rl_modules.classes.action_masking_rlm import ActionMaskingTorchRLModule
from ray.tune.registry import register_env

AGENTS = ("planner", "executor")


class MaskedPPOModule(ActionMaskingTorchRLModule):
    """RLlib's action-masking PPO module for the compat env, whose observation Dict holds
    ``observation`` (RLlib's example expects ``observations``)."""

    def __init__(self, *, observation_space=None, **kwargs):
        space = gym.spaces.Dict({"action_mask": observation_space["action_mask"],
                                 "observations": observation_space["observation"]})
        super().__init__(observation_space=space, **kwargs)

    def _preprocess_batch(self, batch, **kwargs):
        obs = batch[Columns.OBS]
        if "observation" in obs:
            obs["observations"] = obs.pop("observation")
        return super()._preprocess_batch(batch, **kwargs)


def make_env(view: str, env_config: dict) -> PettingZooEnv:
    if view == "compat_env":
        return PettingZooEnv(plex_nav_v0.compat_env(pad=True, **env_config))
    return PettingZooEnv(plex_nav_v0.env(**env_config))


def build(view: str, env_config: dict, batch: int = 400, seed: int = 0):
    """A PPO algorithm with one policy per agent over the chosen view."""
    register_env(f"plex-{view}", lambda cfg: make_env(view, cfg))
    module = {"module_class": MaskedPPOModule} if view == "compat_env" else {}
    config = (
        PPOConfig()
        .environment(f"plex-{view}", env_config=env_config)
        .multi_agent(policies=set(AGENTS), policy_mapping_fn=lambda agent_id, episode, **kw: agent_id)
        .rl_module(rl_module_spec=MultiRLModuleSpec(rl_module_specs={a: RLModuleSpec(**module) for a in AGENTS}),
                   model_config={"fcnet_hiddens": [64, 64]})
        .env_runners(num_env_runners=0, num_envs_per_env_runner=1,
                     **({"env_to_module_connector": lambda env, spaces=None, device=None:
                         FlattenObservations(multi_agent=True)} if view == "env" else {}))
        .learners(num_learners=0)
        .training(train_batch_size_per_learner=batch, minibatch_size=min(batch, 128), num_epochs=1, lr=3e-4)
        .debugging(seed=seed)
    )
    return config.build_algo()


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--view", choices=["env", "compat_env"], default="compat_env")
    p.add_argument("--iterations", type=int, default=10)
    p.add_argument("--batch", type=int, default=400, help="env steps per training iteration")
    p.add_argument("--resolution", type=int, default=64)
    p.add_argument("--num-scenes", type=int, default=4)
    p.add_argument("--max-steps", type=int, default=100)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    import ray

    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, ignore_reinit_error=True)
    algo = build(args.view, dict(resolution=args.resolution, num_scenes=args.num_scenes, max_steps=args.max_steps),
                 args.batch, args.seed)
    steps = 0
    try:
        for i in range(1, args.iterations + 1):
            result = algo.train()
            runners = result.get("env_runners", {})
            steps = int(result.get("num_env_steps_sampled_lifetime", runners.get("num_env_steps_sampled_lifetime", 0)))
            ret = runners.get("episode_return_mean", float("nan"))
            print(f"iteration {i}: {steps} env steps, {runners.get('num_episodes_lifetime', 0)} episodes, "
                  f"mean return {ret:.3f}", flush=True)
    finally:
        algo.stop()
        ray.shutdown()
    return {"iterations": args.iterations, "env_steps": steps}


if __name__ == "__main__":
    main()
