"""The episode rules every environment shares (``EnvConfig``), validated once where they are built."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any, ClassVar

from idas_sumo.env.actions import DEFAULT_SAFETY_MASK, SAFETY_MASKS, SafetyMask
from idas_sumo.env.rewards import RewardConfig

DEFAULT_MAX_EPISODE_S = 60.0  # ours: timeout, not a success
MAX_EPISODE_S = 86_400.0
"""The longest episode accepted (a day of simulated time; the paper's last 60 s): bounded like every count,
so that a typo cannot ask SUMO for a time it cannot represent."""


@dataclass(frozen=True)
class EnvConfig:
    """Episode rules shared by every environment."""

    RETIRED_KEYS: ClassVar[dict[str, Any]] = {"standstill": "keeps_command"}
    """Experiment switches measured and retired (experiments/README.md): files holding the default still load."""

    max_episode_s: float = DEFAULT_MAX_EPISODE_S
    """Simulated seconds before the episode is cut off (a timeout is not a success)."""
    reward: RewardConfig = field(default_factory=RewardConfig)
    safety_mask: SafetyMask = DEFAULT_SAFETY_MASK
    """Which car the safety mask keeps a safe distance to: 'own_lane' (the paper, L219 and L233-237: the
    front car in the agent's own lane; the car on the other road is the conflict the policy must
    learn) or 'merge_aware' (ours, an optional shield: the other road's car closer to the merge point
    counts too, main road first; see ``MergeEngine.front_cars``)."""
    junction: str | None = None
    """Which merge of a net with several the episodes run on (its junction id, ``choose_merge``); None
    (or "", as a recipe writes it): the net's only one."""

    def __post_init__(self) -> None:
        if self.junction == "":
            object.__setattr__(self, "junction", None)  # frozen: the one normalisation, at the edge
        t = self.max_episode_s
        if isinstance(t, bool) or not isinstance(t, int | float) or not (0 < t <= MAX_EPISODE_S):
            raise ValueError(f"max_episode_s must be positive and at most {MAX_EPISODE_S:g} s, got {t!r}")
        if self.safety_mask not in SAFETY_MASKS:
            raise ValueError(
                f"safety_mask must be one of {', '.join(SAFETY_MASKS)}, got {self.safety_mask!r}"
            )


def with_safety_mask(config: EnvConfig | None, safety_mask: SafetyMask | None) -> EnvConfig:
    """``config`` (default: ``EnvConfig()``) with ``safety_mask`` when one is given (the environments'
    ``safety_mask=`` argument)."""
    config = config or EnvConfig()
    return config if safety_mask is None else replace(config, safety_mask=safety_mask)
