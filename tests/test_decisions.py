"""The planner's decision buffer: each world's chain of decisions and its GAE."""

import numpy as np
import torch

from plex_ma.trainers.decisions import DecisionBuffer

GAMMA = LAM = 0.95


def _decide(buf, count, rows, values):
    """Decisions in ``rows`` whose observation tags them 10 * world + their index in the
    world's decisions (``count`` counts them)."""
    rows = np.array(rows)
    tags = [10 * w + int(count[w]) for w in rows]
    count[rows] += 1
    k = len(rows)
    buf.decide(rows, {"x": torch.tensor(tags, dtype=torch.float32)[:, None]}, np.zeros(k, np.int64),
               torch.zeros(k, 2), torch.zeros(k), np.array(values, np.float32))


def test_chains_and_advantages_hand_computed():
    """Three worlds: world 0's chain of 3 decisions ends in done; world 1's 2 are cut with
    its third decision pending (V = 4); world 2's episode ends after its 2nd decision, and
    its 3rd is cut with its 4th pending (V = 2). Transitions close interleaved across worlds;
    the batch holds each world's chain in decision order."""
    buf = DecisionBuffer(3)
    count = np.zeros(3, int)
    none = np.zeros(3, bool)
    _decide(buf, count, [0, 1, 2], [1.0, 0.5, 3.0])
    buf.rewards(np.array([1.0, 0.0, 0.5]), none)
    _decide(buf, count, [1], [1.0])  # closes world 1's first: reward 0
    buf.rewards(np.array([0.0, 0.5, 0.5]), none)
    _decide(buf, count, [0, 2], [2.0, 1.5])  # closes world 0's first (reward 1) and world 2's (reward 1)
    buf.rewards(np.array([0.0, 0.5, 2.0]), np.array([False, False, True]))  # world 2's second: reward 2, done
    _decide(buf, count, [0, 2], [0.5, 1.0])  # closes world 0's second: reward 0
    buf.rewards(np.array([2.0, 0.0, -1.0]), np.array([True, False, False]))  # world 0's third: reward 2, done
    _decide(buf, count, [2, 1], [2.0, 4.0])  # closes world 2's third (reward -1) and world 1's second (reward 1)
    buf.rewards(np.array([0.0, 0.0, 0.5]), none)
    assert len(buf) == 8

    batch = buf.batch(GAMMA, LAM)
    g, gl = GAMMA, GAMMA * LAM
    # world 0: r = (1, 0, 2), V = (1, 2, 0.5), the last done
    w0_2 = 2.0 - 0.5  # 1.5
    w0_1 = 0.0 + g * 0.5 - 2.0 + gl * w0_2  # -1.525 + 1.35375 = -0.17125
    w0_0 = 1.0 + g * 2.0 - 1.0 + gl * w0_1  # 1.9 - 0.154553125 = 1.745446875
    # world 1: r = (0, 1), V = (0.5, 1), cut: bootstraps from its pending decision's V = 4
    w1_1 = 1.0 + g * 4.0 - 1.0  # 3.8
    w1_0 = 0.0 + g * 1.0 - 0.5 + gl * w1_1  # 0.45 + 3.4295 = 3.8795
    # world 2: r = (1, 2, -1), V = (3, 1.5, 1); done after the second; the third is cut (pending V = 2)
    w2_2 = -1.0 + g * 2.0 - 1.0  # -0.1
    w2_1 = 2.0 - 1.5  # 0.5: done, nothing flows back from the next episode
    w2_0 = 1.0 + g * 1.5 - 3.0 + gl * w2_1  # -0.575 + 0.45125 = -0.12375
    expected = torch.tensor([w0_0, w0_1, w0_2, w1_0, w1_1, w2_0, w2_1, w2_2])
    torch.testing.assert_close(expected, torch.tensor([1.745446875, -0.17125, 1.5, 3.8795, 3.8, -0.12375, 0.5, -0.1]))
    values = torch.tensor([1.0, 2.0, 0.5, 0.5, 1.0, 3.0, 1.5, 1.0])
    assert batch.obs["x"][:, 0].tolist() == [0, 1, 2, 10, 11, 20, 21, 22]
    assert torch.equal(batch.values, values)
    torch.testing.assert_close(batch.advantages, expected)
    torch.testing.assert_close(batch.returns, expected + values)
    # the batch empties the buffer; the pending decisions stay for the next one
    assert len(buf) == 0 and buf.pending.tolist() == [False, True, True]


def _reference_advantages(closed, pending, pending_value, gamma, lam):
    """The trainer's GAE loop before the decision buffer (a second loop beside compute_gae)."""
    cat = {k: np.concatenate([c[k] for c in closed]) for k in ("world", "reward", "done", "value")}
    order = np.argsort(cat["world"], kind="stable")
    world, reward, done, value = (cat[k][order] for k in ("world", "reward", "done", "value"))
    m = len(world)
    last = np.r_[world[1:] != world[:-1], True]
    nxt = np.r_[value[1:], 0.0].astype(np.float32)
    boot = np.where(pending[world], pending_value[world], 0.0)
    nxt = np.where(last, boot, nxt)
    nxt = np.where(done, 0.0, nxt)
    delta = reward + gamma * nxt - value
    adv = np.zeros(m, np.float32)
    a = 0.0
    for t in range(m - 1, -1, -1):
        a = delta[t] + (0.0 if (last[t] or done[t]) else gamma * lam * a)
        adv[t] = a
    return adv, adv + value


def test_advantages_match_the_former_loop_bit_for_bit():
    """Random chains over 5 worlds, three batches in a row (the pending decisions carry over):
    compute_gae gives the former hand-written loop's advantages and returns, bit for bit."""
    rng = np.random.default_rng(0)
    buf = DecisionBuffer(5)
    count = np.zeros(5, int)
    for _ in range(3):
        for _ in range(40):
            rows = np.flatnonzero(rng.random(5) < 0.3)
            if len(rows):
                _decide(buf, count, rows, rng.normal(size=len(rows)))
            buf.rewards(rng.normal(size=5).astype(np.float32), rng.random(5) < 0.1)
        ref = _reference_advantages(buf.closed, buf.pending.copy(), buf.value.copy(), GAMMA, LAM)
        batch = buf.batch(GAMMA, LAM)
        assert np.array_equal(batch.advantages.numpy(), ref[0]) and np.array_equal(batch.returns.numpy(), ref[1])


def test_per_step_discount_hand_computed():
    """With a per-step discount g, a decision that lasted k executor steps discounts its
    successor by g^k and its i-th step's reward by g^i; the decision's own step (the
    planner's action) does not count as a step. World 0: 3 steps then a decision, then 1
    step and a done; world 1: 1 step, cut with its next decision pending (V = 4)."""
    g = 0.9
    buf = DecisionBuffer(2, step_gamma=g)
    count = np.zeros(2, int)
    none = np.zeros(2, bool)
    _decide(buf, count, [0, 1], [1.0, 2.0])
    buf.rewards(np.array([0.5, 0.0]), none, executor_step=False)  # the decisions' own step: undiscounted, not counted
    buf.rewards(np.array([1.0, 3.0]), none)
    _decide(buf, count, [1], [4.0])  # world 1's first lasted 1 step: reward 3
    buf.rewards(np.array([1.0, 0.0]), none)
    buf.rewards(np.array([1.0, 0.0]), none)
    _decide(buf, count, [0], [2.0])  # world 0's first lasted 3 steps: reward 0.5 + 1 + g + g^2
    buf.rewards(np.array([5.0, 0.0]), np.array([True, False]))  # world 0's second: reward 5, done
    batch = buf.batch(0.123, LAM)  # the per-decision gamma is ignored
    w0_1 = 5.0 - 2.0
    w0_0 = (0.5 + 1.0 + g + g * g) + g ** 3 * 2.0 - 1.0 + g ** 3 * LAM * w0_1
    w1_0 = 3.0 + g * 4.0 - 2.0
    torch.testing.assert_close(batch.advantages, torch.tensor([w0_0, w0_1, w1_0]))
    assert batch.obs["x"][:, 0].tolist() == [0, 1, 10]
