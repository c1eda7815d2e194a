"""Batched multi-agent merge: every controlled car of K worlds an agent, in fixed slots, as numpy arrays.

For MARL libraries that want tensors of a fixed shape (TorchRL, BenchMARL, JAX-style code), not agents
that come and go by name. ``MergeMarlBatch`` runs K worlds side by side in one SUMO on the episode engine
(copies = K) and hands out arrays of shape (K, S, ...): world k's slot i holds its scenario's i-th
controlled car (scenario order), S = the most controlled cars a scenario can have.

A slot is *active* while its car is on the road and acts: it has the car's observation and action mask.
Otherwise (its car has not entered yet, has ended, or the scenario has fewer cars) the slot is inactive:
zero observation, a mask that allows only action 0, reward 0, and its action is ignored. In the step a
car ends, its slot reports ``terminated`` (collided, finished, removed) or ``truncated`` (timeout) with
the reward of that step, and is already inactive in the returned state (a truncated car's observation
after that step, to bootstrap from, is in ``final_obs``).

Waves, as the vector env (env/vector_env.py): the K worlds start their episodes together (one SUMO
load), and the next K episodes start once every world's episode is over; a world whose episode ended
first waits with every slot inactive. ``step`` never returns a state in which no slot of any world acts
while the wave still runs (it lets SUMO run, as ``run_episodes`` does while cars wait to enter); the
step that ends a wave returns with every slot inactive, and the next ``step`` starts the next wave (its
actions are ignored). Episodes, rewards and outcomes are those of ``run_episodes`` on the same
scenarios (tests/test_marl_batch.py).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

from idas_sumo.env.actions import N_ACTIONS, SafetyMask
from idas_sumo.env.config import EnvConfig, with_safety_mask
from idas_sumo.env.contracts import AgentBatch
from idas_sumo.env.engine import MergeEngine
from idas_sumo.env.layout import OBS_DIM
from idas_sumo.env.outcome import EpisodeOutcome
from idas_sumo.env.scenario import Scenario, TrafficConfig, check_against_net, generate_scenario, start_room_m
from idas_sumo.errors import SimulationError
from idas_sumo.resources import DEFAULT_NET
from idas_sumo.sim.merge_detect import MergeSite
from idas_sumo.sim.netgen import MergeNet

BoolArray = npt.NDArray[np.bool_]
FloatArray = npt.NDArray[np.float64]


@dataclass
class MarlStep:
    """The state the agents act on next, and (after a step) what the step gave. Arrays (K, S, ...)."""

    obs: npt.NDArray[np.float32]
    """(K, S, OBS_DIM): each active slot's observation, zeros elsewhere."""
    action_mask: BoolArray
    """(K, S, N_ACTIONS): allowed actions; an inactive slot allows only action 0."""
    active: BoolArray
    """(K, S): the slot's car is on the road and acts in the next step."""
    reward: FloatArray
    """(K, S): each car's own reward of the step (the engine's: finish + collide + impede)."""
    terminated: BoolArray
    """(K, S): the car ended in this step by collision, finishing or leaving the road."""
    truncated: BoolArray
    """(K, S): the car was cut off by the episode's timeout in this step."""
    final_obs: npt.NDArray[np.float32]
    """(K, S, OBS_DIM): a truncated car's observation after the step it was cut off in (to bootstrap
    its value from: it is still on the road); zeros elsewhere."""
    joint_reward: FloatArray
    """(K,): each world's joint reward of the step (its cars' rewards plus the shared flow penalty)."""
    world_over: BoolArray
    """(K,): the world's episode is over (it waits for the next wave)."""
    wave: int
    """How many waves have started (1 after ``reset``)."""


def slots_for(traffic: TrafficConfig) -> int:
    """The most controlled cars a scenario drawn from ``traffic`` can have (its slot count)."""
    n = traffic.max_total
    return min(n, traffic.max_controlled) if traffic.max_controlled > 0 else n


class MergeMarlBatch:
    """K merge worlds in one SUMO, every controlled car an agent in a fixed slot (module docstring).

    ``scenarios``: the episodes to run, K per wave in order (cycled when they run out); without them,
    world k draws its scenarios from ``traffic`` with a generator seeded ``seed + k`` at ``reset``.
    """

    def __init__(
        self,
        num_worlds: int = 1,
        net: MergeSite | MergeNet | str | Path = DEFAULT_NET,
        scenarios: Sequence[Scenario] | None = None,
        traffic: TrafficConfig | None = None,
        config: EnvConfig | None = None,
        safety_mask: SafetyMask | None = None,
    ) -> None:
        self.engine = MergeEngine(net, copies=num_worlds, config=with_safety_mask(config, safety_mask))
        if self.engine.copies != num_worlds:
            self.engine.close()
            raise SimulationError(
                f"{num_worlds} worlds need one SUMO run of {num_worlds} copies, which this process cannot "
                "hold: another simulation is open in it (close that environment first) or the net cannot "
                "be copied"
            )
        self.num_worlds = num_worlds
        self.traffic = traffic or TrafficConfig()
        self.scenarios = list(scenarios) if scenarios is not None else None
        if self.scenarios is not None:
            if not self.scenarios:
                raise ValueError("scenarios is empty")
            for s in self.scenarios:
                check_against_net(s, self.engine.speed_limits_mps, start_room_m(self.engine.site), s.name)
            self.num_slots = max(len(s.controlled_ids) for s in self.scenarios)
        else:
            self.num_slots = slots_for(self.traffic)
        self._rngs = [np.random.default_rng(k) for k in range(num_worlds)]
        self._next_job = 0
        self.jobs: list[int] = []
        """Each world's episode of this wave: its index in ``scenarios`` (counting on when cycled), or
        the wave's index (from 0) with drawn scenarios."""
        self.wave = 0
        self._slot_of: list[dict[str, int]] = []
        self._batch: AgentBatch | None = None
        self._rows = np.zeros((0, 2), dtype=np.int64)
        """(world, slot) of each row of ``_batch``."""
        self.outcomes: list[list[EpisodeOutcome]] = [[] for _ in range(num_worlds)]
        """Each world's finished episodes, in order (the engine's outcome of each)."""

    @property
    def shape(self) -> tuple[int, int]:
        return self.num_worlds, self.num_slots

    # -- episodes ----------------------------------------------------------------------------------
    def reset(self, seed: int | None = None) -> MarlStep:
        """Start a wave (drawn scenarios: world k's generator seeded ``seed + k`` when ``seed`` is given;
        given scenarios: from the first again). Returns the first state in which some slot acts."""
        if seed is not None:
            self._rngs = [np.random.default_rng(seed + k) for k in range(self.num_worlds)]
        self._next_job = 0
        self.wave = 0
        self.outcomes = [[] for _ in range(self.num_worlds)]
        self._new_wave()
        return self._output(self._empty_rewards())

    def _draw(self) -> list[Scenario]:
        if self.scenarios is not None:
            picked = [
                self.scenarios[(self._next_job + k) % len(self.scenarios)] for k in range(self.num_worlds)
            ]
            self.jobs = [self._next_job + k for k in range(self.num_worlds)]
            self._next_job += self.num_worlds
            return picked
        limits = self.engine.speed_limits_mps
        self.jobs = [self.wave] * self.num_worlds
        return [
            generate_scenario(rng, self.traffic, limits, start_room_m=start_room_m(self.engine.site))
            for rng in self._rngs
        ]

    def _new_wave(self) -> None:
        scenarios = self._draw()
        for s in scenarios:
            if len(s.controlled_ids) > self.num_slots:
                raise ValueError(
                    f"scenario {s.name!r} has {len(s.controlled_ids)} controlled cars, more than the "
                    f"{self.num_slots} slots of this batch"
                )
        self._slot_of = [{vid: i for i, vid in enumerate(s.controlled_ids)} for s in scenarios]
        self.engine.reset(scenarios)
        self.wave += 1
        self._reported = np.zeros(self.num_worlds, dtype=np.bool_)
        self._observe()
        self._run_idle()

    def _release_over(self) -> None:
        """Over worlds leave SUMO (they cost nothing until the next wave); their outcomes are kept."""
        for k in range(self.num_worlds):
            if not self._reported[k] and self.engine.over(k):
                self._reported[k] = True
                self.outcomes[k].append(self.engine.outcome(k))
                self.engine.release_slot(k)

    def _observe(self) -> None:
        self._release_over()
        batch = self._batch = self.engine.observe()
        copies = batch.copy.tolist()
        self._rows = np.array(
            [(k, self._slot_of[k][a]) for a, k in zip(batch.ids, copies, strict=True)], dtype=np.int64
        ).reshape(-1, 2)

    def _run_idle(self) -> None:
        """While the wave runs but no car acts (cars still to enter), let SUMO run, as ``run_episodes``."""
        while self._batch is not None and not len(self._batch) and not self._reported.all():
            self.engine.step(np.zeros(0, dtype=np.int64))
            self._observe()

    # -- stepping ----------------------------------------------------------------------------------
    def step(self, actions: npt.ArrayLike) -> MarlStep:
        """Every active slot takes its action (K, S) (a masked one is replaced by the closest allowed
        action, as everywhere in the engine); inactive slots' actions are ignored."""
        batch = self._batch
        if batch is None:
            raise SimulationError("step() before reset(): call reset() first")
        acts = np.asarray(actions)
        if acts.shape != self.shape:
            raise ValueError(f"actions of shape {acts.shape}: expected (worlds, slots) = {self.shape}")
        if acts.dtype.kind not in "iu":
            raise ValueError(f"actions must be integers, got dtype {acts.dtype}")
        out = self._empty_rewards()
        if self._reported.all():  # the last step ended the wave: start the next
            self._new_wave()
            return self._output(out)
        k, s = self._rows[:, 0], self._rows[:, 1]
        result = self.engine.step(acts[k, s].astype(np.int64))
        reward, terminated, truncated, joint = out
        reward[k, s] = result.rewards
        reasons = np.array(result.end_reason, dtype=object)
        truncated[k, s] = reasons == "timeout"
        terminated[k, s] = (reasons != "") & (reasons != "timeout")
        joint[: len(result.joint_reward)] = result.joint_reward
        final = self._final_observations(truncated)
        self._observe()
        self._run_idle()
        return self._output(out, final)

    def _final_observations(self, truncated: BoolArray) -> npt.NDArray[np.float32]:
        """The truncated cars' observations now (before their worlds leave SUMO)."""
        final = np.zeros((*self.shape, OBS_DIM), dtype=np.float32)
        for k in np.flatnonzero(truncated.any(axis=1)).tolist():
            slots = np.flatnonzero(truncated[k])
            ids = self.engine.slots[k].scenario.controlled_ids
            final[k, slots] = self.engine.observe_agents(k, [ids[s] for s in slots.tolist()])
        return final

    def _empty_rewards(self) -> tuple[FloatArray, BoolArray, BoolArray, FloatArray]:
        shape = self.shape
        return (
            np.zeros(shape),
            np.zeros(shape, dtype=np.bool_),
            np.zeros(shape, dtype=np.bool_),
            np.zeros(self.num_worlds),
        )

    def _output(
        self,
        step: tuple[FloatArray, BoolArray, BoolArray, FloatArray],
        final: npt.NDArray[np.float32] | None = None,
    ) -> MarlStep:
        batch = self._batch
        assert batch is not None
        obs = np.zeros((*self.shape, OBS_DIM), dtype=np.float32)
        mask = np.zeros((*self.shape, N_ACTIONS), dtype=np.bool_)
        mask[:, :, 0] = True
        active = np.zeros(self.shape, dtype=np.bool_)
        if len(batch):
            k, s = self._rows[:, 0], self._rows[:, 1]
            obs[k, s] = batch.obs
            mask[k, s] = batch.masks.astype(bool)
            active[k, s] = True
        reward, terminated, truncated, joint = step
        return MarlStep(
            obs=obs,
            action_mask=mask,
            active=active,
            reward=reward,
            terminated=terminated,
            truncated=truncated,
            final_obs=final if final is not None else np.zeros_like(obs),
            joint_reward=joint,
            world_over=self._reported.copy(),
            wave=self.wave,
        )

    def close(self) -> None:
        self.engine.close()
