"""TorchRL view of the batched multi-agent merge (``pip install idas-sumo[torchrl]``; imports torchrl).

``MergeTorchRLEnv`` is a ``torchrl.envs.EnvBase`` with batch size (K,) over ``MergeMarlBatch``
(env/marl_batch.py): K worlds in one SUMO, S agent slots each, in one group ``"agents"`` of shape (K, S),
as TorchRL's multi-agent envs (VMAS, PettingZoo) lay them out:

- ``("agents", "observation")`` (K, S, OBS_DIM), ``("agents", "action_mask")`` (K, S, 7) bool (read by
  ``MaskedCategorical``), ``("agents", "active")`` (K, S, 1) bool, ``("agents", "action")`` (K, S);
- ``("agents", "reward")`` and ``("agents", "done" | "terminated" | "truncated")`` (K, S, 1) per slot:
  a slot is done in the step its car ends (a car cut off by the timeout shows the observation it was cut
  off in, to bootstrap from). TorchRL then "resets" that slot: nothing happens in SUMO (the
  slot stays inactive until a car of a later wave fills it), only its done flag is cleared;
- no root ``done``: a world is an endless stream of episodes in waves, so the only done flags are the
  slots' (a root done, never set, would make TorchRL skip the slots' resets: it updates the nested
  entries only where no root ``_reset`` exists). ``reset()`` with no ``_reset`` entry (the first one)
  starts a wave.

Inactive slots carry zeros and allow only action 0: a masked policy takes no other action there, with
log-probability 0. A TorchRL loss leaves them out with ``loss.loss_mask_key = ("agents", "active")``
(examples/torchrl_mappo.py).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Binary, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from idas_sumo.env.actions import N_ACTIONS
from idas_sumo.env.config import EnvConfig
from idas_sumo.env.layout import OBS_DIM
from idas_sumo.env.marl_batch import MarlStep, MergeMarlBatch
from idas_sumo.env.scenario import Scenario, TrafficConfig
from idas_sumo.resources import DEFAULT_NET
from idas_sumo.sim.merge_detect import MergeSite
from idas_sumo.sim.netgen import MergeNet

GROUP = "agents"


class MergeTorchRLEnv(EnvBase):
    """``MergeMarlBatch`` as a batched TorchRL env (module docstring)."""

    def __init__(
        self,
        num_worlds: int = 1,
        net: MergeSite | MergeNet | str | Path = DEFAULT_NET,
        scenarios: list[Scenario] | None = None,
        traffic: TrafficConfig | None = None,
        config: EnvConfig | None = None,
        seed: int | None = None,
    ) -> None:
        super().__init__(batch_size=torch.Size([num_worlds]), device="cpu")
        self.marl = MergeMarlBatch(num_worlds, net, scenarios=scenarios, traffic=traffic, config=config)
        self._seed_value = seed
        self._last: MarlStep | None = None
        k, s = self.marl.shape
        self.group_map = {GROUP: [f"slot{i}" for i in range(s)]}
        slot = torch.Size([k, s])
        self.observation_spec = Composite(
            {
                GROUP: Composite(
                    observation=Unbounded(shape=(*slot, OBS_DIM), dtype=torch.float32),
                    action_mask=Binary(n=N_ACTIONS, shape=(*slot, N_ACTIONS), dtype=torch.bool),
                    active=Binary(n=1, shape=(*slot, 1), dtype=torch.bool),
                    shape=slot,
                )
            },
            shape=(k,),
        )
        self.action_spec = Composite(
            {GROUP: Composite(action=Categorical(n=N_ACTIONS, shape=slot, dtype=torch.int64), shape=slot)},
            shape=(k,),
        )
        self.reward_spec = Composite(
            {GROUP: Composite(reward=Unbounded(shape=(*slot, 1)), shape=slot)}, shape=(k,)
        )
        flags = {
            name: Categorical(n=2, shape=(*slot, 1), dtype=torch.bool)
            for name in ("done", "terminated", "truncated")
        }
        self.done_spec = Composite({GROUP: Composite(flags, shape=slot)}, shape=(k,))

    def _set_seed(self, seed: int | None) -> None:
        self._seed_value = seed

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs: Any) -> TensorDictBase:
        partial = tensordict is not None and any(
            key[-1] == "_reset" if isinstance(key, tuple) else key == "_reset"
            for key in tensordict.keys(True)
        )
        if not partial or self._last is None:  # the first reset (or one without _reset): a new wave
            self._last = self.marl.reset(seed=self._seed_value)
            self._seed_value = None  # later waves draw on from the same generators
        # a slot or world that ended: nothing to do in SUMO, only its done flags are cleared
        return self._tensordict(self._last, with_step=False)

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        actions = tensordict.get((GROUP, "action")).cpu().numpy().astype(np.int64)
        self._last = self.marl.step(actions)
        return self._tensordict(self._last, with_step=True)

    def _tensordict(self, state: MarlStep, with_step: bool) -> TensorDictBase:
        k, s = self.marl.shape
        slot_done = {
            "terminated": state.terminated if with_step else np.zeros((k, s), dtype=np.bool_),
            "truncated": state.truncated if with_step else np.zeros((k, s), dtype=np.bool_),
        }
        slot_done["done"] = slot_done["terminated"] | slot_done["truncated"]
        # the next observation of a car the timeout cut off is where it was cut off (its value bootstraps)
        obs = (
            np.where(slot_done["truncated"][..., None], state.final_obs, state.obs)
            if with_step
            else state.obs
        )
        agents = {
            "observation": torch.from_numpy(obs),
            "action_mask": torch.from_numpy(state.action_mask),
            "active": torch.from_numpy(state.active)[..., None],
            **{name: torch.from_numpy(v)[..., None] for name, v in slot_done.items()},
        }
        if with_step:
            agents["reward"] = torch.from_numpy(state.reward.astype(np.float32))[..., None]
        return TensorDict({GROUP: TensorDict(agents, batch_size=[k, s])}, batch_size=[k])

    def close(self, *, raise_if_closed: bool = True) -> None:
        marl = getattr(self, "marl", None)  # None: __init__ failed before it (EnvBase.__del__ closes too)
        if marl is not None:
            marl.close()
        super().close(raise_if_closed=raise_if_closed)
