"""One-step TD targets and advantages, GAE and λ-returns (pure tensor functions).

``dones`` is 1 where the agent's episode ended by finishing or colliding at that step: nothing
follows, so no bootstrap. A timeout is not a done here: the state still has a value.
"""

from __future__ import annotations

import torch

GAMMA = 0.9  # discount per 0.2 s decision step (paper Sec. IV-C)


def td_targets(
    rewards: torch.Tensor, next_values: torch.Tensor, dones: torch.Tensor, gamma: float = GAMMA
) -> torch.Tensor:
    """y = r + γ V(o') (1 - done)."""
    return rewards + gamma * (1.0 - dones.to(rewards.dtype)) * next_values


def td_advantages(
    rewards: torch.Tensor,
    values: torch.Tensor,
    next_values: torch.Tensor,
    dones: torch.Tensor,
    gamma: float = GAMMA,
) -> torch.Tensor:
    """The TD error r + γ V(o') (1 - done) - V(o): the paper's estimate of A1 for ∇J1."""
    return td_targets(rewards, next_values, dones, gamma) - values


def gae_advantages(
    td_errors: torch.Tensor, next_row: torch.Tensor, gamma: float = GAMMA, lam: float = 0.95
) -> torch.Tensor:
    """Generalised advantage estimates A_i = δ_i + γλ·A_next(i) over agent-steps in any row order.

    ``next_row[i]`` is the row of the same agent's next step (-1 when the agent has none in the batch);
    it must point forward (``next_row[i] > i``), as rollouts record steps in time order. λ = 0 gives
    the one-step TD error back (the paper's A1); λ = 1 the discounted return minus V.
    """
    adv = td_errors.detach().clone()
    nxt = next_row.tolist()
    values = adv.tolist()
    for i in range(len(values) - 1, -1, -1):
        j = nxt[i]
        if j >= 0:
            if j <= i:
                raise ValueError(f"next_row[{i}] = {j} does not point forward")
            values[i] += gamma * lam * values[j]
    return torch.tensor(values, dtype=td_errors.dtype, device=td_errors.device)


def lambda_targets(
    one_step_targets: torch.Tensor,
    baseline: torch.Tensor,
    next_row: torch.Tensor,
    gamma: float = GAMMA,
    lam: float = 0.95,
) -> torch.Tensor:
    """λ-returns from one-step targets y_i = r_i + γ·B(next): B_i + GAE_λ(y - B), along ``next_row``.

    λ = 0 gives the one-step targets back; λ = 1 the discounted reward sum, bootstrapped only where an
    agent's rows end without ``done``.
    """
    return baseline + gae_advantages(one_step_targets - baseline, next_row, gamma, lam)
