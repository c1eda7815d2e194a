"""The episode engine: K merge episodes side by side in one SUMO run, every agent of every copy at once.

``MergeEngine`` owns K episode *slots* over a ``BatchBackend`` (K copies of the merge net in one libsumo
simulation, sim/batch.py; each copy moves exactly as its scenario alone). Each step it reads SUMO once,
builds one copy-aware ``TrafficSnapshot`` (env/snapshot.py: pairwise relations never cross copies),
hands every active agent of every copy to the policies as one ``AgentBatch``, applies the masked actions
and scores the step with numpy over all copies. ``run_episodes`` is the one episode loop: it fills the
slots with the next scenarios, steps until all are over, and refills; results come back in scenario
order, whatever K is.

A slot follows the single-episode rules exactly: an agent acts from the step it enters; a copy with no
agent on the road but controlled cars still to come only lets time run (nothing is scored, as when one
episode waits for its first car); a copy is over when every controlled car finished, collided or left,
or time ran out. ``EpisodeOutcome`` defines success once, for training, validation and evaluation.
"""

from __future__ import annotations

import functools
import itertools
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Literal, Protocol, get_args

import numpy as np
import numpy.typing as npt

from idas_sumo.env.actions import (
    DEFAULT_SAFETY_MASK,
    HARD_BRAKE,
    N_ACTIONS,
    N_DELTA_ACTIONS,
    SAFETY_MASKS,
    MaskInputs,
    SafetyMask,
    action_masks,
    candidate_accelerations,
    closest_allowed_action,
    effective_speed_limit,
    next_acceleration,
    safety_bound,
)
from idas_sumo.env.jit import kernel
from idas_sumo.env.layout import (
    ACCEL_SCALE_MPS2,
    B_TYPE_SCALE,
    DIST_SCALE_M,
    OBS_DIM,
    RELATIVE_SPEED_SCALE_MPS,
    SPEED_SCALE_MPS,
    VISIBILITY_M,
)
from idas_sumo.env.observation import build_observations, build_observations_checked
from idas_sumo.env.rewards import (
    FINISH_DISTANCE_PAST_MERGE_M,
    FLOW_PENALTY_PER_HARD_BRAKE,
    IMPEDE_PENALTY,
    MERGE_ZONE_RADIUS_M,
    REWARD_PART_NAMES,
    RewardConfig,
)
from idas_sumo.env.scenario import Road, Scenario, VehicleSpec
from idas_sumo.env.snapshot import (
    MAIN,
    MERGE,
    NO_LEADER,
    OUT,
    TrafficSnapshot,
    leader_speeds,
    leaders_and_speeds,
    nearest_ahead,
    other_road_leaders,
)
from idas_sumo.env.state_layout import STATE_DIM, STATE_FEATURES, STATE_SLOTS
from idas_sumo.errors import SimulationError
from idas_sumo.physics.idm import DEFAULT_IDM
from idas_sumo.sim.backend import (
    STEP_LENGTH_S,
    VEHICLE_LENGTH_M,
    Backend,
    StepEvents,
    make_backend,
    slot_taken,
)
from idas_sumo.sim.batch import BatchBackend, BatchStates, BatchStepEvents
from idas_sumo.sim.merge_detect import MergeSite, as_site
from idas_sumo.sim.netgen import MergeNet

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]
BoolArray = npt.NDArray[np.bool_]
HARD_BRAKE_DETECT_MPS2 = -3.0  # a SUMO-driven car decelerating harder than this counts as a hard brake
DEFAULT_MAX_EPISODE_S = 60.0  # ours: timeout, not a success
Standstill = Literal["keeps_command", "at_rest"]
"""What acceleration an agent at rest drives on with (``EnvConfig.standstill``)."""
END_REASONS: tuple[str, ...] = ("finished", "collided", "removed", "timeout")
_PART = {name: i for i, name in enumerate(REWARD_PART_NAMES)}


@dataclass(frozen=True)
class EnvConfig:
    """Episode rules shared by every environment."""

    max_episode_s: float = DEFAULT_MAX_EPISODE_S
    """Simulated seconds before the episode is cut off (a timeout is not a success)."""
    reward: RewardConfig = field(default_factory=RewardConfig)
    safety_mask: SafetyMask = DEFAULT_SAFETY_MASK
    """Which car the safety mask keeps a safe distance to: 'own_lane' (the paper, L219 and L233-237: the
    front car in the agent's own lane; the car on the other road is the conflict the policy must
    learn) or 'merge_aware' (ours, an optional shield: the other road's car closer to the merge point
    counts too, main road first; see ``MergeEngine.front_cars``)."""
    junction: str | None = None
    """Which merge of a net with several the episodes run on (its junction id, ``choose_merge``); None:
    the net's only one. Here, so that every engine of a run (workers, Ray actors) runs on the same."""
    standstill: Standstill = "keeps_command"
    """The acceleration an agent that comes to rest drives on with. 'keeps_command' (the default; every
    shipped policy was trained so): the one it commanded, so a car that stopped at -1.5 m/s² needs eight
    steps of +0.2 before it moves. 'at_rest' (ours, a labelled variant): 0, the acceleration a car at rest
    has (the paper's agents observe "the current acceleration", L277), so one +0.1 moves it."""

    def __post_init__(self) -> None:
        if not (self.max_episode_s > 0):
            raise ValueError(f"max_episode_s must be positive, got {self.max_episode_s}")
        if self.standstill not in get_args(Standstill):
            raise ValueError(f"standstill must be one of {get_args(Standstill)}, got {self.standstill!r}")
        if self.safety_mask not in SAFETY_MASKS:
            raise ValueError(
                f"safety_mask must be one of {', '.join(SAFETY_MASKS)}, got {self.safety_mask!r}"
            )


def with_safety_mask(config: EnvConfig | None, safety_mask: SafetyMask | None) -> EnvConfig:
    """``config`` (default: ``EnvConfig()``) with ``safety_mask`` when one is given (the environments'
    ``safety_mask=`` argument)."""
    config = config or EnvConfig()
    return config if safety_mask is None else replace(config, safety_mask=safety_mask)


# -- what an episode amounted to -------------------------------------------------------------------


def is_success(collisions: int, all_finished: bool) -> bool:
    """The paper's success: no collision and every controlled car finished (in time)."""
    return collisions == 0 and all_finished


def is_perfect(success: bool, impedes: int, hard_brakes_merge_zone: int) -> bool:
    """Success without any reward deduction: no impede, no flow penalty (no hard brake in the merging zone)."""
    return success and impedes == 0 and hard_brakes_merge_zone == 0


@dataclass
class EpisodeOutcome:
    """One episode's facts, and the one definition of success (docs/design-notes.md, "Definitions").

    Counts cover the steps in which some agent acted (a copy waiting for its next car scores nothing),
    except collisions, which count whenever the episode runs (a car may collide as it enters).
    """

    scenario: Scenario
    end_reasons: dict[str, str] = field(default_factory=dict)
    """Per controlled car that entered: 'finished', 'collided', 'removed' or 'timeout'."""
    collisions: int = 0
    """Collision pairs (any cars): SUMO's reports and the engine's geometric cross-check."""
    geometric_collisions: int = 0
    """Of those, the pairs only the geometric cross-check found (``geometric_collisions``)."""
    hard_brakes: int = 0
    """Hard brakes: agents choosing the hard-brake action, SUMO-driven cars decelerating harder than
    ``HARD_BRAKE_DETECT_MPS2``."""
    hard_brakes_merge_zone: int = 0
    """Of those, the ones within ``MERGE_ZONE_RADIUS_M`` of the merge point (each costs the flow penalty)."""
    impedes: int = 0
    """Agent-steps with an impede penalty."""
    returns: dict[str, float] = field(default_factory=dict)
    """Per agent: the sum of its rewards (finish + collide + impede)."""
    finish_times_s: dict[str, float] = field(default_factory=dict)
    """Per finished agent: the simulated time it crossed the finish line."""
    decision_steps: int = 0
    """Steps in which at least one agent acted."""
    agent_steps: int = 0
    start_time_s: float = 0.0
    """When the first agent could act (the insertion step ends at 0.2 s)."""
    end_time_s: float = 0.0
    timed_out: bool = False

    @property
    def duration_s(self) -> float:
        return self.end_time_s - self.start_time_s

    @property
    def all_finished(self) -> bool:
        """Every controlled car of the scenario finished."""
        return all(self.end_reasons.get(a) == "finished" for a in self.scenario.controlled_ids)

    @property
    def success(self) -> bool:
        return is_success(self.collisions, self.all_finished)

    @property
    def perfect(self) -> bool:
        return is_perfect(self.success, self.impedes, self.hard_brakes_merge_zone)


# -- what the policies see -------------------------------------------------------------------------


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

    @functools.cached_property
    def obs(self) -> npt.NDArray[np.float32]:
        """(n, OBS_DIM) observations, built on first use (rule-based policies never need them)."""
        if not len(self.ids):
            return np.zeros((0, OBS_DIM), dtype=np.float32)
        obs, scalars_finite = build_observations_checked(
            self.snapshot, self.egos, self.prev_accel, self.b_prio, self.b_type
        )
        # The grids hold 1s and relative speeds, finite whenever the speeds' spread is: only when the
        # scalars or the speeds are not is every entry tested (a fifth of a step's observation time).
        speed = self.snapshot.speed_mps
        spread = float(np.ptp(speed)) if len(speed) else 0.0
        if not (scalars_finite and spread / RELATIVE_SPEED_SCALE_MPS < _FLOAT32_SAFE):
            finite = np.isfinite(obs).all(axis=1)
            if not finite.all():
                bad = self.ids[int(np.argmin(finite))]
                raise SimulationError(
                    f"non-finite observation for agent {bad!r} at t = {self.time_s:.1f} s (a bug)"
                )
        return obs

    @functools.cached_property
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
    """finish + collide + impede."""
    reward_parts: FloatArray
    """(n, len(REWARD_PART_NAMES)): the named parts; 'flow' is the agent's copy's shared flow penalty."""
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


# -- SUMO side -------------------------------------------------------------------------------------


class _SoloBackend:
    """One scenario on a single-simulation backend (in-process, a subprocess, or sumo-gui), behind the
    ``BatchBackend`` calls the engine makes: the K = 1 engine of the environments and of ``--gui``."""

    copies = 1

    def __init__(self, backend: Backend) -> None:
        self._backend = backend
        self._index: dict[str, int] = {}
        """Vehicle id -> its index in the scenario."""

    def reset(self, scenarios: Sequence[Scenario], extra_args: Sequence[str] = ()) -> None:
        if len(scenarios) != 1:
            raise SimulationError(f"{len(scenarios)} scenarios for a single simulation (a bug)")
        self._backend.reset(scenarios[0], extra_args)
        self._index = {v.id: i for i, v in enumerate(scenarios[0].vehicles)}

    def global_id(self, copy: int, vehicle_id: str) -> str:
        return vehicle_id

    def step(self) -> BatchStepEvents:
        events: StepEvents = self._backend.step()
        return BatchStepEvents(events.time_s, [events])

    def vehicle_states(self) -> BatchStates:
        s = self._backend.vehicle_states()
        n = len(s.ids)
        zeros = np.zeros(n, dtype=np.int64)
        return BatchStates(
            s.ids,
            zeros,
            np.fromiter(map(self._index.get, s.ids, itertools.repeat(-1)), np.int64, n),
            s.edge,
            zeros,
            s.lane_pos_m,
            s.speed_mps,
            s.accel_mps2,
            np.array([0, n]),
            s.lane_index,
        )

    def set_speeds(
        self, vehicle_ids: Sequence[str], speeds_mps: npt.ArrayLike, copy: npt.ArrayLike | None = None
    ) -> None:
        speeds = np.asarray(speeds_mps, dtype=np.float64).tolist()
        self._backend.set_speeds(dict(zip(vehicle_ids, speeds, strict=True)))

    def release(self, vehicle_id: str, copy: int) -> None:
        self._backend.release(vehicle_id)

    def remove(self, vehicle_id: str, copy: int) -> None:
        self._backend.remove(vehicle_id)

    def clear_copy(self, copy: int) -> None:
        """Nothing to do: the next reset reloads the simulation."""

    def close(self) -> None:
        self._backend.close()


@dataclass
class _Slot:
    """One copy's episode (its cars' per-step state is in the engine's ``_Cars``)."""

    scenario: Scenario
    spec: dict[str, VehicleSpec]
    order: dict[str, int]
    """Vehicle id -> its index in the scenario."""
    state_slot: dict[str, int]
    outcome: EpisodeOutcome
    over: bool = False
    started: bool = False


WAITING, ACTIVE, ENDED = 0, 1, 2
"""A controlled car's part in its episode (``_Cars.state``): not entered yet, acting, or ended."""


@dataclass
class _Cars:
    """Every vehicle of the slots' scenarios, slot by slot in scenario order (car ``first[k] + i`` is
    vehicle i of slot k's scenario): what a step looks up per car, as arrays over all copies at once
    instead of dictionaries per copy."""

    ids: tuple[str, ...]
    """Copy-local ids."""
    global_ids: tuple[str, ...]
    """The backend's ids (what ``set_speeds`` takes without a copy)."""
    first: IntArray
    """(K + 1,): slot k's cars are ``first[k]:first[k + 1]``."""
    copy: IntArray
    origin: IntArray
    """MAIN or MERGE: the road the car starts on."""
    controlled: BoolArray
    b_type: FloatArray
    state: npt.NDArray[np.int8]
    """WAITING, ACTIVE or ENDED (SUMO's cars stay WAITING)."""
    admitted: BoolArray
    """Became an agent (``accel`` holds the acceleration it drives with)."""
    accel: FloatArray
    scored: BoolArray
    """Has an entry in its outcome's ``returns`` (from its first action on)."""
    row: IntArray
    """Each car's row in the engine's snapshot (-1: not on the road); replaced, never changed, by a read."""

    @staticmethod
    def of(scenarios: Sequence[Scenario], global_id: Callable[[int, str], str]) -> _Cars:
        vehicles = [(k, v) for k, s in enumerate(scenarios) for v in s.vehicles]
        n = len(vehicles)
        return _Cars(
            ids=tuple(v.id for _, v in vehicles),
            global_ids=tuple(global_id(k, v.id) for k, v in vehicles),
            first=np.cumsum([0, *(len(s.vehicles) for s in scenarios)]).astype(np.int64),
            copy=np.array([k for k, _ in vehicles], dtype=np.int64),
            origin=np.array([MAIN if v.road == "main" else MERGE for _, v in vehicles], dtype=np.int64),
            controlled=np.array([v.controlled for _, v in vehicles], dtype=np.bool_),
            b_type=np.array([v.b_type for _, v in vehicles], dtype=np.float64),
            state=np.full(n, WAITING, dtype=np.int8),
            admitted=np.zeros(n, dtype=np.bool_),
            accel=np.zeros(n, dtype=np.float64),
            scored=np.zeros(n, dtype=np.bool_),
            row=np.full(n, -1, dtype=np.int64),
        )


@dataclass(frozen=True)
class _Agents:
    """The acting agents of every running slot, in slot then scenario order (``observe``'s batch rows):
    kept until an agent enters or ends or a slot's episode ends."""

    car: IntArray
    ids: tuple[str, ...]
    global_ids: tuple[str, ...]
    copy: IntArray
    b_type: FloatArray


class MergeEngine:
    """K merge episodes at a time on one SUMO simulation (``copies`` = K)."""

    def __init__(
        self,
        net: MergeSite | MergeNet | str | Path,
        copies: int = 1,
        seed: int = 0,
        config: EnvConfig | None = None,
        gui: bool = False,
    ) -> None:
        """``net``: the merge the episodes run on: a ``MergeSite``, a ``MergeNet`` or a net file with one
        merge (or several and ``config.junction`` naming one: ``choose_merge``)."""
        if copies < 1:
            raise ValueError(f"copies must be at least 1, got {copies}")
        if gui and copies != 1:
            raise ValueError("sumo-gui shows one simulation: copies must be 1 with gui")
        self.config = config or EnvConfig()
        self.site = as_site(net, self.config.junction)
        # libsumo holds one simulation per process: when it is taken (another environment is open), run
        # the episodes one at a time in a SUMO child process. Results do not depend on K.
        if copies > 1 and slot_taken():
            copies = 1
        self.copies = copies
        self._seed = seed
        self._gui = gui
        self._backend: BatchBackend | _SoloBackend | None = None
        self.speed_limits_mps: dict[Road, float] = {
            "main": self.site.main.road.speed_limit_mps,
            "merge": self.site.merge.road.speed_limit_mps,
        }
        """Each approach's own road's limit (the scenarios' start speeds are fractions of it)."""
        self.road_lengths_m: dict[Road, float] = {
            "main": self.site.main.length_m,
            "merge": self.site.merge.length_m,
        }
        """Each approach's length to the merge point (the scenarios' starts are measured from its start)."""
        self.out_limit_mps = self.site.out[0].speed_limit_mps
        """The limit after the merge point (the rule mask's exemption near the merge)."""
        self._edge_code, self._start_by, self._incoming_by, self._limit_by = _route_tables(self.site)
        # Per edge code: the main approach's lane on an edge both approaches share (a lane drop's
        # acceleration edge), else -1. A merging car on that lane has changed onto the main road.
        self._merged_lane = np.full(self._start_by.shape[1], -1, dtype=np.int64)
        for edge_id, lane_index in self.site.shared_lanes.items():
            self._merged_lane[self._edge_code[edge_id]] = lane_index
        self._via_length_by_code = np.array([self.site.main.via_length_m, self.site.merge.via_length_m])
        self._code_by_edge_index: IntArray | None = None
        """The edge codes by ``BatchStates.edge_index``, where the backend numbers its edges (``_make_backend``)."""
        self.slots: list[_Slot] = []
        self.snapshot = _empty_snapshot()
        self._controlled = np.zeros(0, dtype=np.bool_)
        self._origin = np.zeros(0, dtype=np.int64)
        self._cars = _Cars.of((), lambda k, vid: vid)
        self._car = np.zeros(0, dtype=np.int64)
        """Each snapshot row's car (``_Cars``)."""
        self._agents: _Agents | None = None
        """``observe``'s agents while they stay the same (None: gather them again)."""
        self._batch: AgentBatch | None = None
        self._batch_agents: _Agents | None = None
        self._time_s = 0.0
        self._closed = False

    # -- episodes ------------------------------------------------------------------------------
    def _make_backend(self) -> BatchBackend | _SoloBackend:
        if self.copies == 1:
            return _SoloBackend(make_backend(self.site, seed=self._seed, gui=self._gui))
        backend = BatchBackend(self.site, copies=self.copies, seed=self._seed)
        # Its states number each edge (``BatchStates.edge_index``, -1: none of the net's): the edge codes by
        # that number, the last entry for -1, spare a dictionary lookup per car and step.
        unknown = self._start_by.shape[1] - 1
        self._code_by_edge_index = np.array(
            [*(self._edge_code.get(e, unknown) for e in backend.net.edge_ids), unknown], dtype=np.int64
        )
        return backend

    def reset(self, scenarios: Sequence[Scenario], sumo_args: Sequence[str] = ()) -> None:
        """Start one episode per scenario (at most ``copies``), scenario k in slot k."""
        if self._closed:
            raise SimulationError("this engine is closed; create a new one")
        if not 1 <= len(scenarios) <= self.copies:
            raise ValueError(f"{len(scenarios)} scenarios for {self.copies} slots")
        if self._backend is None:
            self._backend = self._make_backend()
        self.slots = []
        for s in scenarios:
            self.slots.append(
                _Slot(
                    scenario=s,
                    spec={v.id: v for v in s.vehicles},
                    order={v.id: i for i, v in enumerate(s.vehicles)},
                    state_slot={v.id: i for i, v in enumerate(s.vehicles) if i < STATE_SLOTS},
                    outcome=EpisodeOutcome(s),
                )
            )
        # b_prio by (slot, road): the outgoing road takes the higher of the two incoming priorities.
        self._prio_by_road = np.array(
            [
                (float(s.main_prio), float(s.merge_prio), float(max(s.main_prio, s.merge_prio)))
                for s in scenarios
            ]
        )
        self._batch = None
        self._cars = _Cars.of(scenarios, self._backend.global_id)
        self._agents = None
        self._backend.reset(scenarios, sumo_args)
        events = self._backend.step()  # insertion step: vehicles appear where the scenarios put them
        self._time_s = events.time_s
        self._read_snapshot()
        self._cross_check(events)
        for k, slot in enumerate(self.slots):
            ev = events.copies[k]
            slot.outcome.collisions += len(ev.collision_pairs)
            self._settle(k, self._admit(k, ev) > 0)

    @property
    def backend(self) -> BatchBackend | _SoloBackend:
        if self._backend is None:
            raise SimulationError("step() before reset()")
        return self._backend

    @property
    def single_backend(self) -> Backend:
        """The one SUMO simulation of a K = 1 engine (in-process, a subprocess, or sumo-gui)."""
        backend = self.backend
        if not isinstance(backend, _SoloBackend):
            raise SimulationError("a K-copy engine has no single backend (a bug)")
        return backend._backend

    @property
    def time_s(self) -> float:
        """Simulated seconds since the scenarios started (the insertion step ends at 0.2 s)."""
        return self._time_s

    def timed_out(self) -> bool:
        return self._time_s >= self.config.max_episode_s - 1e-9

    @property
    def running(self) -> list[int]:
        """Slots whose episode is not over."""
        return [k for k, s in enumerate(self.slots) if not s.over]

    def over(self, k: int) -> bool:
        return self.slots[k].over

    def outcome(self, k: int) -> EpisodeOutcome:
        return self.slots[k].outcome

    def active_agents(self, k: int) -> list[str]:
        """Slot k's controlled cars on the road that still act (in scenario order)."""
        cars = self._cars
        lo, hi = int(cars.first[k]), int(cars.first[k + 1])
        return [cars.ids[c] for c in (lo + np.flatnonzero(cars.state[lo:hi] == ACTIVE)).tolist()]

    def finished_agents(self, k: int) -> dict[str, str]:
        return dict(self.slots[k].outcome.end_reasons)

    def spec(self, k: int, vehicle_id: str) -> VehicleSpec:
        return self.slots[k].spec[vehicle_id]

    def _car_of(self, k: int, vehicle_id: str) -> int:
        """``vehicle_id``'s car (``_Cars``) in slot k (KeyError: not in its scenario)."""
        return int(self._cars.first[k]) + self.slots[k].order[vehicle_id]

    def admitted(self, k: int, vehicle_id: str) -> bool:
        """Whether slot k's ``vehicle_id`` became an agent (it has a ``prev_accel``)."""
        i = self.slots[k].order.get(vehicle_id)
        return i is not None and bool(self._cars.admitted[int(self._cars.first[k]) + i])

    def prev_accel(self, k: int, agent_id: str) -> float:
        """The acceleration slot k's agent drives with (KeyError: it never became an agent)."""
        c = self._car_of(k, agent_id)
        if not self._cars.admitted[c]:
            raise KeyError(agent_id)
        return float(self._cars.accel[c])

    def rows_of(self, k: int) -> slice:
        """Slot k's vehicles in ``snapshot``."""
        lo, hi = self._bounds[k], self._bounds[k + 1]
        return slice(int(lo), int(hi))

    def row(self, k: int, vehicle_id: str) -> int | None:
        """``vehicle_id``'s row in ``snapshot`` (None: not on the road)."""
        i = self.slots[k].order.get(vehicle_id)
        if i is None:
            return None
        r = int(self._cars.row[int(self._cars.first[k]) + i])
        return r if r >= 0 else None

    def _waiting(self, k: int) -> bool:
        """Controlled cars of slot k still to enter."""
        cars = self._cars
        lo, hi = int(cars.first[k]), int(cars.first[k + 1])
        return bool(((cars.state[lo:hi] == WAITING) & cars.controlled[lo:hi]).any())

    def _settle(self, k: int, active: bool) -> None:
        """After a step: mark the episode over, and the first step an agent can act (``active``: slot k
        has agents on the road)."""
        slot = self.slots[k]
        if self.timed_out() or (not active and not self._waiting(k)):
            slot.over = True
            self._agents = None
            slot.outcome.end_time_s = self._time_s
            slot.outcome.timed_out = self.timed_out()
            if not slot.started:
                slot.outcome.start_time_s = self._time_s
                slot.started = True
        elif active and not slot.started:
            slot.outcome.start_time_s = self._time_s
            slot.started = True

    def _admit(self, k: int, events: StepEvents) -> int:
        """Slot k's controlled cars that entered in this step start acting; one that collided as it
        entered (a later departure onto a car, which SUMO then removed) or is gone already ends there.
        Returns how many started acting."""
        slot = self.slots[k]
        cars = self._cars
        first = int(cars.first[k])
        added = 0
        for vid in events.departed:
            i = slot.order.get(vid)
            if i is None or not cars.controlled[first + i] or cars.state[first + i] != WAITING:
                continue
            c = first + i
            if vid in events.collided or cars.row[c] < 0:
                reason = "collided" if vid in events.collided else "removed"
                cars.state[c] = ENDED
                slot.outcome.end_reasons[vid] = reason
                if reason == "collided":
                    prio = float(slot.scenario.prio(slot.spec[vid].road))
                    reward = self.config.reward.collide(prio)
                    slot.outcome.returns[vid] = slot.outcome.returns.get(vid, 0.0) + reward
                continue
            cars.state[c] = ACTIVE
            cars.admitted[c] = True
            cars.accel[c] = 0.0
            added += 1
        if added:
            self._agents = None
        return added

    @staticmethod
    def _brake_onsets(
        before: TrafficSnapshot, brakes: IntArray, batch: AgentBatch, agent_brake: BoolArray
    ) -> BoolArray:
        """Which of ``brakes`` (the agents' first, in batch order) begin a brake: the car was not braking
        hard before this step (an agent's last acceleration, a SUMO car's measured one, above the
        detection threshold). What ``brake_count = 'manoeuvre'`` prices."""
        n_agent = int(agent_brake.sum())
        was_braking = (
            np.concatenate([batch.prev_accel[agent_brake], before.accel_mps2[brakes[n_agent:]]])
            <= HARD_BRAKE_DETECT_MPS2
        )
        return ~was_braking

    def _impede_culprits(
        self, before: TrafficSnapshot, brakes: IntArray, batch: AgentBatch, agent_brake: BoolArray
    ) -> IntArray:
        """The row in ``before`` of whoever pays r_impede, once per hard brake that has a payer
        (``RewardConfig.impede_blame``). ``brakes`` lists the agents' brakes first, in batch order."""
        if self.config.reward.impede_blame == "car_ahead" or not agent_brake.any():
            return _impeding_vehicles(before, brakes)
        chosen = batch.masks[agent_brake, :N_DELTA_ACTIONS].any(axis=1)
        n_agent = int(agent_brake.sum())
        agent_rows, sumo_rows = brakes[:n_agent], brakes[n_agent:]
        forced = np.concatenate([agent_rows[~chosen], sumo_rows])
        return np.concatenate([_impeding_vehicles(before, forced), agent_rows[chosen]])

    def _cross_check(self, events: BatchStepEvents) -> None:
        """Add the collisions SUMO did not report: cars of one running episode whose bodies overlap on
        one road (``geometric_collisions``). Both count as collided, as in a SUMO-reported
        collision (their episodes end with r_collide), and leave the road as SUMO's ``--collision.action
        remove`` would take them; the snapshot is then read again without them."""
        pairs = geometric_collisions(self.snapshot, self._origin, self._via_length_by_code[self._origin])
        if not pairs:
            return
        snap = self.snapshot
        removed = False
        for i, j in pairs:
            k = int(self._copy_of(snap, i))
            if self.slots[k].over:
                continue
            ev = events.copies[k]
            a, b = snap.ids[i], snap.ids[j]
            ev.collision_pairs.append((a, b))
            ev.collided.update((a, b))
            self.slots[k].outcome.geometric_collisions += 1
            for vid in (a, b):
                self.backend.remove(vid, k)
            removed = True
        if removed:
            self._read_snapshot()

    def _read_snapshot(self) -> None:
        states = self.backend.vehicle_states()
        n = len(states.ids)
        copy = states.copy
        bounds = states.bounds
        cars = self._cars
        if n and int(states.vehicle.min()) < 0:
            bad = states.ids[int(np.argmin(states.vehicle))]
            raise SimulationError(f"vehicle {bad!r} on the road is from no scenario of the engine")
        car = cars.first[copy] + states.vehicle
        origin = cars.origin[car]
        controlled = cars.controlled[car]
        row = np.full(len(cars.ids), -1, dtype=np.int64)
        row[car] = np.arange(n)
        cars.row = row
        self._car = car
        # Distances along each car's own route (engine docstring of ``_route_tables``): one code per edge,
        # then a table lookup by (origin, edge).
        if self._code_by_edge_index is not None:
            code = self._code_by_edge_index[states.edge_index]
        else:
            unknown = self._start_by.shape[1] - 1
            code = np.fromiter(map(self._edge_code.get, states.edge, itertools.repeat(unknown)), np.int64, n)
        if states.lane_index is not None and n:
            # On a lane drop a merging car that changed onto the main road's lane drives on as a main-road
            # car: the cars behind it in that lane see it in their own lane (the paper's mask keeps its
            # distance to it), and it sees theirs. Before, it stayed a merge-road car beside the lane it
            # had joined, and highway cars ran into it (most of the on-ramp's collisions).
            merged = (origin == MERGE) & (states.lane_index == self._merged_lane[code])
            origin = np.where(merged, MAIN, origin)
        pos = states.lane_pos_m
        incoming = self._incoming_by[origin, code]
        road = np.where(incoming, origin, OUT)
        # -(pos - start), not start - pos: bit for bit the T-junction's former formulas (L - pos on an
        # incoming road, -(via + pos) on the outgoing one, -pos on a junction lane, -0.0 included).
        dist = -(pos - self._start_by[origin, code])
        lane_limit = self._limit_by[origin, code]
        own_limit = effective_speed_limit(lane_limit, dist, self.out_limit_mps)
        limit = np.where(incoming, own_limit, lane_limit)
        self._bounds = bounds
        self._controlled = controlled
        self._origin = origin
        self.snapshot = TrafficSnapshot(
            ids=states.ids,
            road=road.astype(np.int64),
            dist_to_merge_m=dist,
            speed_mps=states.speed_mps.copy(),
            accel_mps2=states.accel_mps2.copy(),
            length_m=np.full(n, VEHICLE_LENGTH_M),
            speed_limit_mps=limit,
            copy=copy if len(self.slots) > 1 else None,
            known_copy_bounds=bounds,
        )

    # -- observation ---------------------------------------------------------------------------
    def observe(self) -> AgentBatch:
        """Every active agent of every running slot, in slot then scenario order."""
        agents = self._agents
        if agents is None:
            agents = self._agents = self._gather_agents()
        cars = self._cars
        egos = cars.row[agents.car]
        prev = cars.accel[agents.car]
        batch = AgentBatch(
            ids=agents.ids,
            copy=agents.copy,
            egos=egos,
            prev_accel=prev,
            masks=self._masks(egos, prev),
            snapshot=self.snapshot,
            b_prio=self._prio_by_road[agents.copy, self.snapshot.road[egos]],
            b_type=agents.b_type,
            time_s=self._time_s,
        )
        self._batch = batch
        self._batch_agents = agents
        return batch

    def _gather_agents(self) -> _Agents:
        cars = self._cars
        running = np.array([not slot.over for slot in self.slots], dtype=np.bool_)
        car = np.flatnonzero((cars.state == ACTIVE) & running[cars.copy])
        picked = car.tolist()
        copy = cars.copy[car]
        b_type = cars.b_type[car]
        for a in (car, copy, b_type):
            a.flags.writeable = False  # shared by every batch until the agents change
        return _Agents(
            car=car,
            ids=tuple(map(cars.ids.__getitem__, picked)),
            global_ids=tuple(map(cars.global_ids.__getitem__, picked)),
            copy=copy,
            b_type=b_type,
        )

    def observe_agents(self, k: int, agent_ids: Sequence[str]) -> npt.NDArray[np.float32]:
        """Observations of slot k's agents that are on the road now, acting or not (e.g. the state a
        timeout cut an agent off in, to bootstrap from)."""
        slot = self.slots[k]
        cars = self._cars
        car = np.array([self._car_of(k, a) for a in agent_ids], dtype=np.int64)
        if not len(car):
            return np.zeros((0, OBS_DIM), dtype=np.float32)
        egos = cars.row[car]
        if (egos < 0).any() or not cars.admitted[car].all():
            bad = agent_ids[int(np.argmax((egos < 0) | ~cars.admitted[car]))]
            raise KeyError(f"{bad!r} is no agent on the road of slot {k}")
        return build_observations(
            self.snapshot,
            egos,
            cars.accel[car],
            self._prio_by_road[k, self.snapshot.road[egos]],
            np.array([slot.spec[a].b_type for a in agent_ids]),
        )

    def _masks(self, egos: IntArray, prev: FloatArray) -> npt.NDArray[np.int8]:
        if len(egos) == 0:
            return np.zeros((0, N_ACTIONS), dtype=np.int8)
        snap = self.snapshot
        gap, leader_speed, ease_in = self.front_cars(egos)
        return action_masks(
            MaskInputs(
                prev_accel_mps2=prev,
                speed_mps=snap.speed_mps[egos],
                speed_limit_mps=snap.speed_limit_mps[egos],
                gap_m=gap,
                leader_speed_mps=leader_speed,
                ease_in=ease_in,
            )
        )

    def front_cars(self, egos: IntArray) -> tuple[FloatArray, FloatArray, npt.NDArray[np.bool_]]:
        """The car the safety mask keeps its distance to: (gap m, its speed m/s, ease_in; see MaskInputs).

        ``EnvConfig.safety_mask`` = 'own_lane' (the paper's mask, the default): the nearest car ahead in
        the ego's own lane (its road, then the outgoing road); ``ease_in`` is all False. Before the merge
        point a car on the other road is no front car: the order at the merge point is the policy's to
        settle (FSM+IDM adds that car itself, as a virtual leader; baselines/fsm_idm.py).

        'merge_aware' (ours, a shield): in a merge the car in front is not only the one ahead in the
        ego's lane. A car on the other incoming road that is closer to the merge point (projected, within
        sight of both) will be in front of the ego after the merge, so whichever of the two asks for the
        lower IDM acceleration counts. Level cars: the main-road car counts as ahead. With only the ego's
        own lane the cars of the two roads met side by side at the merge point in the old dense traffic:
        28 of the first 40 paper-suite scenarios had a collision with IDM driving every car, 26 with
        IDAS (docs/design-notes.md).
        """
        snap = self.snapshot
        _, gap, leader_speed = leaders_and_speeds(snap, egos)
        if self.config.safety_mask == "own_lane":
            return gap, leader_speed, np.zeros(len(egos), dtype=np.bool_)
        # SUMO's own cars on the merge road give way to every main-road car at the junction (stage 1's
        # "merge always yields"); counting them as front cars of main-road cars deadlocked both.
        sumo_yielding = (snap.road == MERGE) & ~self._controlled
        merge_leader, merge_gap = other_road_leaders(
            snap,
            egos,
            max_ahead_m=np.inf,
            zone_m=VISIBILITY_M,
            level_counts_for_main=True,
            never_leading=sumo_yielding,
        )
        speed = snap.speed_mps[egos]
        merge_speed = leader_speeds(snap, egos, merge_leader)
        own_lane_bound = safety_bound(speed, gap, leader_speed)
        other_road = (merge_leader >= 0) & (safety_bound(speed, merge_gap, merge_speed) < own_lane_bound)
        ease_in = (
            other_road
            & (snap.dist_to_merge_m[egos] > MERGE_ZONE_RADIUS_M)
            & (own_lane_bound >= -DEFAULT_IDM.comfortable_decel_mps2)
        )
        return np.where(other_road, merge_gap, gap), np.where(other_road, merge_speed, leader_speed), ease_in

    def state(self, k: int) -> npt.NDArray[np.float32]:
        """Slot k's global state for the centralised critic (layout in ``env/state_layout.py``)."""
        slot = self.slots[k]
        state = np.zeros((STATE_SLOTS, STATE_FEATURES), dtype=np.float32)
        snap = self.snapshot
        table = self._prio_by_road[k]
        rows = self.rows_of(k)
        for i in range(rows.start, rows.stop):
            vid = snap.ids[i]
            place = slot.state_slot.get(vid)
            if place is None:
                continue
            spec = slot.spec[vid]
            road = int(snap.road[i])
            state[place] = (
                1.0,
                road == MAIN,
                road == MERGE,
                road == OUT,
                snap.dist_to_merge_m[i] / DIST_SCALE_M,
                snap.speed_mps[i] / SPEED_SCALE_MPS,
                snap.accel_mps2[i] / ACCEL_SCALE_MPS2,
                table[road],
                spec.b_type / B_TYPE_SCALE,
                float(self._cars.state[self._car[i]] == ACTIVE),
            )
        return state.reshape(STATE_DIM)

    # -- stepping ------------------------------------------------------------------------------
    def step(self, actions: npt.ArrayLike) -> StepResult:
        """Apply one action per agent of the last ``observe()`` batch, advance SUMO one step, score it."""
        if self._closed:
            raise SimulationError("step() after close(); create a new engine")
        batch, agents = self._batch, self._batch_agents
        if batch is None or agents is None:
            raise SimulationError("step() without observe() first")
        self._batch = self._batch_agents = None
        cars = self._cars
        n = len(batch)
        requested = _checked_actions(batch, actions)
        before = self.snapshot
        applied = requested
        if n:
            masks, prev = batch.masks, batch.prev_accel
            if not _all_allowed(masks, requested):
                rows = np.arange(n)
                allowed = masks[rows, requested].astype(bool)
                wanted = candidate_accelerations(prev)[rows, requested]
                applied = np.where(allowed, requested, closest_allowed_action(wanted, prev, masks))
            new_accel = next_acceleration(prev, applied)
            next_speed = _next_speeds(before.speed_mps, batch.egos, new_accel, STEP_LENGTH_S)
            self.backend.set_speeds(agents.global_ids, next_speed)
            if self.config.standstill == "at_rest":
                new_accel = np.where((next_speed == 0.0) & (new_accel < 0.0), 0.0, new_accel)
            cars.accel[agents.car] = new_accel
        events = self.backend.step()
        self._time_s = events.time_s
        rows_before = cars.row
        self._read_snapshot()
        self._cross_check(events)
        after = self.snapshot
        k_count = len(self.slots)
        acting = np.zeros(k_count, dtype=np.bool_)
        acting[batch.copy] = True

        # Hard brakes, placed where the braking car was when it decided (the step's start): agents that
        # chose the hard brake, then SUMO-driven cars of acting copies that braked hard on their own.
        agent_brake = applied == HARD_BRAKE
        brakes, brake_copy, in_zone, hard_brakes, zone_brakes = _hard_brakes(
            batch.egos,
            agent_brake,
            after.accel_mps2,
            self._car,
            acting,
            cars.copy,
            cars.state,
            rows_before,
            self._row_copy(before),
            before.dist_to_merge_m,
            MERGE_ZONE_RADIUS_M,
        )
        hard_brake_ids: list[list[str]] = [[] for _ in range(k_count)]
        for r, k in zip(brakes.tolist(), brake_copy.tolist(), strict=True):
            hard_brake_ids[k].append(before.ids[r])
        # The brakes the rewards count (RewardConfig.brake_count); the statistics above count every step.
        priced_zone, priced_brakes, priced_agents = zone_brakes, brakes, agent_brake
        if self.config.reward.brake_count == "manoeuvre":
            onset = self._brake_onsets(before, brakes, batch, agent_brake)
            priced_zone = np.bincount(brake_copy[in_zone & onset], minlength=k_count)
            priced_brakes = brakes[onset]
            priced_agents = agent_brake.copy()
            priced_agents[agent_brake] = onset[: int(agent_brake.sum())]
        flow = FLOW_PENALTY_PER_HARD_BRAKE * priced_zone  # per merge-zone brake, shared per copy
        impeded_by = self._impede_culprits(before, priced_brakes, batch, priced_agents)

        # End reasons: collided, removed, finished, else timeout (if time is up).
        copies = batch.copy.tolist()
        collided = np.zeros(n, dtype=np.bool_)
        if any(ev.collided for ev in events.copies):
            collided[:] = [a in events.copies[k].collided for a, k in zip(batch.ids, copies, strict=True)]
        code = _end_codes(
            collided,
            cars.row[agents.car],
            after.dist_to_merge_m,
            -FINISH_DISTANCE_PAST_MERGE_M,
            _REASON_CODE["timeout" if self.timed_out() else ""],
        )
        reasons = [_REASON_BY_CODE[c] for c in code.tolist()]

        parts = np.zeros((n, len(REWARD_PART_NAMES)))
        if n:
            _penalty_parts(
                parts,
                batch.copy,
                batch.egos,
                flow,
                impeded_by,
                len(before),
                IMPEDE_PENALTY,
                _PART["flow"],
                _PART["impede"],
            )
            for i in np.flatnonzero(collided).tolist():
                slot = self.slots[copies[i]]
                # The priority of the road the car came from: collisions happen on the junction or
                # after it, where the snapshot's road is the outgoing one (priority max of both).
                prio = float(slot.scenario.prio(slot.spec[batch.ids[i]].road))
                parts[i, _PART["collide"]] = self.config.reward.collide(prio)
            won = code == _REASON_CODE["finished"]
            parts[won, _PART["finish"]] = self.config.reward.finish(batch.b_type[won])
            if self.config.reward.timeout == "forfeit_finish":
                cut = code == _REASON_CODE["timeout"]
                parts[cut, _PART["finish"]] = -self.config.reward.finish(batch.b_type[cut])
        rewards = parts[:, _PART["finish"]] + parts[:, _PART["collide"]] + parts[:, _PART["impede"]]
        joint = np.bincount(batch.copy, weights=rewards, minlength=k_count) + flow

        # Book-keeping per slot: outcome, ended agents, new arrivals, episode over.
        # Returns: an agent's entry from its first action on, in batch order; a zero reward leaves a sum
        # as it is (x + 0.0 == x: a sum is never -0.0), so only the others are added.
        first_action = ~cars.scored[agents.car]
        if first_action.any():
            for i in np.flatnonzero(first_action).tolist():
                self.slots[copies[i]].outcome.returns[batch.ids[i]] = 0.0
            cars.scored[agents.car] = True
        scored = np.flatnonzero(rewards)
        for i, r in zip(scored.tolist(), rewards[scored].tolist(), strict=True):
            self.slots[copies[i]].outcome.returns[batch.ids[i]] += r
        impedes = np.bincount(batch.copy[parts[:, _PART["impede"]] < 0], minlength=k_count).tolist()
        for i in np.flatnonzero(code).tolist():
            a, k, reason = batch.ids[i], copies[i], reasons[i]
            out = self.slots[k].outcome
            out.end_reasons[a] = reason
            cars.state[agents.car[i]] = ENDED
            self._agents = None
            if reason == "finished":
                out.finish_times_s[a] = self._time_s
                self.backend.release(a, k)
        agents_per_copy = np.bincount(batch.copy, minlength=k_count).tolist()
        active_per_copy = np.bincount(cars.copy[cars.state == ACTIVE], minlength=k_count).tolist()
        hard_brake_list, zone_brake_list = hard_brakes.tolist(), zone_brakes.tolist()
        acting_list = acting.tolist()
        collisions: list[list[tuple[str, str]]] = []
        for k, slot in enumerate(self.slots):
            ev = events.copies[k]
            collisions.append(ev.collision_pairs)
            if slot.over:
                continue
            # Collisions count in every running episode, also while it waits for its next car to enter.
            out = slot.outcome
            out.collisions += len(ev.collision_pairs)
            if acting_list[k]:
                out.hard_brakes += hard_brake_list[k]
                out.hard_brakes_merge_zone += zone_brake_list[k]
                out.decision_steps += 1
                out.agent_steps += agents_per_copy[k]
                out.impedes += impedes[k]
            added = self._admit(k, ev) if ev.departed else 0
            self._settle(k, active_per_copy[k] + added > 0)
        return StepResult(
            rewards=rewards,
            reward_parts=parts,
            end_reason=tuple(reasons),
            applied=np.asarray(applied, dtype=np.int64),
            joint_reward=joint,
            collisions=collisions,
            hard_brakes=hard_brakes,
            hard_brakes_merge_zone=zone_brakes,
            hard_brake_ids=hard_brake_ids,
        )

    @staticmethod
    def _row_copy(snap: TrafficSnapshot) -> IntArray:
        """Each row's copy (all 0 in a one-copy snapshot, which has none)."""
        return snap.copy if snap.copy is not None else np.zeros(len(snap), dtype=np.int64)

    def _copy_of(self, snap: TrafficSnapshot, rows: npt.ArrayLike) -> IntArray:
        r = np.asarray(rows, dtype=np.int64)
        if snap.copy is None:
            return np.zeros(r.shape, dtype=np.int64)
        return np.asarray(snap.copy[r], dtype=np.int64)

    def release_slot(self, k: int) -> None:
        """Slot k's episode is over: its cars leave SUMO so that they cost nothing until the next reset."""
        self.backend.clear_copy(k)

    def close(self) -> None:
        if self._backend is not None:
            self._backend.close()
            self._backend = None
        self._closed = True


def _route_tables(site: MergeSite) -> tuple[dict[str, int], FloatArray, npt.NDArray[np.bool_], FloatArray]:
    """What ``_read_snapshot`` looks a car up in, by its origin (MAIN or MERGE) and the edge it is on.

    (edge id -> code, start (2, E + 1), incoming (2, E + 1), limit (2, E + 1)): for every edge of either
    approach's route (junction-internal ones included), the distance of its start to the merge point
    along that origin's route (``MergeSite.distance_table``; a car at lane position ``pos`` is ``start -
    pos`` before it), whether it lies before the merge point (the car is still on its own road, MAIN or
    MERGE; after it the road is OUT), and its lane's speed limit (a junction lane
    takes the limit of the lane it leads onto: SUMO sets its speed from its curvature, not a sign). On a
    lane drop both approaches share the last edges and differ only by origin. The last column is for an
    edge on no route (a car SUMO sent elsewhere): past the merge point at its start, the outgoing limit.
    """
    routes = (site.route("main"), site.route("merge"))
    code: dict[str, int] = {}
    for route in routes:
        for lane in route:
            code.setdefault(lane.edge_id, len(code))
    unknown = len(code)
    start = np.zeros((2, unknown + 1))
    incoming = np.zeros((2, unknown + 1), dtype=np.bool_)
    limit = np.full((2, unknown + 1), site.out[0].speed_limit_mps)
    for origin, route in zip((MAIN, MERGE), routes, strict=True):
        onward = site.out[0].speed_limit_mps
        for lane in reversed(route):  # backwards: a junction lane takes the next ordinary lane's limit
            if not lane.internal:
                onward = lane.speed_limit_mps
            c = code[lane.edge_id]
            start[origin, c] = lane.start_to_merge_m
            incoming[origin, c] = lane.start_to_merge_m > 0.0
            limit[origin, c] = onward
    return code, start, incoming, limit


_REASON_BY_CODE: tuple[str, ...] = ("", *END_REASONS)
_REASON_CODE = {reason: code for code, reason in enumerate(_REASON_BY_CODE)}
_COLLIDED, _REMOVED, _FINISHED = _REASON_CODE["collided"], _REASON_CODE["removed"], _REASON_CODE["finished"]


def _copy_runs(copy: IntArray) -> list[tuple[int, int, int]]:
    """(copy, lo, hi) for each run of equal entries in ``copy`` (a batch comes copy by copy)."""
    if len(copy) == 0:
        return []
    starts = np.flatnonzero(np.diff(copy)) + 1
    lo = [0, *starts.tolist()]
    hi = [*starts.tolist(), len(copy)]
    return list(zip(copy[lo].tolist(), lo, hi, strict=True))


def _checked_actions(batch: AgentBatch, actions: npt.ArrayLike) -> IntArray:
    """Actions as int64 (n,), or a ValueError naming the first bad one's agent and the time."""
    raw = np.asarray(actions)
    n = len(batch)
    if raw.shape != (n,):
        raise ValueError(f"{raw.shape} actions for {n} agents")
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    if raw.dtype.kind not in "iu":
        bad = 0
        for i, v in enumerate(raw.tolist()):
            if isinstance(v, bool) or not isinstance(v, int):
                bad = i
                break
        else:
            raw = raw.astype(np.int64)
        if raw.dtype.kind not in "iu":
            raise ValueError(
                f"invalid action {raw[bad]!r} for agent {batch.ids[bad]!r} at t = {batch.time_s:.1f} s: "
                f"expected an int in [0, {N_ACTIONS})"
            )
    out = raw.astype(np.int64)
    i = _first_outside(out, N_ACTIONS)
    if i >= 0:
        raise ValueError(
            f"invalid action {int(out[i])} for agent {batch.ids[i]!r} at t = {batch.time_s:.1f} s: "
            f"expected an int in [0, {N_ACTIONS})"
        )
    return out


@kernel
def _first_outside(actions, n_actions):
    """The first index whose action is not in [0, n_actions), or -1."""
    for i in range(actions.shape[0]):
        if not 0 <= actions[i] < n_actions:
            return i
    return -1


@kernel
def _all_allowed(masks, actions):
    """Whether each agent's action (all in range: ``_checked_actions``) is allowed by its mask row."""
    for i in range(actions.shape[0]):  # noqa: SIM110 (numba compiles the loop, not a generator in all())
        if masks[i, actions[i]] == 0:
            return False
    return True


@kernel
def _next_speeds(speed, egos, accel, step_s):
    """The speed (m/s) each agent is told to reach in this step: v + a·dt, at least 0, as
    ``np.maximum(v + a * dt, 0.0)`` gives it (a NaN stays NaN, -0.0 becomes 0.0)."""
    out = np.empty(egos.shape[0])
    for i in range(egos.shape[0]):
        v = speed[egos[i]] + accel[i] * step_s
        out[i] = v if v > 0.0 or v != v else 0.0
    return out


@kernel
def _hard_brakes(
    egos,
    agent_brake,
    accel,
    car_of_row,
    acting,
    car_copy,
    car_state,
    rows_before,
    copy_before,
    dist_before,
    zone_m,
):
    """The step's hard brakes as rows of the step's first snapshot: the agents' (``agent_brake``, batch
    order), then those of the cars now braking at ``HARD_BRAKE_DETECT_MPS2`` or harder (rows of the new
    snapshot, in order) that are no agents, drive in an acting copy and were on the road before.

    Returns (rows, their copies, within ``zone_m`` of the merge point, brakes per copy, of those within
    ``zone_m`` per copy); ``acting`` has one entry per copy."""
    rows = np.empty(egos.shape[0] + accel.shape[0], dtype=np.int64)
    m = 0
    for i in range(egos.shape[0]):
        if agent_brake[i]:
            rows[m] = egos[i]
            m += 1
    for r in range(accel.shape[0]):
        if accel[r] <= HARD_BRAKE_DETECT_MPS2:
            c = car_of_row[r]
            if acting[car_copy[c]] and car_state[c] != ACTIVE and rows_before[c] >= 0:
                rows[m] = rows_before[c]
                m += 1
    rows = rows[:m].copy()
    copy = np.empty(m, dtype=np.int64)
    in_zone = np.empty(m, dtype=np.bool_)
    per_copy = np.zeros(acting.shape[0], dtype=np.int64)
    zone_per_copy = np.zeros(acting.shape[0], dtype=np.int64)
    for i in range(m):
        copy[i] = copy_before[rows[i]]
        in_zone[i] = np.abs(dist_before[rows[i]]) <= zone_m
        per_copy[copy[i]] += 1
        if in_zone[i]:
            zone_per_copy[copy[i]] += 1
    return rows, copy, in_zone, per_copy, zone_per_copy


@kernel
def _end_codes(collided, row, dist, finish_below_m, otherwise):
    """Each agent's end reason (``_REASON_CODE``), the first that holds: collided, removed (no ``row`` in
    the new snapshot), finished (its distance to the merge point at or below ``finish_below_m``), else
    ``otherwise`` (timeout, or going on)."""
    code = np.empty(collided.shape[0], dtype=np.int64)
    for i in range(collided.shape[0]):
        if collided[i]:
            code[i] = _COLLIDED
        elif row[i] < 0:
            code[i] = _REMOVED
        elif dist[row[i]] <= finish_below_m:
            code[i] = _FINISHED
        else:
            code[i] = otherwise
    return code


@kernel
def _penalty_parts(parts, copy, egos, flow, impeded_by, n_rows, impede_penalty, flow_part, impede_part):
    """Into ``parts`` (agents x reward parts): each agent's copy's ``flow`` penalty, and ``impede_penalty``
    times the hard brakes it caused (``impeded_by``: the culprits' rows, one per brake)."""
    culprits = np.zeros(n_rows, dtype=np.int64)
    for r in impeded_by:
        culprits[r] += 1
    for i in range(copy.shape[0]):
        parts[i, flow_part] = flow[copy[i]]
        parts[i, impede_part] = impede_penalty * culprits[egos[i]]


def _impeding_vehicles(before: TrafficSnapshot, brake_rows: IntArray) -> IntArray:
    """For each hard-braking vehicle, the nearest vehicle ahead of it on either lane (within sight, same
    copy): their rows in ``before`` (one per brake that has one)."""
    if len(brake_rows) == 0:
        return np.zeros(0, dtype=np.int64)
    ahead, _ = nearest_ahead(before, brake_rows, any_lane=True, level_counts=True, max_ahead_m=VISIBILITY_M)
    return np.asarray(ahead[ahead != NO_LEADER], dtype=np.int64)


def geometric_collisions(
    snap: TrafficSnapshot, origin: IntArray, joined_past_m: FloatArray | float = 0.0
) -> list[tuple[int, int]]:
    """Rows (i, j), i < j, in order, of cars of one copy whose bodies overlap on one road.

    A body spans [front, front + length] in distance to the merge point; overlapping means a bumper gap
    below zero, SUMO's own criterion with ``--collision.mingap-factor 0``. A car drives on the lanes of
    its incoming road (``origin``: MAIN or MERGE) until its lane joins the outgoing one,
    ``joined_past_m`` past the merge point (per car or one value: the junction's internal lane of its
    road; 0 for a net without one). So two overlapping cars collide when they came from the same road,
    or when both fronts are past the point where their lanes joined. Before that the two roads' cars are
    side by side, however close in projection; in the junction SUMO's own check
    (``--collision.check-junctions``) sees when their shapes touch. Counting every projected overlap
    inside the junction called near misses collisions: 3 of 100 paper-suite episodes (own-lane mask,
    IDM ego) where the cars came within 0.6 m in projection while their lanes were still apart, and the
    leader pulled away.

    Sorted by (copy, distance) only neighbours closer than the longest car can overlap, so this costs
    O(n log n) per step rather than an n x n matrix (measured on 256 cars in 16 copies: 0.07 ms; the
    matrix took 0.83 ms, about as much as SUMO's step of those cars).
    """
    n = len(snap)
    if n < 2:
        return []
    d = snap.dist_to_merge_m
    copy = snap.copy if snap.copy is not None else np.zeros(n, dtype=np.int64)
    order = snap.by_distance.order  # by (copy, distance), shared with the step's relations and grids
    joined_past = np.asarray(joined_past_m, dtype=np.float64)
    if joined_past.shape != d.shape:  # one value for every car
        joined_past = np.broadcast_to(joined_past, d.shape)
    pairs = _overlapping_pairs(
        order,
        np.ascontiguousarray(d, dtype=np.float64),
        np.ascontiguousarray(copy, dtype=np.int64),
        np.ascontiguousarray(snap.length_m, dtype=np.float64),
        np.ascontiguousarray(origin, dtype=np.int64),
        np.ascontiguousarray(joined_past),
        snap.longest_m,
    )
    return sorted(zip(pairs[:, 0].tolist(), pairs[:, 1].tolist(), strict=True))


@kernel
def _overlapping_pairs(order, d, copy, length, origin, joined_past, reach):
    """(pairs, 2) rows (lower, higher) of ``geometric_collisions``' colliding pairs, in scan order. Sorted
    by (copy, distance), each car only meets the next ones of its copy until one is farther than
    ``reach`` (the longest car) ahead of it."""
    n = order.shape[0]
    found = np.empty((0, 2), dtype=np.int64)
    for count_only in (True, False):
        m = 0
        for p in range(n):
            i = order[p]
            for q in range(p + 1, n):
                j = order[q]
                if copy[j] != copy[i] or d[j] - d[i] > reach:
                    break
                one_road = origin[i] == origin[j] or (d[i] < -joined_past[i] and d[j] < -joined_past[j])
                if one_road and d[i] < d[j] + length[j] and d[j] < d[i] + length[i]:
                    if not count_only:
                        found[m, 0] = min(i, j)
                        found[m, 1] = max(i, j)
                    m += 1
        if count_only:
            found = np.empty((m, 2), dtype=np.int64)
    return found


def _empty_snapshot() -> TrafficSnapshot:
    z = np.zeros(0)
    return TrafficSnapshot((), np.zeros(0, dtype=np.int64), z, z, z, z, z)


def placeholder_mask() -> npt.NDArray[np.int8]:
    """The action mask handed back with an agent's last observation: one action, never used."""
    mask = np.zeros(N_ACTIONS, dtype=np.int8)
    mask[0] = 1
    return mask


# -- the one episode loop --------------------------------------------------------------------------


class EpisodeObserver(Protocol):
    """Hooks of ``run_episodes``; ``job`` is the scenario's index in the list given to it."""

    def decided(self, engine: MergeEngine, jobs: Sequence[int], batch: AgentBatch, actions: IntArray) -> None:
        """Before a step: the actions chosen for ``batch`` (``jobs[k]``: the job in slot k)."""

    def stepped(
        self,
        engine: MergeEngine,
        jobs: Sequence[int],
        batch: AgentBatch,
        actions: IntArray,
        result: StepResult,
    ) -> None:
        """After the step."""

    def ended(self, engine: MergeEngine, slot: int, job: int, outcome: EpisodeOutcome) -> None:
        """Slot ``slot``'s episode (job ``job``) is over; ``engine.snapshot`` still shows its last state."""


AssignPolicy = Callable[[int, str], int]
"""(job, agent id) -> index of the policy that drives that agent."""


def iter_episodes(
    engine: MergeEngine,
    scenarios: Sequence[Scenario],
    assign_policy: AssignPolicy,
    policies: Sequence[Policy],
    observer: EpisodeObserver | None = None,
    sumo_args: Callable[[int], Sequence[str]] | None = None,
) -> Iterator[tuple[int, EpisodeOutcome]]:
    """Run every scenario to its end, ``engine.copies`` at a time; yield (job, outcome) in job order.

    ``sumo_args(job)``: SUMO options for that job's run (only with one copy: a run holds all copies).
    """
    if sumo_args is not None and engine.copies != 1:
        raise ValueError("per-scenario SUMO options need an engine with one copy")
    k_max = engine.copies
    for start in range(0, len(scenarios), k_max):
        jobs = list(range(start, min(start + k_max, len(scenarios))))
        args = sumo_args(jobs[0]) if sumo_args is not None else ()
        engine.reset([scenarios[j] for j in jobs], args)
        assigned: list[dict[str, int]] = [{} for _ in jobs]
        reported: set[int] = set()
        while True:
            for k in range(len(jobs)):
                if k not in reported and engine.over(k):
                    reported.add(k)
                    if observer is not None:
                        observer.ended(engine, k, jobs[k], engine.outcome(k))
                    engine.release_slot(k)
            if len(reported) == len(jobs):
                break
            batch = engine.observe()
            batch.job = np.asarray(jobs, dtype=np.int64)[batch.copy]
            actions = np.zeros(len(batch), dtype=np.int64)
            if len(batch):
                which = np.empty(len(batch), dtype=np.int64)
                for i, (a, k) in enumerate(zip(batch.ids, batch.copy.tolist(), strict=True)):
                    p = assigned[k].get(a)
                    if p is None:
                        p = assigned[k][a] = assign_policy(jobs[k], a)
                    which[i] = p
                for p in np.unique(which).tolist():
                    rows = np.flatnonzero(which == p)
                    actions[rows] = policies[p].act(batch, rows)
            if observer is not None:
                observer.decided(engine, jobs, batch, actions)
            result = engine.step(actions)
            if observer is not None:
                observer.stepped(engine, jobs, batch, actions, result)
        for k, j in enumerate(jobs):
            yield j, engine.outcome(k)


def run_episodes(
    engine: MergeEngine,
    scenarios: Sequence[Scenario],
    assign_policy: AssignPolicy,
    policies: Sequence[Policy],
    observer: EpisodeObserver | None = None,
    sumo_args: Callable[[int], Sequence[str]] | None = None,
) -> list[EpisodeOutcome]:
    """Every scenario's outcome, in scenario order (``iter_episodes``)."""
    return [o for _, o in iter_episodes(engine, scenarios, assign_policy, policies, observer, sumo_args)]


__all__ = [
    "DEFAULT_MAX_EPISODE_S",
    "DEFAULT_SAFETY_MASK",
    "END_REASONS",
    "SAFETY_MASKS",
    "AgentBatch",
    "EnvConfig",
    "EpisodeObserver",
    "EpisodeOutcome",
    "MergeEngine",
    "Policy",
    "SafetyMask",
    "StepResult",
    "geometric_collisions",
    "is_perfect",
    "is_success",
    "iter_episodes",
    "placeholder_mask",
    "run_episodes",
    "with_safety_mask",
]
