"""COMA's counterfactual baseline and advantage, and the IDAS combined policy loss."""

from __future__ import annotations

import torch

ALPHA = 0.7  # weight of ∇J1 (decentralised critic) in ∇J = α∇J1 + (1-α)∇J2 (paper Sec. IV-C)


def coma_baseline(q_values: torch.Tensor, probs: torch.Tensor) -> torch.Tensor:
    """Σ_a' π(a'|o) Q(s, (a⁻ⁿ, a')): (B, A), (B, A) -> (B,).

    Masked actions have probability 0 under the masked policy, so their (never trained) Q-values
    drop out of the sum.
    """
    if q_values.shape != probs.shape:
        raise ValueError(f"q_values {tuple(q_values.shape)} and probs {tuple(probs.shape)} differ in shape")
    return (q_values * probs).sum(dim=-1)


def coma_advantage(q_values: torch.Tensor, probs: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
    """Q(s, a) - baseline for the actions taken: (B, A), (B, A), (B,) -> (B,)."""
    q_taken = q_values.gather(-1, actions.long().unsqueeze(-1)).squeeze(-1)
    return q_taken - coma_baseline(q_values, probs)


def combined_policy_loss(
    log_probs: torch.Tensor,
    adv_v: torch.Tensor,
    adv_q: torch.Tensor | None,
    alpha: float = ALPHA,
    *,
    entropy: torch.Tensor | None = None,
    entropy_coef: float = 0.0,
) -> torch.Tensor:
    """-mean(α A1 log π + (1-α) A2 log π) - entropy_coef · mean(entropy).

    Its gradient is -(α∇J1 + (1-α)∇J2) per sample. The advantages are treated as constants
    (detached here so a caller cannot leak critic gradients into the actor). ``adv_q`` may be None
    only with α = 1 (stage 1: J1 alone).
    """
    if not 0.0 <= alpha <= 1.0:
        raise ValueError(f"alpha must lie in [0, 1], got {alpha}")
    weighted = alpha * adv_v.detach()
    if adv_q is None:
        if alpha != 1.0:
            raise ValueError("adv_q is required unless alpha == 1")
    else:
        weighted = weighted + (1.0 - alpha) * adv_q.detach()
    loss = -(weighted * log_probs).mean()
    if entropy is not None and entropy_coef != 0.0:
        loss = loss - entropy_coef * entropy.mean()
    return loss
