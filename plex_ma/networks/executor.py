"""The PLEX executor (:class:`Executor`): an RGB-D CNN (:class:`RGBDEncoder`) and a memory
(:mod:`plex_ma.networks.memory`) to an action, the ELI and a value."""

from __future__ import annotations

import math
from typing import TypedDict

import torch
from torch import nn
from torch.distributions import Categorical

from plex_ma.envs.rules import ELI_DIM
from plex_ma.envs.sim.core import NUM_ACTIONS, STOP, TURN_LEFT, TURN_RIGHT
from plex_ma.networks.common import _conv_out_dim, as_tensor, encode_polar, layer_init
from plex_ma.networks.memory import GRUMemory, SMTMemory

MASKED_LOGIT = -1e8  # a barred action's logit: probability 0 in float32, finite log-probs and entropy


def reversal_mask(prev: torch.Tensor) -> torch.Tensor:
    """(..., NUM_ACTIONS) bool, True for the turn that would undo the previous action ``prev``
    (..., long): RIGHT after LEFT and LEFT after RIGHT."""
    mask = torch.zeros(*prev.shape, NUM_ACTIONS, dtype=torch.bool, device=prev.device)
    mask[..., TURN_RIGHT] = prev == TURN_LEFT
    mask[..., TURN_LEFT] = prev == TURN_RIGHT
    return mask


class ExecutorAct(TypedDict):
    """An executor step per env, as :meth:`Executor.act` returns it."""
    action: torch.Tensor  # (B,) long: FORWARD, LEFT, RIGHT or STOP
    log_prob: torch.Tensor  # (B,)
    value: torch.Tensor  # (B,)
    eli: torch.Tensor  # (B, ELI_DIM) the Executor Latent Information sent to the planner


class RGBDEncoder(nn.Module):
    """conv 8x8/4, 4x4/2, 3x3/1 (ReLU) over RGB-D, then FC + ReLU (habitat's SimpleCNN shape)."""

    def __init__(self, resolution: int, out_dim: int, channels: tuple[int, int, int] = (32, 64, 32)):
        super().__init__()
        self.resolution = resolution
        self.convs = nn.Sequential(
            layer_init(nn.Conv2d(4, channels[0], 8, stride=4)), nn.ReLU(),
            layer_init(nn.Conv2d(channels[0], channels[1], 4, stride=2)), nn.ReLU(),
            layer_init(nn.Conv2d(channels[1], channels[2], 3, stride=1)), nn.ReLU(),
            nn.Flatten(),
        )
        n_flat = _conv_out_dim(self.convs, (4, resolution, resolution))
        self.fc = nn.Sequential(layer_init(nn.Linear(n_flat, out_dim)), nn.ReLU())

    def forward(self, rgb: torch.Tensor, depth: torch.Tensor) -> torch.Tensor:
        """rgb (N, H, W, 3) uint8, depth (N, H, W, 1) float -> (N, out_dim)."""
        # One NHWC buffer, viewed as NCHW: the convolutions then run channels-last, and the
        # largest tensor of the update is written once (no divide-then-concatenate copies).
        x = torch.empty(*rgb.shape[:-1], 4, device=rgb.device)
        torch.div(rgb, 255.0, out=x[..., :3])
        x[..., 3:] = depth
        return self.fc(self.convs(x.permute(0, 3, 1, 2)))


class Executor(nn.Module):
    """Executor: RGB-D CNN -> FC (+ goal) -> GRU or SMT memory -> 128-d output, which is
    both the action embedding and the ELI -> 4-way action logits and a value.

    ``memory="gru"``: FC 512, a GRU of ``gru_hidden`` units (the trainer passes
    ``--executor-hidden``, 128), then a linear layer to the 128-d output.
    ``memory="smt"``: FC 128, SMT with ``smt_heads`` heads over up to ``smt_memory``
    tokens, then a linear layer to the 128-d output. The output goes through tanh so the
    ELI sent to the planner stays in [-1, 1].

    ``no_reversal``: the policy never undoes its previous turn within a sequence (a sub-goal,
    or the flat agents' episode): after LEFT, RIGHT has probability 0, and after RIGHT, LEFT.
    Without it greedy agents dithered LEFT, RIGHT, LEFT ... in front of obstacles until the
    time-out (docs/results.md).

    State: the memory's state flattened, then one column holding the previous action
    (:meth:`act` writes it; ``forward`` leaves 0 there, as it does not choose the action).
    """

    goal_key = "subgoal"

    def __init__(self, memory: str = "gru", resolution: int = 128, eli_dim: int = ELI_DIM,
                 smt_memory: int = 128, smt_heads: int = 8, gru_hidden: int = 512,
                 no_reversal: bool = False, stop_bias: float = 0.0):
        """``stop_bias``: a constant added to the actor's STOP bias at initialisation (the same
        in every state), which sets how long an untrained executor's turns last."""
        super().__init__()
        if memory not in ("gru", "smt"):
            raise ValueError(f"memory must be 'gru' or 'smt', got {memory!r}")
        self.memory_kind, self.resolution, self.eli_dim, self.no_reversal = memory, resolution, eli_dim, no_reversal
        emb = 512 if memory == "gru" else 128
        self.encoder = RGBDEncoder(resolution, emb)
        if memory == "gru":
            self.memory = GRUMemory(emb + 3, gru_hidden)
        else:
            self.memory = SMTMemory(emb + 3, 128, smt_heads, smt_memory)
        self._memory_shape = tuple(self.memory.initial_state(1).shape[1:])
        self.eli_head = layer_init(nn.Linear(self.memory.out_dim, eli_dim))
        # the heads also read the encoded goal vector, so that "turn towards the
        # goal" is a simple function of their input from the first update on (through the
        # memory alone, 3 goal inputs beside 512 image features are learnt too slowly).
        head_in = eli_dim + 3
        self.actor = layer_init(nn.Linear(head_in, NUM_ACTIONS), std=0.01)
        self.critic = layer_init(nn.Linear(head_in, 1), std=1.0)
        with torch.no_grad():
            self.actor.bias[STOP] += stop_bias

    @property
    def device(self) -> torch.device:
        return self.actor.weight.device

    def initial_state(self, batch: int) -> torch.Tensor:
        """(B, memory state size + 1): an empty memory and no previous action."""
        mem = self.memory.initial_state(batch, self.device)
        return torch.cat([mem.reshape(batch, -1), torch.zeros(batch, 1, device=self.device)], dim=1)

    def split_state(self, state: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(the memory's state, a view of ``state``; the previous action (B,) long)."""
        return state[:, :-1].view(state.shape[0], *self._memory_shape), state[:, -1].long()

    def _bar_reversals(self, logits: torch.Tensor, prev: torch.Tensor, starts: torch.Tensor) -> torch.Tensor:
        if not self.no_reversal:
            return logits
        prev = prev.masked_fill(starts, STOP)  # a new sequence has no previous action
        return logits.masked_fill(reversal_mask(prev), MASKED_LOGIT)

    def _inputs(self, obs: dict) -> tuple[torch.Tensor, torch.Tensor]:
        """Any leading dims (...) -> memory input (..., emb + 3) and encoded goal (..., 3)."""
        dev = self.device
        rgb = as_tensor(obs["rgb"], dev)
        depth = as_tensor(obs["depth"], dev, torch.float32)
        goal = encode_polar(as_tensor(obs[self.goal_key], dev, torch.float32))
        lead = rgb.shape[:-3]
        feat = self.encoder(rgb.reshape(-1, *rgb.shape[-3:]), depth.reshape(-1, *depth.shape[-3:]))
        return torch.cat([feat.view(*lead, -1), goal], dim=-1), goal

    def _heads(self, out: torch.Tensor, goal: torch.Tensor):
        eli = torch.tanh(self.eli_head(out))
        h = torch.cat([eli, goal], dim=-1)
        return self.actor(h), self.critic(h).squeeze(-1), eli

    def forward(self, obs: dict, state: torch.Tensor, starts):
        """One step for a batch: (logits (B, 4), value (B,), eli (B, 128), new state)."""
        starts = as_tensor(starts, self.device, torch.bool)
        x, goal = self._inputs(obs)
        mem, prev = self.split_state(state)
        out, mem = self.memory.step(x, mem, starts)
        logits, value, eli = self._heads(out, goal)
        state = torch.cat([mem.reshape(mem.shape[0], -1), torch.zeros_like(state[:, -1:])], dim=1)
        return self._bar_reversals(logits, prev, starts), value, eli, state

    @torch.no_grad()
    def act(self, obs: dict, state: torch.Tensor, starts, deterministic: bool = False) -> tuple[ExecutorAct, torch.Tensor]:
        """Rollout step: (:class:`ExecutorAct`, new memory state)."""
        logits, value, eli, state = self(obs, state, starts)
        dist = Categorical(logits=logits)
        action = logits.argmax(-1) if deterministic else dist.sample()
        state[:, -1] = action
        return ExecutorAct(action=action, log_prob=dist.log_prob(action), value=value, eli=eli), state

    def evaluate_sequences(self, obs_seq: dict, actions: torch.Tensor, starts: torch.Tensor,
                           initial_state: torch.Tensor):
        """Training pass over (T, B) sequences whose memory is ``initial_state`` before step 0
        and is cleared where ``starts``: (log_prob, entropy, value), each (T, B)."""
        starts = as_tensor(starts, self.device, torch.bool)
        actions = as_tensor(actions, self.device).long()
        x, goal = self._inputs(obs_seq)
        mem, prev = self.split_state(initial_state)
        out = self.memory.sequence(x, mem, starts)
        logits, value, _ = self._heads(out, goal)
        logits = self._bar_reversals(logits, torch.cat([prev[None], actions[:-1]]), starts)
        dist = Categorical(logits=logits)
        return dist.log_prob(actions), dist.entropy(), value

    def example_obs(self, batch: int = 1, generator: torch.Generator | None = None) -> dict:
        r = self.resolution
        return {"rgb": torch.randint(0, 256, (batch, r, r, 3), dtype=torch.uint8, generator=generator),
                "depth": torch.rand(batch, r, r, 1, generator=generator),
                self.goal_key: torch.rand(batch, 2, generator=generator) * torch.tensor([5.0, 2 * math.pi]) - torch.tensor([0.0, math.pi])}
