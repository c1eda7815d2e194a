"""Discounted returns and one-step TD targets and advantages (pure tensor functions).

``dones`` is 1 where the agent's episode ended by finishing or colliding at that step: nothing
follows, so no bootstrap. A timeout is not a done here: the state still has a value.
"""

from __future__ import annotations

import torch

GAMMA = 0.9  # discount per 0.2 s decision step (paper Sec. IV-C)


def discounted_returns(
    rewards: torch.Tensor,
    dones: torch.Tensor,
    gamma: float = GAMMA,
    bootstrap: torch.Tensor | float = 0.0,
) -> torch.Tensor:
    """G_t = r_t + γ (1 - done_t) G_{t+1}, with G_T = ``bootstrap`` (the value after the last step).

    Time is axis 0; any trailing axes (e.g. agents) are carried along. A done cuts the sum, so
    several episodes may be laid end to end.
    """
    if rewards.shape != dones.shape:
        raise ValueError(f"rewards {tuple(rewards.shape)} and dones {tuple(dones.shape)} differ in shape")
    out = torch.empty_like(rewards)
    running = torch.as_tensor(bootstrap, dtype=rewards.dtype, device=rewards.device).expand(rewards.shape[1:])
    not_done = 1.0 - dones.to(rewards.dtype)
    for t in range(rewards.shape[0] - 1, -1, -1):
        running = rewards[t] + gamma * not_done[t] * running
        out[t] = running
    return out


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
