"""The planner's decisions as PPO transitions (paper Algorithm 2).

A planner decision is one transition whose reward is everything the planner earns until its
next decision. Its successor is discounted by gamma_PL per decision, or, with a per-step
discount gamma_step, by gamma_step^k for a decision that lasted k executor steps (and the
rewards within it by gamma_step per step), as options are discounted in a semi-Markov
decision process (Sutton, Precup and Singh 1999): the planner then pays for time, not for
the number of its decisions. :class:`DecisionBuffer` keeps, per
world, the decision that waits for its reward (*pending*): its reward adds up over the
executor's turn, and it closes when the world's next decision comes (its successor's value
bootstraps it) or when the episode ends (done). :meth:`DecisionBuffer.batch` lays the
closed transitions out world by world, each world's chain in decision order, and gets their
advantages from :func:`~.ppo.compute_gae`: a chain's last transition that is not done is
cut there (a truncation) and bootstraps from the value of the world's pending decision.
"""

from __future__ import annotations

import numpy as np
import torch

from .ppo import Transitions, compute_gae


class DecisionBuffer:
    """The planner's transitions of ``num_worlds`` worlds: each world's pending decision and
    the closed transitions of this planner rollout, in the order they closed."""

    def __init__(self, num_worlds: int, step_gamma: float | None = None):
        n = num_worlds
        self.step_gamma = step_gamma  # None: the discount is per decision
        self.pending = np.zeros(n, np.bool_)
        self.reward = np.zeros(n)  # earned so far by each pending decision
        self.steps = np.zeros(n, np.int64)  # executor steps each pending decision has lasted
        self.value = np.zeros(n, np.float32)  # V of each pending decision's observation
        self.data: dict[str, torch.Tensor] | None = None  # their obs/*, stop, raw_subgoal, log_prob (made on first use)
        self.closed: list[dict] = []

    def __len__(self) -> int:
        """Closed transitions waiting for :meth:`batch`."""
        return sum(len(c["world"]) for c in self.closed)

    def decide(self, rows: np.ndarray, obs: dict, stop, raw_subgoal, log_prob, value) -> None:
        """Decisions in the worlds ``rows`` (a stop (k,), a raw sub-goal (k, 2), their log-prob
        and V(obs)): each closes the world's pending decision, not done, and becomes pending."""
        self._close(rows, done=False)
        if self.data is None:
            n = len(self.pending)
            self.data = {f"obs/{k}": torch.zeros((n,) + v.shape[1:], dtype=torch.as_tensor(v).dtype)
                         for k, v in obs.items()}
            self.data |= {"stop": torch.zeros(n, dtype=torch.long), "raw_subgoal": torch.zeros(n, 2),
                          "log_prob": torch.zeros(n)}
        idx = torch.as_tensor(rows)
        for k, v in obs.items():
            self.data[f"obs/{k}"][idx] = torch.as_tensor(v)
        self.data["stop"][idx] = torch.as_tensor(stop)
        self.data["raw_subgoal"][idx] = raw_subgoal
        self.data["log_prob"][idx] = log_prob
        self.value[rows] = np.asarray(value)
        self.reward[rows] = 0.0
        self.steps[rows] = 0
        self.pending[rows] = True

    def rewards(self, rewards: np.ndarray, ended: np.ndarray, executor_step: bool = True) -> None:
        """The planner's rewards (N,) of one env step (an executor step, or the decisions'
        own), and the worlds whose episode it ended (N,) bool: their pending decisions
        close, done."""
        p = self.pending
        scale = 1.0 if self.step_gamma is None else self.step_gamma ** self.steps[p]
        self.reward[p] += scale * rewards[p]
        if executor_step:
            self.steps[p] += 1
        self._close(np.flatnonzero(ended), done=True)

    def _close(self, rows: np.ndarray, done: bool) -> None:
        rows = rows[self.pending[rows]]
        if not len(rows):
            return
        self.closed.append({"world": rows.copy(), "reward": self.reward[rows].astype(np.float32),
                            "steps": self.steps[rows].copy(),
                            "done": np.full(len(rows), done), "value": self.value[rows].copy(),
                            **{k: v[rows].clone() for k, v in self.data.items()}})
        self.pending[rows] = False

    def batch(self, gamma: float, lam: float, device: str | torch.device = "cpu") -> Transitions:
        """The closed transitions, world by world in decision order, with GAE(``gamma``,
        ``lam``) advantages and returns (``gamma`` per decision; ignored with a per-step
        discount); they leave the buffer (the pending decisions stay)."""
        cat = {k: (torch.cat if isinstance(v, torch.Tensor) else np.concatenate)([c[k] for c in self.closed])
               for k, v in self.closed[0].items()}
        self.closed = []
        order = np.argsort(cat["world"], kind="stable")  # each world's chain, in decision order
        world, reward, done, value, steps = (cat[k][order] for k in ("world", "reward", "done", "value", "steps"))
        if self.step_gamma is not None:
            gamma = (self.step_gamma ** steps.astype(np.float64)).astype(np.float32)[:, None]
        # one (m, 1) sequence: a chain's last transition ends it, done or cut (bootstrapping
        # from the world's pending decision, or from 0 if it has none)
        cut = np.r_[world[1:] != world[:-1], True] & ~done
        boot = np.where(self.pending[world], self.value[world], 0.0)
        adv, ret = compute_gae(reward[:, None], value[:, None], done[:, None], cut[:, None], boot[:, None], gamma, lam)
        idx = torch.as_tensor(order)
        return Transitions(obs={k[4:]: v[idx].to(device) for k, v in cat.items() if k.startswith("obs/")},
                           actions={"stop": cat["stop"][idx].to(device), "raw_subgoal": cat["raw_subgoal"][idx].to(device)},
                           log_probs=cat["log_prob"][idx].to(device), values=torch.as_tensor(value, device=device),
                           advantages=adv[:, 0].to(device), returns=ret[:, 0].to(device))
