"""A learned actor (IDAS, IDAS-V, IDAS-direct) behind the engine's ``Policy`` contract (env/engine.py)."""

from __future__ import annotations

from typing import Protocol

import numpy as np
import numpy.typing as npt
import torch

from idas_sumo.env.engine import AgentBatch

IntArray = npt.NDArray[np.int64]


class Actor(Protocol):
    """What acts: ``Learner.act`` (one masked forward for all rows)."""

    def act(
        self,
        obs: npt.NDArray[np.float32],
        mask: npt.NDArray[np.int8],
        generator: torch.Generator,
        deterministic: bool = False,
    ) -> IntArray: ...


class ActorPolicy:
    """An actor driving agents: greedy (the most probable allowed action) or sampling with its own
    seeded generator; one forward pass per step for all the rows it is given, of every copy."""

    def __init__(self, actor: Actor, seed: int = 0, deterministic: bool = True) -> None:
        self.actor = actor
        self.deterministic = deterministic
        self.generator = torch.Generator().manual_seed(seed)

    def act(self, batch: AgentBatch, rows: IntArray) -> IntArray:
        obs = batch.obs
        if len(rows) != len(batch):
            obs, masks = obs[rows], batch.masks[rows]
        else:
            masks = batch.masks
        return self.actor.act(obs, masks, self.generator, deterministic=self.deterministic)


__all__ = ["Actor", "ActorPolicy"]
