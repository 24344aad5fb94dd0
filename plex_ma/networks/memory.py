"""The recurrent policies' memories: a GRU (:class:`GRUMemory`) and a scene-memory
transformer (:class:`SMTMemory`, over :class:`MultiHeadAttention`). Each keeps one state
tensor whose first dimension is the batch, and has ``step`` (one step) and ``sequence``
(a whole sequence in one call, the memory cleared where ``starts``)."""

from __future__ import annotations

import math

import torch
from torch import nn
from torch.nn import functional as F

from plex_ma.networks.common import layer_init


class GRUMemory(nn.Module):
    """GRU memory. State: (B, hidden)."""

    def __init__(self, in_dim: int, hidden: int = 512):
        super().__init__()
        self.hidden = hidden
        self.out_dim = hidden
        self.gru = nn.GRU(in_dim, hidden)
        for name, p in self.gru.named_parameters():
            if "weight" in name:
                nn.init.orthogonal_(p, 1.0)
            else:
                nn.init.constant_(p, 0.0)

    def initial_state(self, batch: int, device=None) -> torch.Tensor:
        return torch.zeros(batch, self.hidden, device=device)

    def step(self, x: torch.Tensor, state: torch.Tensor, starts: torch.Tensor):
        h = state * (~starts).unsqueeze(-1)
        out, h = self.gru(x.unsqueeze(0), h.unsqueeze(0))
        return out[0], h[0]

    def sequence(self, x: torch.Tensor, state: torch.Tensor, starts: torch.Tensor) -> torch.Tensor:
        """x (T, B, D), starts (T, B) -> (T, B, hidden): the same GRU as :meth:`step`, with
        the memory cleared where ``starts``."""
        # Memory restarts at almost every step (each sub-goal), so reset-free nn.GRU chunks
        # would be one or two steps long: project all inputs at once, recur step by step.
        g = self.gru
        gi = F.linear(x, g.weight_ih_l0, g.bias_ih_l0)
        keep = (~starts).unsqueeze(-1).to(x.dtype)
        h, outs = state, []
        for t in range(x.shape[0]):
            h = h * keep[t]
            i_r, i_z, i_n = gi[t].chunk(3, -1)
            h_r, h_z, h_n = F.linear(h, g.weight_hh_l0, g.bias_hh_l0).chunk(3, -1)
            r = torch.sigmoid(i_r + h_r)
            z = torch.sigmoid(i_z + h_z)
            n = torch.tanh(i_n + r * h_n)
            h = n + z * (h - n)
            outs.append(h)
        return torch.stack(outs)


class MultiHeadAttention(nn.Module):
    """Plain multi-head attention with a boolean mask (True = may attend).

    Written out with matmuls (not scaled_dot_product_attention) so that FLOP counting
    sees it and one step and a whole sequence use the same arithmetic.
    """

    def __init__(self, dim: int, heads: int):
        super().__init__()
        assert dim % heads == 0, "dim must be divisible by heads"
        self.heads, self.head_dim = heads, dim // heads
        self.q, self.k, self.v, self.o = (layer_init(nn.Linear(dim, dim), std=1.0) for _ in range(4))

    def forward(self, x: torch.Tensor, memory: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        """x (B, Tq, D) attends over memory (B, S, D) where mask (B, Tq, S)."""
        B, Tq, D = x.shape
        S = memory.shape[1]
        q = self.q(x).view(B, Tq, self.heads, self.head_dim).transpose(1, 2)
        k = self.k(memory).view(B, S, self.heads, self.head_dim).transpose(1, 2)
        v = self.v(memory).view(B, S, self.heads, self.head_dim).transpose(1, 2)
        scores = (q @ k.transpose(-1, -2)) / math.sqrt(self.head_dim)
        attn = scores.masked_fill(~mask.unsqueeze(1), float("-inf")).softmax(dim=-1)
        return self.o((attn @ v).transpose(1, 2).reshape(B, Tq, D))


class SMTMemory(nn.Module):
    """Scene-memory transformer (after Fang et al. 2019, without furthest-point sampling).

    Each step's input is embedded into a memory token; the current token attends with
    ``heads`` heads over the memory of the last ``capacity`` tokens of its sequence
    (itself included), followed by a feed-forward block (pre-norm residuals). One
    attention block; Fang et al.'s separate memory encoder is left out.

    State: (B, capacity, dim + 1): the stored tokens, oldest first and the newest in the
    last slot, plus a last channel that is 1 for a filled slot and 0 for an empty one.
    """

    def __init__(self, in_dim: int, dim: int = 128, heads: int = 8, capacity: int = 128):
        super().__init__()
        self.dim, self.capacity, self.out_dim = dim, capacity, dim
        self.embed = layer_init(nn.Linear(in_dim, dim), std=1.0)
        self.norm1, self.norm2, self.norm_out = nn.LayerNorm(dim), nn.LayerNorm(dim), nn.LayerNorm(dim)
        self.attn = MultiHeadAttention(dim, heads)
        self.ff = nn.Sequential(layer_init(nn.Linear(dim, 2 * dim)), nn.ReLU(), layer_init(nn.Linear(2 * dim, dim), std=1.0))

    def initial_state(self, batch: int, device=None) -> torch.Tensor:
        return torch.zeros(batch, self.capacity, self.dim + 1, device=device)

    def _block(self, x: torch.Tensor, memory: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        kv = self.norm1(memory)
        h = x + self.attn(self.norm1(x), kv, mask)
        h = h + self.ff(self.norm2(h))
        return self.norm_out(h)

    def step(self, x: torch.Tensor, state: torch.Tensor, starts: torch.Tensor):
        tok = self.embed(x)
        mem = state * (~starts).view(-1, 1, 1)  # a start empties every slot
        new = torch.cat([tok, torch.ones_like(tok[:, :1])], dim=-1)
        mem = torch.cat([mem[:, 1:], new.unsqueeze(1)], dim=1)  # drop the oldest, append
        used = self._filled_tail(mem)  # attend over the filled slots only (cheaper, same result)
        valid = used[..., self.dim] > 0.5
        out = self._block(tok.unsqueeze(1), used[..., : self.dim], valid.unsqueeze(1))
        return out[:, 0], mem

    def _filled_tail(self, mem: torch.Tensor) -> torch.Tensor:
        """The last slots of ``mem`` that hold a token in at least one env. Filled slots are
        always a suffix, and empty ones are masked out anyway."""
        n = int((mem[..., self.dim] > 0.5).sum(dim=1).max())
        return mem[:, mem.shape[1] - n:]

    def sequence(self, x: torch.Tensor, state: torch.Tensor, starts: torch.Tensor) -> torch.Tensor:
        """x (T, B, D), starts (T, B) -> (T, B, dim), all steps in one attention call."""
        T, M = x.shape[0], self.capacity
        tok = self.embed(x).transpose(0, 1)  # (B, T, dim)
        old = self._filled_tail(state)  # stored memory slots M - K .. M - 1
        K = old.shape[1]
        keys = torch.cat([old[..., : self.dim], tok], dim=1)  # (B, K + T, dim)
        # Block-causal, sliding-window mask reproducing ``step``: step t sees step s of
        # this call if both are in the same sequence (no start in (s, t]), s <= t and
        # t - s < M; it sees slot j of the stored memory (which holds step j - M) only if
        # no start happened in [0, t], the slot is filled and t - (j - M) < M, i.e. j > t.
        seg = starts.long().cumsum(0).transpose(0, 1)  # (B, T) sequence id; 0 = continues state
        t = torch.arange(T, device=x.device)
        j = torch.arange(M - K, M, device=x.device)
        causal = (t[None, :] <= t[:, None]) & (t[:, None] - t[None, :] < M)  # (T, T) [query, key]
        new_ok = (seg[:, :, None] == seg[:, None, :]) & causal
        filled = old[..., self.dim] > 0.5  # (B, K)
        mem_ok = (seg == 0)[:, :, None] & filled[:, None, :] & (j[None, :] > t[:, None])
        out = self._block(tok, keys, torch.cat([mem_ok, new_ok], dim=-1))
        return out.transpose(0, 1)
