"""Observation, actions, masks, rewards and the two environments (PettingZoo and Gymnasium)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from idas_sumo.env.gym_env import MergeEnv
    from idas_sumo.env.parallel import MergeParallelEnv

__all__ = ["MergeEnv", "MergeParallelEnv"]


def __getattr__(name: str) -> Any:
    # Lazy so that importing a pure module (actions, layout) does not pull in PettingZoo and SUMO.
    if name == "MergeParallelEnv":
        from idas_sumo.env.parallel import MergeParallelEnv

        return MergeParallelEnv
    if name == "MergeEnv":
        from idas_sumo.env.gym_env import MergeEnv

        return MergeEnv
    raise AttributeError(name)
