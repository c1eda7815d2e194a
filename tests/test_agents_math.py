"""TD targets, GAE and λ-returns, COMA baseline/advantage and the combined loss against hand-worked numbers."""

from __future__ import annotations

import pytest
import torch

from idas_sumo.agents.coma import (
    ALPHA,
    coma_advantage,
    coma_baseline,
    combined_policy_loss,
)
from idas_sumo.agents.returns import GAMMA, lambda_targets, td_advantages, td_targets


def t(*values: float) -> torch.Tensor:
    return torch.tensor(values, dtype=torch.float64)


def test_paper_constants() -> None:
    assert GAMMA == 0.9
    assert ALPHA == 0.7


def test_td_targets_and_advantages() -> None:
    # sample 0: 1 + 0.9·2 = 2.8; sample 1 finished (done): -5, no bootstrap
    rewards, next_values, dones = t(1, -5), t(2, 3), t(0, 1)
    torch.testing.assert_close(td_targets(rewards, next_values, dones, 0.9), t(2.8, -5.0))
    # advantages: 2.8 - 2 = 0.8; -5 - 1 = -6
    torch.testing.assert_close(td_advantages(rewards, t(2, 1), next_values, dones, 0.9), t(0.8, -6.0))


def test_td_default_gamma_is_paper_value() -> None:
    # 0 + 0.9·1 = 0.9
    torch.testing.assert_close(td_targets(t(0), t(1), t(0)), t(0.9))


def test_coma_baseline_and_advantage() -> None:
    q = torch.tensor(
        [
            [1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0],
            [3.0, 0.0, 0.0, 0.0, 0.0, -1.0, 6.0],
        ],
        dtype=torch.float64,
    )
    probs = torch.tensor(
        [
            [0.5, 0.5, 0.0, 0.0, 0.0, 0.0, 0.0],
            # action 6 is masked (p = 0): its large Q of 6 must not enter the baseline
            [0.2, 0.0, 0.0, 0.0, 0.0, 0.8, 0.0],
        ],
        dtype=torch.float64,
    )
    # row 0: 0.5·1 + 0.5·2 = 1.5; row 1: 0.2·3 + 0.8·(-1) = -0.2
    torch.testing.assert_close(coma_baseline(q, probs), t(1.5, -0.2))
    # row 0 took action 1: 2 - 1.5 = 0.5; row 1 took action 5: -1 - (-0.2) = -0.8
    torch.testing.assert_close(coma_advantage(q, probs, torch.tensor([1, 5])), t(0.5, -0.8))


def test_coma_advantage_is_zero_in_expectation() -> None:
    # Σ_a π(a) (Q(a) - Σ_a' π(a') Q(a')) = 0 for any Q
    q = torch.randn(4, 7, dtype=torch.float64)
    probs = torch.softmax(torch.randn(4, 7, dtype=torch.float64), dim=1)
    expected = sum(probs[:, a] * coma_advantage(q, probs, torch.full((4,), a)) for a in range(7))
    torch.testing.assert_close(expected, torch.zeros(4, dtype=torch.float64))


def test_combined_policy_loss_alpha_07() -> None:
    log_probs = t(-1, -2).requires_grad_()
    adv_v, adv_q = t(2, -1), t(1, 3)
    # weights: 0.7·2 + 0.3·1 = 1.7 and 0.7·(-1) + 0.3·3 = 0.2
    # terms: 1.7·(-1) = -1.7 and 0.2·(-2) = -0.4; loss = -mean = 1.05
    loss = combined_policy_loss(log_probs, adv_v, adv_q, 0.7)
    torch.testing.assert_close(loss, torch.tensor(1.05, dtype=torch.float64))
    loss.backward()
    # d loss / d log π = -weight / B = [-0.85, -0.1]
    assert log_probs.grad is not None
    torch.testing.assert_close(log_probs.grad, t(-0.85, -0.1))


def test_combined_policy_loss_entropy_bonus() -> None:
    # 1.05 - 0.1·mean(1.0, 0.5) = 1.05 - 0.075 = 0.975
    loss = combined_policy_loss(t(-1, -2), t(2, -1), t(1, 3), 0.7, entropy=t(1.0, 0.5), entropy_coef=0.1)
    torch.testing.assert_close(loss, torch.tensor(0.975, dtype=torch.float64))


def test_combined_policy_loss_alpha_one_is_j1_only() -> None:
    # terms 2·(-1) = -2 and (-1)·(-2) = 2: loss 0, whatever adv_q is
    assert float(combined_policy_loss(t(-1, -2), t(2, -1), None, 1.0)) == pytest.approx(0.0)
    assert float(combined_policy_loss(t(-1, -2), t(2, -1), t(100, 100), 1.0)) == pytest.approx(0.0)


def test_combined_policy_loss_needs_adv_q_below_alpha_one() -> None:
    with pytest.raises(ValueError):
        combined_policy_loss(t(-1), t(1), None, 0.7)
    with pytest.raises(ValueError):
        combined_policy_loss(t(-1), t(1), t(1), 1.5)


def test_combined_policy_loss_does_not_backprop_into_advantages() -> None:
    adv_v = t(1.0).requires_grad_()
    adv_q = t(2.0).requires_grad_()
    combined_policy_loss(t(-1.0).requires_grad_(), adv_v, adv_q, 0.7).backward()
    assert adv_v.grad is None and adv_q.grad is None


def test_gae_against_hand_worked_values() -> None:
    from idas_sumo.agents.returns import gae_advantages

    # Two agents interleaved: rows 0, 2, 3 are agent A's steps, rows 1, 4 agent B's.
    # δ = [1, 2, 0.5, -1, 3], γ = 0.9, λ = 0.5 → γλ = 0.45.
    # A: A3 = -1; A2 = 0.5 + 0.45·(-1) = 0.05; A0 = 1 + 0.45·0.05 = 1.0225
    # B: A4 = 3;  A1 = 2 + 0.45·3 = 3.35
    delta = torch.tensor([1.0, 2.0, 0.5, -1.0, 3.0])
    next_row = torch.tensor([2, 4, 3, -1, -1])
    adv = gae_advantages(delta, next_row, gamma=0.9, lam=0.5)
    torch.testing.assert_close(adv, torch.tensor([1.0225, 3.35, 0.05, -1.0, 3.0]))
    # λ = 0 is the one-step TD error (the paper's A1).
    torch.testing.assert_close(gae_advantages(delta, next_row, gamma=0.9, lam=0.0), delta)
    with pytest.raises(ValueError, match="point forward"):
        gae_advantages(delta, torch.tensor([0, -1, -1, -1, -1]), gamma=0.9, lam=0.5)


def test_lambda_targets_hand_worked() -> None:
    # One agent, rows 0 -> 1 -> 2 (row 2 ends with done, so its one-step target is r2 alone).
    # Rewards 1, 2, 3; baseline B = 10, 20, 30; γ = 0.5.
    # One-step targets y = r + γ·B(next): 1 + 10 = 11, 2 + 15 = 17, 3.
    y = torch.tensor([11.0, 17.0, 3.0])
    baseline = torch.tensor([10.0, 20.0, 30.0])
    next_row = torch.tensor([1, 2, -1])
    # λ = 0: y itself.
    torch.testing.assert_close(lambda_targets(y, baseline, next_row, 0.5, 0.0), y)
    # λ = 1: the discounted reward sums 1 + 0.5·2 + 0.25·3 = 2.75, 2 + 0.5·3 = 3.5, 3.
    torch.testing.assert_close(
        lambda_targets(y, baseline, next_row, 0.5, 1.0), torch.tensor([2.75, 3.5, 3.0])
    )
    # λ = 0.5: row 2: 3; row 1: B1 + (y1 - B1) + γλ(G2 - B2) = 20 - 3 + 0.25·(3 - 30) = 10.25;
    # row 0: 10 + 1 + 0.25·(10.25 - 20) = 8.5625.
    torch.testing.assert_close(
        lambda_targets(y, baseline, next_row, 0.5, 0.5), torch.tensor([8.5625, 10.25, 3.0])
    )
