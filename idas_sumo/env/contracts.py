"""What the engine and the policies exchange: the batch of agents a step acts on, the policy contract, a step's result."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np
import numpy.typing as npt

from idas_sumo.env.actions import N_ACTIONS
from idas_sumo.env.layout import OBS_DIM, RELATIVE_SPEED_SCALE_MPS
from idas_sumo.env.lazy import lazy
from idas_sumo.env.observation import build_observations_checked, speed_spread
from idas_sumo.env.rewards import REWARD_PART_NAMES
from idas_sumo.env.snapshot import TrafficSnapshot
from idas_sumo.errors import SimulationError

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

_FLOAT32_SAFE = 3e38
"""Below float32's largest value (3.4e38) with room for rounding: a relative speed under it stays finite."""


@dataclass
class AgentBatch:
    """Every active agent of every copy at one step (row i: agent ``ids[i]`` of copy ``copy[i]``)."""

    ids: tuple[str, ...]
    """Copy-local agent ids (the same id may appear in several copies)."""
    copy: IntArray
    egos: IntArray
    """Each agent's row in ``snapshot``."""
    prev_accel: FloatArray
    """The acceleration each agent drives with (m/s²)."""
    masks: npt.NDArray[np.int8]
    """(n, N_ACTIONS) allowed actions."""
    snapshot: TrafficSnapshot
    """Every vehicle of every copy (copy-aware)."""
    b_prio: FloatArray
    b_type: FloatArray
    time_s: float
    job: IntArray | None = None
    """Each agent's job (its scenario's index in ``run_episodes``), set by the episode loop."""

    def __len__(self) -> int:
        return len(self.ids)

    @lazy
    def obs(self) -> npt.NDArray[np.float32]:
        """(n, OBS_DIM) observations, built on first use (rule-based policies never need them)."""
        return self._build_obs(None)

    def obs_of(self, rows: IntArray) -> npt.NDArray[np.float32]:
        """The observations of these rows only (a new array): ``obs[rows]``, built for them alone unless
        every row's is built already (a single-ego env among other agents needs one of N)."""
        if "obs" in self.__dict__:
            return self.obs[rows]
        return self._build_obs(rows)

    def all_obs(self) -> npt.NDArray[np.float32]:
        """Every row's observation in a new array that the batch does not keep (``obs`` keeps its own)."""
        return self._build_obs(None)

    def obs_row(self, row: int) -> npt.NDArray[np.float32]:
        """Row ``row``'s observation (a new array): ``obs_of`` for one row, its inputs taken as views."""
        if "obs" in self.__dict__:
            return self.obs[row].copy()
        return self._build_obs(slice(row, row + 1))[0]

    def _build_obs(self, rows: IntArray | slice | None) -> npt.NDArray[np.float32]:
        """The observations of ``rows`` (None: every row), checked finite."""
        if not len(self.ids) or (isinstance(rows, np.ndarray) and not len(rows)):
            return np.zeros((0, OBS_DIM), dtype=np.float32)
        sel = slice(None) if rows is None else rows  # a slice takes views: every row costs no copy
        obs, scalars_finite = build_observations_checked(
            self.snapshot, self.egos[sel], self.prev_accel[sel], self.b_prio[sel], self.b_type[sel]
        )
        # (np.ptp's value, in one compiled pass)
        self._check_finite(obs, rows, scalars_finite, speed_spread(self.snapshot.speed_mps))
        return obs

    def keep_obs(self, obs: npt.NDArray[np.float32], scalars_finite: bool, spread: float) -> None:
        """Every row's observations, built by the caller as ``obs`` builds them (the engine's one-call
        observe of a single world, ``observe_own_lane_obs``), checked and kept as ``obs``."""
        self._check_finite(obs, None, scalars_finite, spread)
        self.__dict__["obs"] = obs

    def _check_finite(
        self,
        obs: npt.NDArray[np.float32],
        rows: IntArray | slice | None,
        scalars_finite: bool,
        spread: float,
    ) -> None:
        """A SimulationError naming the first agent whose observation is not finite."""
        # The grids hold 1s and relative speeds, finite whenever the speeds' spread is: only when the
        # scalars or the speeds are not is every entry tested.
        if not (scalars_finite and spread / RELATIVE_SPEED_SCALE_MPS < _FLOAT32_SAFE):
            finite = np.isfinite(obs).all(axis=1)
            if not finite.all():
                bad_row = int(np.argmin(finite))
                bad = self.ids[bad_row if rows is None else int(np.arange(len(self.ids))[rows][bad_row])]
                raise SimulationError(
                    f"non-finite observation for agent {bad!r} at t = {self.time_s:.1f} s (a bug)"
                )

    @lazy
    def copy_runs(self) -> list[tuple[int, int, int]]:
        """(copy, lo, hi): the rows of each copy's agents (a batch comes copy by copy)."""
        return _copy_runs(self.copy)


class Policy(Protocol):
    """How a method acts: actions (len(rows),) for the agents ``rows`` of ``batch``, never a masked one.

    A policy holds its own choices (greedy or sampling, its seeded generator); learned actors answer
    all the rows in one forward pass.
    """

    def act(self, batch: AgentBatch, rows: IntArray) -> IntArray: ...


@dataclass
class StepResult:
    """One step, per agent of the batch that acted (aligned with it) and per copy."""

    rewards: FloatArray
    """The sum of the agent's own parts: finish + collide + impede (+ any extra individual term)."""
    reward_parts: FloatArray
    """(n, len(part_names)): the named parts; a shared part ('flow') is the agent's copy's value."""
    end_reason: tuple[str, ...]
    """'' while the agent goes on, else one of END_REASONS."""
    applied: IntArray
    """The actions applied (a masked request replaced by the closest allowed one)."""
    joint_reward: FloatArray
    """Per copy: the sum of its agents' rewards plus its flow penalty (the central critic's reward)."""
    collisions: list[list[tuple[str, str]]]
    """Per copy: collision pairs."""
    hard_brakes: IntArray
    """Per copy."""
    hard_brakes_merge_zone: IntArray
    """Per copy."""
    hard_brake_ids: list[list[str]]
    """Per copy: the vehicles counted in ``hard_brakes``, in the order counted (agents, then SUMO's cars)."""
    part_names: tuple[str, ...] = REWARD_PART_NAMES
    """The columns of ``reward_parts`` (``RewardConfig.part_names``)."""


def placeholder_mask() -> npt.NDArray[np.int8]:
    """The action mask handed back with an agent's last observation: one action, never used."""
    mask = np.zeros(N_ACTIONS, dtype=np.int8)
    mask[0] = 1
    return mask


def _copy_runs(copy: IntArray) -> list[tuple[int, int, int]]:
    """(copy, lo, hi) for each run of equal entries in ``copy`` (a batch comes copy by copy)."""
    if len(copy) == 0:
        return []
    starts = np.flatnonzero(np.diff(copy)) + 1
    lo = [0, *starts.tolist()]
    hi = [*starts.tolist(), len(copy)]
    return list(zip(copy[lo].tolist(), lo, hi, strict=True))
