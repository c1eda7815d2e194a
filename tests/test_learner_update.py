"""``Learner.update`` against hand-worked targets, losses and parameter steps, through the real update.

The batch is two agents over three decision steps (rows time-major: A0 B0 A1 B1 A2 B2). Agent A finishes
at its third step (done: no bootstrap); agent B is cut off by the timeout (V still bootstraps; Q has no
next joint action to bootstrap from). Expected values are worked out here with plain floats and the
paper's formulas written out (γ = 0.9, α = 0.7), never with the module's own helpers; the optimisers are
swapped for plain SGD so one step is Δθ = -lr·∇L, and the gradient clip is set out of reach.
"""

from __future__ import annotations

import copy
import dataclasses
import math
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

import pytest
import torch
from torch import nn

from idas_sumo.agents import critics
from idas_sumo.agents.checkpoint_file import load_actor
from idas_sumo.agents.learner import AdvantageScale, Batch, Learner, LearnerConfig
from idas_sumo.agents.networks import (
    STATE_DIM,
    STATE_SLOTS,
    Actor,
    CentralCritic,
    CentralCriticBase,
    ValueCritic,
)
from idas_sumo.config import from_dict
from idas_sumo.env.actions import HARD_BRAKE, N_ACTIONS, RELEASE_BRAKE
from idas_sumo.env.layout import OBS_DIM
from idas_sumo.errors import InputError

GAMMA = 0.9  # the paper's values, written out rather than imported: the test checks the defaults too
ALPHA = 0.7
LR = 0.1
NO_CLIP = 1e6  # max_grad_norm out of reach, so an SGD step is exactly -lr·∇L

# --- the batch ---------------------------------------------------------------------------------------

ROWS = 6
ALLOWED: list[set[int]] = [
    {1, 2, 3, HARD_BRAKE},
    {2, HARD_BRAKE},
    {1, 2, 3, HARD_BRAKE},
    {HARD_BRAKE, RELEASE_BRAKE},
    {0, 1, 2, HARD_BRAKE},
    {2, 3, 4, HARD_BRAKE},
]
ACTION = [2, HARD_BRAKE, 1, RELEASE_BRAKE, 0, 3]
REWARD = [0.0, -1.0, -1.0, 0.0, 12.5, 0.0]  # A: 0, -1, finish 12.5; B: -1, 0, 0
DONE = [0.0, 0.0, 0.0, 0.0, 1.0, 0.0]  # A finishes at its last row; B's last row is a timeout
JOINT_REWARD = [REWARD[2 * (i // 2)] + REWARD[2 * (i // 2) + 1] for i in range(ROWS)]  # Σ agents at t
NEXT_ROW = [2, 3, 4, 5, -1, -1]
NEXT_VALID = [1.0, 1.0, 1.0, 1.0, 0.0, 0.0]
# The action the same agent took at t+1 (rows without a next step: any value, here out of range on
# purpose, which the learner must clamp and then zero out).
NEXT_ACTION = [ACTION[j] if j >= 0 else N_ACTIONS + 3 for j in NEXT_ROW]
SLOT = [0, 1, 0, 1, 0, 1]
NEXT_SLOT = [SLOT[j] if j >= 0 else STATE_SLOTS + 5 for j in NEXT_ROW]


def make_batch(seed: int = 0) -> Batch:
    """The batch above; observations and states are random, and consistent along each agent's rows."""
    g = torch.Generator().manual_seed(seed)
    obs = torch.rand(ROWS, OBS_DIM, generator=g)
    state = torch.rand(ROWS, STATE_DIM, generator=g)
    others = (torch.rand(ROWS, STATE_SLOTS * N_ACTIONS, generator=g) < 0.1).float()
    last_obs = torch.rand(ROWS, OBS_DIM, generator=g)  # B's timeout observation (and A's, unused)
    nxt = torch.tensor(NEXT_ROW)
    has_next = nxt >= 0
    next_obs = torch.where(has_next[:, None], obs[nxt.clamp(min=0)], last_obs)
    next_state = torch.where(has_next[:, None], state[nxt.clamp(min=0)], torch.zeros_like(state))
    next_others = torch.where(has_next[:, None], others[nxt.clamp(min=0)], torch.zeros_like(others))
    mask = torch.zeros(ROWS, N_ACTIONS, dtype=torch.bool)
    for i, allowed in enumerate(ALLOWED):
        mask[i, sorted(allowed)] = True
    return Batch(
        obs=obs,
        mask=mask,
        action=torch.tensor(ACTION),
        reward=torch.tensor(REWARD),
        next_obs=next_obs,
        done=torch.tensor(DONE),
        state=state,
        others_actions=others,
        slot=torch.tensor(SLOT),
        joint_reward=torch.tensor(JOINT_REWARD),
        next_state=next_state,
        next_others_actions=next_others,
        next_slot=torch.tensor(NEXT_SLOT),
        next_action=torch.tensor(NEXT_ACTION),
        next_valid=torch.tensor(NEXT_VALID),
        next_row=nxt,
    )


def sgd_learner(central: bool, gae_lambda: float = 0.0, q_lambda: float = 0.0) -> Learner:
    """Otherwise the default (paper) config; plain SGD instead of Adam."""
    config = LearnerConfig(
        use_central_critic=central, gae_lambda=gae_lambda, q_lambda=q_lambda, max_grad_norm=NO_CLIP
    )
    learner = Learner(config, seed=3)
    learner.opt_actor = torch.optim.SGD(learner.actor.parameters(), lr=LR)
    learner.opt_value = torch.optim.SGD(learner.value.parameters(), lr=LR)
    learner.opt_central = torch.optim.SGD(learner.central.parameters(), lr=LR)
    return learner


# --- networks with known outputs ---------------------------------------------------------------------

V_ONLINE = 2.0  # V(o) for every o
V_TARGET = 1.0  # V̂(o) for every o: differs, so the test sees which one each formula used
Q_ONLINE = [0.5, 1.0, -1.0, 2.0, 0.0, -3.0, 4.0]  # Q(s, a) for every s
Q_TARGET = [1.0, 0.5, 0.0, -2.0, 1.5, -1.0, 3.0]  # Q̂(s, a) for every s


def pin_head(head: nn.Linear, bias: list[float]) -> None:
    """Zero weight, given bias: the network then outputs ``bias`` whatever its input."""
    with torch.no_grad():
        head.weight.zero_()
        head.bias.copy_(torch.tensor(bias))


def pinned_learner(central: bool, gae_lambda: float = 0.0, q_lambda: float = 0.0) -> Learner:
    """Critics with constant outputs and a uniform policy over each row's allowed actions."""
    learner = sgd_learner(central, gae_lambda, q_lambda)
    pin_head(learner.value.head, [V_ONLINE])
    pin_head(learner.value_target.head, [V_TARGET])
    pin_head(learner.central.head, Q_ONLINE)
    pin_head(learner.central_target.head, Q_TARGET)
    pin_head(learner.actor.head, [0.0] * N_ACTIONS)
    return learner


def pi(i: int, a: int) -> float:
    """The pinned policy: uniform over row i's allowed actions."""
    return 1.0 / len(ALLOWED[i]) if a in ALLOWED[i] else 0.0


def floats(t: torch.Tensor) -> list[float]:
    return [float(x) for x in t.detach().reshape(-1)]


def approx(values: list[float]) -> object:
    return pytest.approx(values, rel=1e-5, abs=1e-5)


# --- the paper's path with hand-known networks -------------------------------------------------------


@pytest.mark.parametrize("central", [True, False], ids=["stage2", "stage1"])
def test_update_hand_worked_targets_losses_and_sgd_steps(central: bool) -> None:
    learner = pinned_learner(central)
    q_head_before = copy.deepcopy(learner.central.head)
    stats = learner.update(make_batch())
    record = learner.last_update
    assert record is not None

    # V: regressed to y = r + γ·V̂(o')·(1 - done), V̂ the target network.
    v_target = [REWARD[i] + GAMMA * V_TARGET * (1.0 - DONE[i]) for i in range(ROWS)]
    assert v_target == approx([0.9, -0.1, -0.1, 0.9, 12.5, 0.9])  # done row 4 has no bootstrap
    assert floats(record.value.target) == approx(v_target)
    assert floats(record.value.prediction) == approx([V_ONLINE] * ROWS)
    v_loss = 0.5 * sum((y - V_ONLINE) ** 2 for y in v_target) / ROWS
    assert v_loss == pytest.approx(10.225)
    assert stats["v_loss"] == pytest.approx(v_loss, rel=1e-6)
    # A1 = r + γ·V(o')·(1 - done) - V(o): the online critic on both ends.
    adv_v = [REWARD[i] + GAMMA * V_ONLINE * (1.0 - DONE[i]) - V_ONLINE for i in range(ROWS)]
    assert adv_v == approx([-0.2, -1.2, -1.2, -0.2, 10.5, -0.2])
    assert floats(record.value.advantage) == approx(adv_v)
    assert stats["adv_v_mean"] == pytest.approx(sum(adv_v) / ROWS, rel=1e-6)

    # Q: regressed to y = R + γ·Q̂(s', a')·(1 - done), a' the action taken at t+1 (SARSA); no bootstrap
    # where the batch holds no next step.
    q_target = [
        JOINT_REWARD[i] + GAMMA * (1.0 - DONE[i]) * (Q_TARGET[NEXT_ACTION[i]] if NEXT_VALID[i] else 0.0)
        for i in range(ROWS)
    ]
    assert q_target == approx([-0.55, 1.7, -0.1, -2.8, 12.5, 12.5])
    q_taken = [Q_ONLINE[ACTION[i]] for i in range(ROWS)]
    q_loss = 0.5 * sum((q_target[i] - q_taken[i]) ** 2 for i in range(ROWS)) / ROWS
    assert q_loss == pytest.approx(26.999375)
    # A2, COMA's counterfactual advantage: Q(s, a) - Σ_a' π(a'|o)·Q(s, a').
    adv_q = [q_taken[i] - sum(pi(i, a) * Q_ONLINE[a] for a in range(N_ACTIONS)) for i in range(ROWS)]
    assert adv_q == approx([-0.75, -1.0, 1.25, 3.5, 1.125, 2.5])
    if central:
        assert record.central is not None
        assert floats(record.central.target) == approx(q_target)
        assert floats(record.central.prediction) == approx(q_taken)
        assert floats(record.central.advantage) == approx(adv_q)
        assert stats["q_loss"] == pytest.approx(q_loss, rel=1e-6)
        assert stats["adv_q_mean"] == pytest.approx(sum(adv_q) / ROWS, rel=1e-6)
        assert stats["q_mean"] == pytest.approx(sum(q_taken) / ROWS, rel=1e-6)
    else:
        assert record.central is None
        assert (stats["q_loss"], stats["adv_q_mean"], stats["q_mean"]) == (0.0, 0.0, 0.0)

    # Actor: L = -mean((α·A1 + (1-α)·A2)·log π(a|o)); α is 1 in stage 1 (no Q).
    alpha = ALPHA if central else 1.0
    weight = [alpha * adv_v[i] + (1.0 - alpha) * (adv_q[i] if central else 0.0) for i in range(ROWS)]
    log_pi = [math.log(pi(i, ACTION[i])) for i in range(ROWS)]
    actor_loss = -sum(weight[i] * log_pi[i] for i in range(ROWS)) / ROWS
    assert stats["actor_loss"] == pytest.approx(actor_loss, rel=1e-6)
    assert stats["entropy"] == pytest.approx(sum(math.log(len(s)) for s in ALLOWED) / ROWS, rel=1e-6)

    # One SGD step on each head bias, with ∂L/∂bias written out:
    # V: ∂/∂b 0.5·mean((y - b)²) = mean(b - y).
    v_bias = V_ONLINE - LR * sum(V_ONLINE - y for y in v_target) / ROWS
    assert floats(learner.value.head.bias) == approx([v_bias])
    # Q: ∂/∂b_a = mean over rows that took a of (Q(s, a) - y).
    q_bias = [
        Q_ONLINE[a] - LR * sum(q_taken[i] - q_target[i] for i in range(ROWS) if ACTION[i] == a) / ROWS
        for a in range(N_ACTIONS)
    ]
    assert floats(learner.central.head.bias) == approx(q_bias if central else Q_ONLINE)
    if not central:
        assert torch.equal(learner.central.head.weight, q_head_before.weight)
    # Actor: ∂(-w·log π(a))/∂logit_j = -w·(1[j = a] - π(j)); masked logits get no gradient.
    actor_bias = [
        LR * sum(weight[i] * ((1.0 if j == ACTION[i] else 0.0) - pi(i, j)) for i in range(ROWS)) / ROWS
        for j in range(N_ACTIONS)
    ]
    assert floats(learner.actor.head.bias) == approx(actor_bias)

    # Targets follow by τ = 0.01 after the step: V̂ ← 0.99·V̂ + 0.01·V.
    assert floats(learner.value_target.head.bias) == approx([0.99 * V_TARGET + 0.01 * v_bias])
    expected_q_hat = (
        [0.99 * qt + 0.01 * qb for qt, qb in zip(Q_TARGET, q_bias, strict=True)] if central else Q_TARGET
    )
    assert floats(learner.central_target.head.bias) == approx(expected_q_hat)


@pytest.mark.parametrize("q_lambda", [0.0, 0.8])
def test_return_advantage_puts_qs_target_in_place_of_q_hand_worked(q_lambda: float) -> None:
    """``central_advantage = "return"`` (ours): A2 = Q's target for the row - Σ_a' π(a'|o)·Q(s, a'), COMA's
    baseline kept; Q's own step and A1 are untouched, and the actor is stepped with that A2."""
    steps = {}
    for kind in ("q", "return"):
        learner = pinned_learner(True, q_lambda=q_lambda)
        learner.config = dataclasses.replace(learner.config, central_advantage=kind)
        stats = learner.update(make_batch())
        assert learner.last_update is not None and learner.last_update.central is not None
        steps[kind] = (learner.last_update, stats, floats(learner.actor.head.bias))
    paper, ours = steps["q"][0], steps["return"][0]
    assert ours.central is not None and paper.central is not None
    assert floats(ours.central.target) == approx(floats(paper.central.target))  # Q learns the same
    assert floats(ours.value.advantage) == approx(floats(paper.value.advantage))
    baseline = [sum(pi(i, a) * Q_ONLINE[a] for a in range(N_ACTIONS)) for i in range(ROWS)]
    target = floats(paper.central.target)
    adv_q = [target[i] - baseline[i] for i in range(ROWS)]
    if q_lambda == 0.0:
        # Row 0: y = R 0 + 0.9·Q̂(s', 1) = -0.55; baseline (Q 1 + Q 2 + Q 3 + Q 5) / 4 = -0.25: A2 = -0.3.
        assert adv_q == approx([-0.3, 3.7, 0.15, -3.3, 13.125, 13.0])
    assert floats(ours.central.advantage) == approx(adv_q)
    # The actor's head bias after one SGD step, with the weight α·A1 + (1-α)·A2 per row.
    adv_v = floats(ours.value.advantage)
    weight = [ALPHA * adv_v[i] + (1.0 - ALPHA) * adv_q[i] for i in range(ROWS)]
    actor_bias = [
        LR * sum(weight[i] * ((1.0 if j == ACTION[i] else 0.0) - pi(i, j)) for i in range(ROWS)) / ROWS
        for j in range(N_ACTIONS)
    ]
    assert steps["return"][2] == approx(actor_bias)
    assert steps["return"][2] != approx(steps["q"][2])


def test_lambda_targets_hand_worked() -> None:
    """q_lambda > 0 (and gae_lambda > 0): λ-returns G = r + γ·((1-λ)·bootstrap + λ·G_next) per agent."""
    lam_v, lam_q = 0.5, 0.8
    learner = pinned_learner(True, gae_lambda=lam_v, q_lambda=lam_q)
    learner.update(make_batch())
    record = learner.last_update
    assert record is not None and record.central is not None

    # Each agent's rows from last to first; an agent's last row bootstraps one step, or not at all.
    g_v = [0.0] * ROWS
    g_q = [0.0] * ROWS
    for i in reversed(range(ROWS)):
        j = NEXT_ROW[i]
        if j < 0:
            # V's λ-return uses the online V (GAE's baseline), not V̂.
            g_v[i] = REWARD[i] + GAMMA * (1.0 - DONE[i]) * V_ONLINE
            g_q[i] = JOINT_REWARD[i]  # no next joint action in the batch: nothing to bootstrap from
        else:
            g_v[i] = REWARD[i] + GAMMA * ((1.0 - lam_v) * V_ONLINE + lam_v * g_v[j])
            g_q[i] = JOINT_REWARD[i] + GAMMA * ((1.0 - lam_q) * Q_TARGET[ACTION[j]] + lam_q * g_q[j])
    # Agent A: G4 = 12.5; G2 = -1 + 0.9·(0.5·2 + 0.5·12.5) = 5.525; G0 = 0 + 0.9·(1 + 0.5·5.525) = 3.38625.
    assert [g_v[4], g_v[2], g_v[0]] == approx([12.5, 5.525, 3.38625])
    # Agent A's Q: G4 = 12.5; G2 = -1 + 0.9·(0.2·Q̂[0] + 0.8·12.5) = 8.18; G0 = -1 + 0.9·(0.2·Q̂[1] + 0.8·8.18).
    assert [g_q[4], g_q[2], g_q[0]] == approx([12.5, 8.18, -1 + 0.9 * (0.2 * 0.5 + 0.8 * 8.18)])
    assert floats(record.value.target) == approx(g_v)
    assert floats(record.value.advantage) == approx([g - V_ONLINE for g in g_v])
    assert floats(record.central.target) == approx(g_q)


# Agent A finishes at step 1 (row 2) while B drives on to step 2 (row 4): rows A0 B0 A1 B1 B2.
LEFT_ACTION = [2, 1, 3, 2, 4]
LEFT_JOINT = [0.0, 0.0, 12.5, -5.0, 12.5]  # A's finish at step 1; an impede, then B's finish later
LEFT_NEXT_ROW = [2, 3, -1, 4, -1]
LEFT_TEAM_ROW = [2, 2, 4, 4, -1]  # the first row of the episode's next step
LEFT_DONE = [0.0, 0.0, 1.0, 0.0, 1.0]


def left_early_batch() -> Batch:
    g = torch.Generator().manual_seed(5)
    n = len(LEFT_ACTION)
    nxt = torch.tensor(LEFT_NEXT_ROW)
    has = nxt >= 0
    state = torch.rand(n, STATE_DIM, generator=g)
    others = torch.zeros(n, STATE_SLOTS * N_ACTIONS)
    slot = torch.tensor([0, 1, 0, 1, 1])
    action = torch.tensor(LEFT_ACTION)
    return Batch(
        obs=torch.rand(n, OBS_DIM, generator=g),
        mask=torch.ones(n, N_ACTIONS, dtype=torch.bool),
        action=action,
        reward=torch.zeros(n),
        next_obs=None,
        done=torch.tensor(LEFT_DONE),
        state=state,
        others_actions=others,
        slot=slot,
        joint_reward=torch.tensor(LEFT_JOINT),
        next_state=torch.where(has[:, None], state[nxt.clamp(min=0)], torch.zeros_like(state)),
        next_others_actions=others.clone(),
        next_slot=torch.where(has, slot[nxt.clamp(min=0)], 0),
        next_action=torch.where(has, action[nxt.clamp(min=0)], 0),
        next_valid=has.float(),
        next_row=nxt,
        bootstrap_obs=torch.zeros(0, OBS_DIM),
        team_next_row=torch.tensor(LEFT_TEAM_ROW),
    )


@pytest.mark.parametrize("q_lambda", [0.0, 0.8])
def test_q_sums_the_joint_reward_to_the_episodes_end_after_its_agent_left(q_lambda: float) -> None:
    """The paper's Q (L160) is the joint return to the episode's end: when A has finished, its last row's
    target goes on with the episode's next step (B's row), not with nothing. The 'agent' horizon (every
    shipped policy's) stops there; it is kept as an option."""
    targets = {}
    for horizon in ("episode", "agent"):
        learner = pinned_learner(True, q_lambda=q_lambda)
        learner.config = dataclasses.replace(learner.config, q_horizon=horizon)
        learner.update(left_early_batch())
        assert learner.last_update is not None and learner.last_update.central is not None
        targets[horizon] = floats(learner.last_update.central.target)
    lam = q_lambda

    def returns(links: list[int]) -> list[float]:
        g = [0.0] * len(links)
        for i in reversed(range(len(links))):
            j = links[i]
            tail = 0.0 if j < 0 else (1 - lam) * Q_TARGET[LEFT_ACTION[j]] + lam * g[j]
            g[i] = LEFT_JOINT[i] + GAMMA * tail
        return g

    episode_links = [j if j >= 0 else t for j, t in zip(LEFT_NEXT_ROW, LEFT_TEAM_ROW, strict=True)]
    assert targets["episode"] == approx(returns(episode_links))
    assert targets["agent"] == approx(returns(LEFT_NEXT_ROW))
    # A's last row: 12.5 + 0.9·Q̂(s2, B's action 4) = 12.5 + 0.9·1.5 at λ = 0, against 12.5 alone.
    if lam == 0.0:
        assert targets["episode"][2] == pytest.approx(12.5 + GAMMA * Q_TARGET[4])
    assert targets["agent"][2] == pytest.approx(12.5)


# --- the paper's path with networks at their initial weights -----------------------------------------


Net = TypeVar("Net", bound=nn.Module)


def sgd_step_of(net: Net, loss_of: Callable[[Net], torch.Tensor]) -> list[torch.Tensor]:
    """The parameters one SGD step on ``loss_of(copy of net)`` would give."""
    twin = copy.deepcopy(net)
    loss = loss_of(twin)
    grads = torch.autograd.grad(loss, list(twin.parameters()), allow_unused=True)
    return [
        p.detach() - LR * (torch.zeros_like(p) if g is None else g)
        for p, g in zip(twin.parameters(), grads, strict=True)
    ]


def assert_params(net: nn.Module, expected: list[torch.Tensor]) -> None:
    for p, e in zip(net.parameters(), expected, strict=True):
        torch.testing.assert_close(p.detach(), e, rtol=1e-5, atol=1e-6)


def test_update_follows_the_hand_worked_losses_at_initial_weights() -> None:
    """The same formulas on the real networks' outputs; every parameter moves by -lr·∇(that loss)."""
    learner = sgd_learner(True)
    batch = make_batch(seed=1)
    state, others, slot = batch.state, batch.others_actions, batch.slot
    next_state, next_others, next_slot = batch.next_state, batch.next_others_actions, batch.next_slot
    assert state is not None and others is not None and slot is not None
    assert next_state is not None and next_others is not None and next_slot is not None
    with torch.no_grad():
        v = floats(learner.value(batch.obs))
        v_next = floats(learner.value(batch.next_obs))
        v_hat_next = floats(learner.value_target(batch.next_obs))
        q = learner.central(state, others, slot).tolist()
        # Q̂(s', a') only where there is a next step; the other rows' slot and action are meaningless.
        q_hat_next = [0.0] * ROWS
        for i in range(ROWS):
            if NEXT_VALID[i]:
                row = slice(i, i + 1)
                q_hat = learner.central_target(next_state[row], next_others[row], next_slot[row])
                q_hat_next[i] = float(q_hat[0, NEXT_ACTION[i]])
        probs = torch.softmax(learner.actor.masked_logits(batch.obs, batch.mask), dim=1).tolist()

    v_target = [REWARD[i] + GAMMA * v_hat_next[i] * (1.0 - DONE[i]) for i in range(ROWS)]
    adv_v = [REWARD[i] + GAMMA * v_next[i] * (1.0 - DONE[i]) - v[i] for i in range(ROWS)]
    q_target = [JOINT_REWARD[i] + GAMMA * (1.0 - DONE[i]) * q_hat_next[i] for i in range(ROWS)]
    adv_q = [q[i][ACTION[i]] - sum(probs[i][a] * q[i][a] for a in range(N_ACTIONS)) for i in range(ROWS)]
    weight = [ALPHA * adv_v[i] + (1.0 - ALPHA) * adv_q[i] for i in range(ROWS)]
    actor_loss = -sum(weight[i] * math.log(probs[i][ACTION[i]]) for i in range(ROWS)) / ROWS

    def v_loss_of(net: ValueCritic) -> torch.Tensor:
        return 0.5 * ((torch.tensor(v_target) - net(batch.obs)) ** 2).mean()

    def q_loss_of(net: CentralCritic) -> torch.Tensor:
        q_taken = net(state, others, slot).gather(1, batch.action[:, None])[:, 0]
        return 0.5 * ((torch.tensor(q_target) - q_taken) ** 2).mean()

    def actor_loss_of(net: Actor) -> torch.Tensor:
        log_pi = torch.log_softmax(net.masked_logits(batch.obs, batch.mask), dim=1)
        return -(torch.tensor(weight) * log_pi.gather(1, batch.action[:, None])[:, 0]).mean()

    expected_value = sgd_step_of(learner.value, v_loss_of)
    expected_central = sgd_step_of(learner.central, q_loss_of)
    expected_actor = sgd_step_of(learner.actor, actor_loss_of)
    before = {name: [p.detach().clone() for p in net.parameters()] for name, net in nets(learner).items()}

    stats = learner.update(batch)
    record = learner.last_update
    assert record is not None and record.central is not None
    assert floats(record.value.target) == approx(v_target)
    assert floats(record.value.advantage) == approx(adv_v)
    assert floats(record.central.target) == approx(q_target)
    assert floats(record.central.advantage) == approx(adv_q)
    assert stats["actor_loss"] == pytest.approx(actor_loss, rel=1e-5)
    for name, expected in (
        ("value", expected_value),
        ("central", expected_central),
        ("actor", expected_actor),
    ):
        # The expected step is a real one (a zero gradient would make the comparison vacuous) ...
        assert any(not torch.allclose(e, b) for e, b in zip(expected, before[name], strict=True)), name
        # ... and the update took exactly it.
        assert_params(nets(learner)[name], expected)


def nets(learner: Learner) -> dict[str, nn.Module]:
    return {"value": learner.value, "central": learner.central, "actor": learner.actor}


@pytest.mark.parametrize("central", [False, True])
def test_next_row_reuse_gives_the_update_of_the_plain_next_observations(central: bool) -> None:
    """With ``next_row`` V(o') is read from V(o) of the next row instead of a second forward pass; the
    update (targets, advantages, new weights) must be the one computed from ``next_obs`` directly."""
    with_rows = make_batch()
    without_rows = dataclasses.replace(with_rows, next_row=None)
    learners = [sgd_learner(central) for _ in range(2)]
    for learner, batch in zip(learners, (with_rows, without_rows), strict=True):
        learner.update(batch)
    a, b = (learner.last_update for learner in learners)
    assert a is not None and b is not None
    torch.testing.assert_close(a.value.target, b.value.target)
    torch.testing.assert_close(a.value.advantage, b.value.advantage)
    for pa, pb in zip(learners[0].actor.parameters(), learners[1].actor.parameters(), strict=True):
        torch.testing.assert_close(pa, pb)


def two_episodes() -> tuple[Batch, Batch, Batch]:
    """Two episodes' batches (``make_batch`` with other draws) and their concatenation, rows linked within each."""
    first, second = make_batch(0), make_batch(1)
    shifted = dataclasses.replace(
        second, next_row=torch.where(second.next_row >= 0, second.next_row + ROWS, -1)
    )
    whole = Batch(
        **{
            f.name: None
            if (v := getattr(first, f.name)) is None
            else torch.cat([v, getattr(shifted, f.name)])
            for f in dataclasses.fields(first)
        }
    )
    return first, second, whole


@pytest.mark.parametrize("central", [False, True])
def test_parts_with_the_batchs_advantage_scale_give_the_normalised_update(central: bool) -> None:
    """``normalize_advantages`` standardises A1 and A2 over the whole batch: parts of it (a rollout worker's
    groups) finish their actor gradients with the moments of all the parts' advantages, and the weighed step is
    the whole batch's ``update`` to float rounding; each part on its own moments is another gradient."""
    first, second, whole = two_episodes()
    config = LearnerConfig(use_central_critic=central, normalize_advantages=True, max_grad_norm=NO_CLIP)
    learners = [Learner(config, seed=3) for _ in range(3)]
    learners[0].update(whole)
    pending = [learners[1].pending_part(b) for b in (first, second)]
    adv = [p.advantages for p in pending]
    scale = AdvantageScale.over(
        [v for v, _ in adv if v is not None], [q for _, q in adv if q is not None] or None
    )
    learners[1].apply_gradients([learners[1].finish_part(p, scale) for p in pending])
    learners[2].apply_gradients([learners[2].gradient_part(b) for b in (first, second)])
    whole, parts, own = ([p.grad for p in learner.actor.parameters()] for learner in learners)  # as stepped
    for a, b in zip(whole, parts, strict=True):
        assert a is not None and b is not None
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-7)
    assert any(
        not torch.allclose(a, b, rtol=1e-4, atol=1e-7)
        for a, b in zip(whole, own, strict=True)
        if a is not None
    )


def test_an_update_without_agent_steps_changes_nothing() -> None:
    """A round whose learning cars never acted (late entries, short episodes) gives an empty batch: no step,
    zero losses (Categorical on zero rows raised inside torch before)."""
    full = make_batch()
    empty = Batch(
        **{
            f.name: (None if (v := getattr(full, f.name)) is None else v[:0])
            for f in dataclasses.fields(full)
        }
    )
    learner = sgd_learner(central=True)
    before = copy.deepcopy(learner.state_dict())
    stats = learner.update(empty)
    assert set(stats) == set(learner.update(full).keys()) and all(v == 0.0 for v in stats.values())
    learner2 = sgd_learner(central=True)
    learner2.update(empty)
    for net in ("actor", "value", "central", "value_target", "central_target"):
        for name, tensor in before[net].items():
            assert torch.equal(learner2.state_dict()[net][name], tensor), f"{net}.{name} moved"


# --- the critic registry: the centralised critic by name ---------------------------------------------

Q_BIAS = [0.2, -0.4, 0.1, 0.6, -0.3, 0.5, -0.1]  # the registered test critic's Q(s, a) before its step


class BiasOnlyCritic(CentralCriticBase):
    """A registered test critic: Q(s, a) = b_a whatever the input, so its SGD step is worked out by hand."""

    def __init__(self) -> None:
        super().__init__()
        self.bias = nn.Parameter(torch.tensor(Q_BIAS))

    def forward(self, state: torch.Tensor, others_actions: torch.Tensor, slot: torch.Tensor) -> torch.Tensor:
        return self.bias.expand(state.shape[0], -1)


@pytest.fixture
def bias_only_critic(monkeypatch: pytest.MonkeyPatch) -> str:
    """``BiasOnlyCritic`` registered as "bias_only" for one test (the registry is restored after it)."""
    monkeypatch.setattr(critics, "CENTRAL_CRITICS", dict(critics.CENTRAL_CRITICS))
    critics.register_central_critic("bias_only")(BiasOnlyCritic)
    return "bias_only"


def test_the_default_critic_is_the_papers_coma_critic() -> None:
    assert LearnerConfig().central_critic == "coma"
    assert type(Learner(LearnerConfig(), seed=0).central) is CentralCritic
    with pytest.raises(InputError, match=r"'comma' is not a registered critic .*did you mean \"coma\""):
        LearnerConfig(central_critic="comma")
    with pytest.raises(ValueError, match="registered already"):
        critics.register_central_critic("coma")(CentralCritic)


def test_a_registered_critic_is_built_and_stepped_by_the_learner(bias_only_critic: str) -> None:
    """A critic registered from here is the learner's Q and its target: the update regresses it to the hand-worked
    SARSA targets R + γ·Q̂(a')·(1 - done) (Q̂ = Q before the step, no bootstrap without a next step), hands the
    actor COMA's advantage from it, and steps it by -lr·∇ 0.5·mean((y - b_a)²)."""
    config = LearnerConfig(central_critic=bias_only_critic, use_central_critic=True, max_grad_norm=NO_CLIP)
    learner = Learner(config, seed=3)
    assert isinstance(learner.central, BiasOnlyCritic) and isinstance(learner.central_target, BiasOnlyCritic)
    learner.opt_central = torch.optim.SGD(learner.central.parameters(), lr=LR)
    pin_head(learner.actor.head, [0.0] * N_ACTIONS)  # uniform over the allowed actions: pi()
    learner.update(make_batch())
    record = learner.last_update
    assert record is not None and record.central is not None

    target = [
        JOINT_REWARD[i] + GAMMA * (1.0 - DONE[i]) * (Q_BIAS[NEXT_ACTION[i]] if NEXT_VALID[i] else 0.0)
        for i in range(ROWS)
    ]
    assert target == approx([-1.36, -1.09, -0.82, -0.46, 12.5, 12.5])
    assert floats(record.central.target) == approx(target)
    assert floats(record.central.prediction) == approx([Q_BIAS[a] for a in ACTION])
    coma = [Q_BIAS[ACTION[i]] - sum(pi(i, a) * Q_BIAS[a] for a in range(N_ACTIONS)) for i in range(ROWS)]
    assert floats(record.central.advantage) == approx(coma)
    stepped = [
        Q_BIAS[a] - LR * sum(Q_BIAS[a] - target[i] for i in range(ROWS) if ACTION[i] == a) / ROWS
        for a in range(N_ACTIONS)
    ]
    assert floats(learner.central.bias) == approx(stepped)
    assert floats(learner.central.bias)[4] == pytest.approx(Q_BIAS[4])  # no row took action 4


def test_a_q_of_another_critic_is_not_loaded(bias_only_critic: str) -> None:
    """A checkpoint whose Q is another critic (a stage-1 run never trains Q) starts a learner with its actor and
    V, and leaves its Q as initialised."""
    coma = Learner(LearnerConfig(), seed=1)
    other = Learner(LearnerConfig(central_critic=bias_only_critic), seed=2)
    q_before = copy.deepcopy(other.central.state_dict())
    other.load_state_dict(coma.state_dict())
    assert all(
        torch.equal(a, b) for a, b in zip(other.actor.parameters(), coma.actor.parameters(), strict=True)
    )
    assert all(torch.equal(v, other.central.state_dict()[k]) for k, v in q_before.items())
    coma_again = Learner(LearnerConfig(), seed=3)
    q_before = copy.deepcopy(coma_again.central.state_dict())
    coma_again.load_state_dict(other.state_dict())
    assert all(torch.equal(v, coma_again.central.state_dict()[k]) for k, v in q_before.items())


def test_a_learner_saved_before_its_first_step_builds_no_optimiser_and_loads_fresh_ones() -> None:
    """Saving must not build an optimiser (the first build imports ``torch._dynamo``: a stop during that import
    left it broken, and the run's starting checkpoint was lost); a learner that loads the state gets fresh
    optimisers, as an uninterrupted run would at its first step, whatever it held before."""
    fresh = Learner(LearnerConfig(), seed=1)
    state = fresh.state_dict()
    assert [state[name] for name in ("opt_actor", "opt_value", "opt_central")] == [None, None, None]
    assert not {"_opt_actor", "_opt_value", "_opt_central"} & fresh.__dict__.keys()
    stepped = Learner(LearnerConfig(), seed=2)
    for p in stepped.actor.parameters():
        p.grad = torch.ones_like(p)
    stepped.opt_actor.step()
    assert stepped.opt_actor.state_dict()["state"]
    stepped.load_state_dict(state)
    assert stepped.opt_actor.state_dict()["state"] == {}
    assert stepped.state_dict()["opt_actor"] == Learner(LearnerConfig(), seed=3).opt_actor.state_dict()


def test_a_policy_trained_with_the_retired_state_value_head_still_acts() -> None:
    """idas_explored10_collide.pt's Q had the retired U(s) + D(s, a) head: ``load_actor`` loads its actor and V,
    and keeps this build's Q (not needed to act)."""
    root = Path(__file__).resolve().parent.parent
    found = sorted(root.glob("idas_sumo/policies/idas_explored10_collide.pt"))
    found += sorted(root.glob("experiments/**/idas_explored10_collide.pt"))
    assert found, "idas_explored10_collide.pt is in neither idas_sumo/policies/ nor experiments/"
    stored = torch.load(found[0], weights_only=True, map_location="cpu")["learner"]
    assert "value_head.weight" in stored["central"]  # the retired head: this build's Q cannot take it
    learner = load_actor(found[0])
    for name, tensor in learner.actor.state_dict().items():
        assert torch.equal(tensor, stored["actor"][name]), name
    assert "value_head.weight" not in learner.central.state_dict()
    obs = torch.rand(3, OBS_DIM, generator=torch.Generator().manual_seed(0)).numpy()
    mask = torch.ones(3, N_ACTIONS, dtype=torch.int8).numpy()
    assert learner.act(obs, mask, torch.Generator().manual_seed(1)).shape == (3,)


def test_retired_learner_switches_load_at_their_default_and_refuse_a_variant() -> None:
    """Checkpoints and recipes store the retired switches: their former defaults load, a variant is one line."""
    where = "recipe.toml: learner"
    retired = {
        "central_head": ("per_action", "state_value"),
        "central_input": ("scenario_slots", "ego_first"),
        "coma_actions": ("all", "delta_only"),
        "coma_action_means": ("keep", "subtract"),
        "central_action_rows": ("all", "explored"),
    }
    for key, (default, variant) in retired.items():
        assert from_dict(LearnerConfig, {key: default}, where) == LearnerConfig()
        with pytest.raises(InputError, match=f"{key}: '{variant}' is a retired experiment variant"):
            from_dict(LearnerConfig, {key: variant}, where)


# --- the anchor (ours, a labelled variant): KL(π ‖ π₀) in the actor loss ------------------------------

ANCHOR_COEF = 0.5
LOGITS = [0.3, -0.2, 0.8, 0.0, 1.1, -0.5, 0.4]  # the online actor's (pinned) logits after the anchor is set


def test_anchor_kl_to_a_uniform_start_is_hand_worked_through_the_update() -> None:
    """π₀ uniform over each row's allowed actions (the pinned actor when the anchor is taken), then π moved
    to softmax(LOGITS) over them: KL(π ‖ π₀) = Σ π log(π · n) per row; the actor's loss is the paper's plus
    anchor_coef · mean KL, and its SGD step is -lr·∇ of exactly that."""
    learner = pinned_learner(True)
    learner.config = dataclasses.replace(learner.config, anchor_coef=ANCHOR_COEF)
    learner.anchor_to_start()
    pin_head(learner.actor.head, LOGITS)
    batch = make_batch(seed=2)

    probs = []
    for i in range(ROWS):
        z = sum(math.exp(LOGITS[a]) for a in ALLOWED[i])
        probs.append([math.exp(LOGITS[a]) / z if a in ALLOWED[i] else 0.0 for a in range(N_ACTIONS)])
    kl = [sum(p * math.log(p * len(ALLOWED[i])) for p in probs[i] if p > 0.0) for i in range(ROWS)]
    assert all(k > 1e-3 for k in kl)  # the term is not vacuous: π has moved off π₀ in every row
    v_next = [0.0 if DONE[i] else V_ONLINE for i in range(ROWS)]
    adv_v = [REWARD[i] + GAMMA * v_next[i] - V_ONLINE for i in range(ROWS)]
    adv_q = [
        Q_ONLINE[ACTION[i]] - sum(probs[i][a] * Q_ONLINE[a] for a in range(N_ACTIONS)) for i in range(ROWS)
    ]
    weight = [ALPHA * adv_v[i] + (1.0 - ALPHA) * adv_q[i] for i in range(ROWS)]
    paper_loss = -sum(weight[i] * math.log(probs[i][ACTION[i]]) for i in range(ROWS)) / ROWS
    expected_loss = paper_loss + ANCHOR_COEF * sum(kl) / ROWS

    def actor_loss_of(net: Actor) -> torch.Tensor:
        log_pi = torch.log_softmax(net.masked_logits(batch.obs, batch.mask), dim=1)
        taken = log_pi.gather(1, batch.action[:, None])[:, 0]
        uniform = torch.tensor([math.log(1.0 / len(allowed)) for allowed in ALLOWED])
        kl_rows = (log_pi.exp() * (log_pi - uniform[:, None])).masked_fill(~batch.mask, 0.0).sum(dim=1)
        return -(torch.tensor(weight) * taken).mean() + ANCHOR_COEF * kl_rows.mean()

    expected_actor = sgd_step_of(learner.actor, actor_loss_of)
    stats = learner.update(batch)
    assert stats["actor_loss"] == pytest.approx(expected_loss, rel=1e-5)
    assert_params(learner.actor, expected_actor)
    anchor = learner.anchor
    assert anchor is not None
    assert float(anchor.head.weight.abs().sum()) == 0.0  # π₀ stayed where it was taken


def test_the_anchor_is_saved_and_loaded_only_by_an_anchored_learner() -> None:
    """A resumed anchored stage keeps its π₀; a learner without the anchor ignores one in the state."""
    config = LearnerConfig(anchor_coef=ANCHOR_COEF)
    anchored = Learner(config, seed=1)
    anchored.anchor_to_start()
    assert "anchor" not in Learner(LearnerConfig(), seed=1).state_dict()
    state = anchored.state_dict()
    resumed = Learner(config, seed=2)
    resumed.load_state_dict(state)
    assert resumed.anchor is not None
    assert all(
        torch.equal(a, b)
        for a, b in zip(resumed.anchor.parameters(), anchored.actor.parameters(), strict=True)
    )
    plain = Learner(LearnerConfig(), seed=2)
    plain.load_state_dict(state)
    assert plain.anchor is None
    with pytest.raises(RuntimeError, match="anchor_to_start"):
        Learner(config, seed=3).update(make_batch())
    with pytest.raises(InputError, match="anchor_coef"):
        LearnerConfig(anchor_coef=-0.1)
