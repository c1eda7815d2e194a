"""The episode engine: K merge episodes side by side in one SUMO run, every agent of every copy at once.

``MergeEngine`` owns K episode *slots* over a ``BatchBackend`` (K copies of the merge net in one libsumo
simulation, sim/batch.py; each copy moves exactly as its scenario alone). Each step it reads SUMO once,
builds one copy-aware ``TrafficSnapshot`` (env/snapshot.py: pairwise relations never cross copies) and
hands every active agent of every copy to the policies as one ``AgentBatch``. A step then reads as
HighwayEnv's: simulate (apply the masked actions, advance SUMO) -> observe (hard brakes, end reasons) ->
score (named reward terms, env/scoring.py) -> terminate -> info (book-keeping into each slot's outcome).
``run_episodes`` (env/episodes.py) is the one episode loop over it.

A slot follows the single-episode rules exactly: an agent acts from the step it enters; a copy with no
agent on the road but controlled cars still to come only lets time run (nothing is scored, as when one
episode waits for its first car); a copy is over when every controlled car finished, collided or left,
or time ran out.
"""

from __future__ import annotations

import contextlib
import dataclasses
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import NamedTuple

import numpy as np
import numpy.typing as npt

from idas_sumo.env.actions import (
    DEFAULT_SAFETY_MASK,
    HARD_BRAKE,
    N_ACTIONS,
    SAFETY_MASKS,
    MaskInputs,
    SafetyMask,
    action_masks,
    candidate_accelerations,
    closest_allowed_action,
    next_acceleration,
)
from idas_sumo.env.cars import ACTIVE, ENDED, WAITING, _Agents, _Cars, _empty_snapshot, _Slot
from idas_sumo.env.collisions import geometric_collisions
from idas_sumo.env.config import DEFAULT_MAX_EPISODE_S, EnvConfig, with_safety_mask
from idas_sumo.env.contracts import AgentBatch, Policy, StepResult, placeholder_mask
from idas_sumo.env.front_cars import front_cars, observe_own_lane, observe_own_lane_obs, own_lane_action_masks
from idas_sumo.env.kernels import (
    _REASON_BY_CODE,
    _REASON_CODE,
    HardBrakes,
    _agent_values,
    _allowed_step,
    _book_counts,
    _checked_actions,
    _hard_brakes,
    _next_speeds,
    _step_ends,
)
from idas_sumo.env.layout import OBS_DIM
from idas_sumo.env.observation import build_observations
from idas_sumo.env.outcome import END_REASONS, EpisodeOutcome, is_perfect, is_success
from idas_sumo.env.rewards import FINISH_DISTANCE_PAST_MERGE_M, MERGE_ZONE_RADIUS_M, REWARD_PART_NAMES
from idas_sumo.env.routes import Routes
from idas_sumo.env.scenario import Road, Scenario, VehicleSpec
from idas_sumo.env.scoring import (
    Scores,
    StepContext,
    check_terms,
    impeding_vehicles,
    nobody_ended_scores,
    quiet_scores,
    score,
)
from idas_sumo.env.snapshot import DistanceOrder, TrafficSnapshot
from idas_sumo.env.solo import _SoloBackend
from idas_sumo.env.state_layout import STATE_SLOTS, critic_states
from idas_sumo.errors import SimulationError
from idas_sumo.sim.backend import (
    STEP_LENGTH_S,
    VEHICLE_LENGTH_M,
    Backend,
    StepEvents,
    make_backend,
    slot_taken,
)
from idas_sumo.sim.batch import BatchBackend, BatchStepEvents
from idas_sumo.sim.frozen import built
from idas_sumo.sim.merge_detect import MergeSite, as_site
from idas_sumo.sim.multinet import MAX_COPIES, copies_run
from idas_sumo.sim.netgen import MergeNet
from idas_sumo.sim.processes import SEED_LIMIT

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]
_IMPEDE = REWARD_PART_NAMES.index("impede")


class _RoadLayout(NamedTuple):
    """``_read_snapshot``'s arrays for the cars on the road, kept while the same cars drive."""

    vehicle: IntArray
    """The backend's ``vehicle`` array they came from (the same object while the same cars drive)."""
    cars: _Cars
    car: IntArray
    row: IntArray
    origin: IntArray
    controlled: npt.NDArray[np.bool_]
    length_m: FloatArray
    longest_m: float


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
        # Checked as the CLI's --copies and --seed are: an out-of-range seed once failed in SUMO, blaming the net.
        if (
            isinstance(copies, bool)
            or not isinstance(copies, int | np.integer)
            or not 1 <= copies <= MAX_COPIES
        ):
            raise ValueError(f"copies must be an integer in [1, {MAX_COPIES}], got {copies!r}")
        if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or not 0 <= seed < SEED_LIMIT:
            raise ValueError(
                f"seed must be an integer in [0, {SEED_LIMIT}) (SUMO's seed range), got {seed!r}"
            )
        if config is not None and not isinstance(config, EnvConfig):
            raise TypeError(f"config must be an EnvConfig, got {type(config).__name__}")
        if gui and copies != 1:
            raise ValueError("sumo-gui shows one simulation: copies must be 1 with gui")
        self.config = config or EnvConfig()
        check_terms(self.config.reward)
        self._paper_terms = self.config.reward.part_names == REWARD_PART_NAMES
        """The paper's four terms, in order: a quiet step's scores are then ``quiet_scores``."""
        self.site = as_site(net, self.config.junction)
        # libsumo holds one simulation per process: when it is taken (another environment is open), run
        # the episodes one at a time in a SUMO child process; a net netconvert cannot copy faithfully
        # (sim/multinet.py) runs them one at a time too. Results do not depend on K.
        if copies > 1 and (slot_taken() or not copies_run(self.site.path, copies)):
            copies = 1
        self.copies = copies
        self._seed = seed
        self._values_cars: tuple[tuple[str, ...], dict[str, int], int, IntArray] | None = None
        """``agent_values``' last ids, their slot's order and first car, and their cars (asked again for
        the same agents step after step)."""
        self._gui = gui
        self.eager_obs = False
        """``observe()`` builds every agent's observation in the same compiled call as the masks (the
        single-world envs, which read them every step; rule-based policies never need them)."""
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
        self._routes = Routes(self.site)
        self.slots: list[_Slot] = []
        self.snapshot = _empty_snapshot()
        self._controlled = np.zeros(0, dtype=np.bool_)
        self._origin = np.zeros(0, dtype=np.int64)
        self._may_overlap = False
        """Whether two bodies of the snapshot may overlap (``any_overlap``): the cross-check looks then."""
        self._row_copies = np.zeros(0, dtype=np.int64)
        """Each snapshot row's copy (zeros with one copy, where the snapshot has no ``copy``)."""
        self._cars = _Cars.of((), lambda k, vid: vid)
        self._car = np.zeros(0, dtype=np.int64)
        """Each snapshot row's car (``_Cars``)."""
        self._layout: _RoadLayout | None = None
        self._agents: _Agents | None = None
        """``observe``'s agents while they stay the same (None: gather them again)."""
        self._batch: AgentBatch | None = None
        self._batch_agents: _Agents | None = None
        self._time_s = 0.0
        self._closed = False
        self._loaded_ahead: tuple[object, ...] | None = None
        """What ``preload`` started (scenarios, SUMO options, config) while no ``observe`` has read it since."""

    # -- episodes ------------------------------------------------------------------------------
    def _make_backend(self) -> BatchBackend | _SoloBackend:
        if self.copies == 1:
            return _SoloBackend(make_backend(self.site, seed=self._seed, gui=self._gui))
        backend = BatchBackend(self.site, copies=self.copies, seed=self._seed)
        self._routes.number_edges(backend.net.edge_ids)
        return backend

    def reset(self, scenarios: Sequence[Scenario], sumo_args: Sequence[str] = ()) -> None:
        """Start one episode per scenario (at most ``copies``), scenario k in slot k."""
        if self._closed:
            raise SimulationError("this engine is closed; create a new one")
        ahead, self._loaded_ahead = self._loaded_ahead, None
        if ahead is not None and ahead == (tuple(scenarios), tuple(sumo_args), self.config):
            return  # ``preload`` started these episodes and nothing has read them since: as a reset leaves them
        if not 1 <= len(scenarios) <= self.copies:
            raise ValueError(f"{len(scenarios)} scenarios for {self.copies} slots")
        if self._backend is None:
            self._backend = self._make_backend()
        self.slots = [_Slot.of(s) for s in scenarios]
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

    def preload(self, scenarios: Sequence[Scenario], sumo_args: Sequence[str] = ()) -> None:
        """``reset`` ahead of its time (a rollout worker's next round, loaded while it waits for its weights):
        the next ``reset`` with the same scenarios, options and config, with no ``observe`` or
        ``release_slot`` before it, then costs nothing; any other reset starts over."""
        self.reset(scenarios, sumo_args)
        self._loaded_ahead = (tuple(scenarios), tuple(sumo_args), self.config)

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

    @contextlib.contextmanager
    def episode_limit(self, max_episode_s: float | None) -> Iterator[None]:
        """Episodes started inside run to ``max_episode_s`` instead of ``config.max_episode_s`` (None: the
        engine's own); the engine's own limit again afterwards."""
        own = self.config
        if max_episode_s is not None:
            self.config = dataclasses.replace(own, max_episode_s=max_episode_s)
        try:
            yield
        finally:
            self.config = own

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

    def agent_values(
        self, k: int, vehicle_ids: Sequence[str]
    ) -> tuple[list[float], list[float], list[float], list[int]]:
        """Speed, acceleration (an agent's: the one it drives with), distance to the merge point and road
        (-1: not on the road) of slot k's vehicles (KeyError: one is not in its scenario), as
        ``single.agent_info`` reads them one by one."""
        cars, snap = self._cars, self.snapshot
        order = self.slots[k].order
        first = int(cars.first[k])
        ids = tuple(vehicle_ids)
        known = self._values_cars
        if known is not None and known[1] is order and known[2] == first and known[0] == ids:
            car = known[3]
        else:
            car = np.array([first + order[v] for v in ids], dtype=np.int64)
            self._values_cars = (ids, order, first, car)
        if not len(snap):
            nothing = [0.0] * len(car)
            return nothing, nothing, nothing, [-1] * len(car)
        # (Filled, not returned: a compiled call's every returned array costs about 0.5 µs of boxing.)
        values, road = np.empty((3, len(car))), np.empty(len(car), dtype=np.int64)
        _agent_values(
            car,
            cars.row,
            cars.admitted,
            cars.accel,
            snap.speed_mps,
            snap.accel_mps2,
            snap.dist_to_merge_m,
            snap.road,
            values,
            road,
        )
        speed, accel, dist = values.tolist()
        return speed, accel, dist, road.tolist()

    def rows_of(self, k: int) -> slice:
        """Slot k's vehicles in ``snapshot``."""
        lo, hi = self._bounds[k], self._bounds[k + 1]
        return slice(int(lo), int(hi))

    def row_and_accel(self, k: int, vehicle_id: str) -> tuple[int, float]:
        """Slot k's ``vehicle_id``: its row in ``snapshot`` and its acceleration (an agent's: the one it
        drives with), or (-1, NaN) when it is not on the road or not in the scenario; one lookup for
        ``row``, ``admitted`` and ``prev_accel`` together."""
        i = self.slots[k].order.get(vehicle_id)
        if i is None:
            return -1, float("nan")
        cars = self._cars
        c = int(cars.first[k]) + i
        r = int(cars.row[c])
        if r < 0:
            return -1, float("nan")
        return r, float(cars.accel[c] if cars.admitted[c] else self.snapshot.accel_mps2[r])

    def car_index(self, k: int, vehicle_id: str) -> int:
        """Slot k's ``vehicle_id`` as a car of this episode's cars (for ``car_rows``; KeyError: not in its
        scenario)."""
        return self._car_of(k, vehicle_id)

    def car_rows(self, cars: IntArray) -> IntArray:
        """Each car's row in ``snapshot`` (-1: not on the road): ``row`` for many cars at once."""
        return self._cars.row[cars]

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

    def _cross_check(self, events: BatchStepEvents) -> None:
        """Add the collisions SUMO did not report: cars of one running episode whose bodies overlap on
        one road (``geometric_collisions``). Both count as collided, as in a SUMO-reported
        collision (their episodes end with r_collide), and leave the road as SUMO's ``--collision.action
        remove`` would take them; the snapshot is then read again without them."""
        if not self._may_overlap:  # (``any_overlap``, found as the snapshot was read: nearly every step)
            return
        snap = self.snapshot
        pairs = geometric_collisions(snap, self._origin, self._routes.via_length_m[self._origin])
        if not pairs:
            return
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
        layout = self._layout
        # What depends only on which cars are on the road is kept while they stay the same (a backend hands
        # out the same ``vehicle`` array then): most steps only read new positions and speeds.
        if layout is None or layout.vehicle is not states.vehicle or layout.cars is not cars:
            if n and int(states.vehicle.min()) < 0:
                bad = states.ids[int(np.argmin(states.vehicle))]
                raise SimulationError(f"vehicle {bad!r} on the road is from no scenario of the engine")
            car = cars.first[copy] + states.vehicle
            row = np.full(len(cars.ids), -1, dtype=np.int64)
            row[car] = np.arange(n)
            length = np.full(n, VEHICLE_LENGTH_M)
            for a in (car, row, length):
                a.flags.writeable = False
            layout = self._layout = _RoadLayout(
                states.vehicle,
                cars,
                car,
                row,
                cars.origin[car],
                cars.controlled[car],
                length,
                float(length.max()) if n else 0.0,
            )
        cars.row = layout.row
        self._car = layout.car
        origin, road, dist, limit, order, sorted_dist, overlap = self._routes.place_in_order(
            states, layout.origin, layout.length_m, layout.longest_m
        )
        self._may_overlap = overlap
        self._bounds = bounds
        self._controlled = layout.controlled
        self._origin = origin
        self._row_copies = copy
        by_distance = built(DistanceOrder, order=order, sorted_dist=sorted_dist, starts=bounds)
        snap = self.snapshot = built(  # (``TrafficSnapshot(...)``, every field given)
            TrafficSnapshot,
            ids=states.ids,
            road=road,
            dist_to_merge_m=dist,
            speed_mps=states.speed_mps,  # (fresh arrays of each read: nobody else holds them)
            accel_mps2=states.accel_mps2,
            length_m=layout.length_m,
            speed_limit_mps=limit,
            copy=copy if len(self.slots) > 1 else None,
            known_copy_bounds=bounds,
            known_longest_m=layout.longest_m,
            known_by_distance=by_distance,
        )
        # Its two ``lazy`` values every step reads, set as their first read would (without its call).
        snap.__dict__.update(by_distance=by_distance, longest_m=layout.longest_m)

    # -- observation ---------------------------------------------------------------------------
    def observe(self) -> AgentBatch:
        """Every active agent of every running slot, in slot then scenario order."""
        self._loaded_ahead = None
        agents = self._agents
        if agents is None:
            agents = self._agents = self._gather_agents()
        cars = self._cars
        snap = self.snapshot
        obs = None
        if self.config.safety_mask == "own_lane" and len(agents.car):  # (the default: one compiled call)
            if self.eager_obs:  # (the observations in the same call)
                obs = np.zeros((len(agents.car), OBS_DIM), dtype=np.float32)
                egos, prev, b_prio, masks, finite, spread = observe_own_lane_obs(
                    snap,
                    self._row_copies,
                    cars.row,
                    cars.accel,
                    agents.car,
                    agents.copy,
                    self._prio_by_road,
                    agents.b_type,
                    obs,
                )
            else:
                egos, prev, b_prio, masks = observe_own_lane(
                    snap, self._row_copies, cars.row, cars.accel, agents.car, agents.copy, self._prio_by_road
                )
        else:
            egos = cars.row[agents.car]
            prev = cars.accel[agents.car]
            masks = self._masks(egos, prev)
            b_prio = self._prio_by_road[agents.copy, snap.road[egos]]
        batch = AgentBatch(
            ids=agents.ids,
            copy=agents.copy,
            egos=egos,
            prev_accel=prev,
            masks=masks,
            snapshot=snap,
            b_prio=b_prio,
            b_type=agents.b_type,
            time_s=self._time_s,
        )
        if obs is not None:
            batch.keep_obs(obs, finite, spread)
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
        origin_prio = self._prio_by_road[copy, cars.origin[car]]
        acting = np.zeros(len(self.slots), dtype=np.bool_)
        acting[copy] = True
        for a in (car, copy, b_type, origin_prio):  # (``acting`` stays writeable: a kernel reads it)
            a.flags.writeable = False  # shared by every batch until the agents change
        return _Agents(
            car=car,
            ids=tuple(map(cars.ids.__getitem__, picked)),
            global_ids=tuple(map(cars.global_ids.__getitem__, picked)),
            copy=copy,
            b_type=b_type,
            origin_prio=origin_prio,
            acting=acting,
            per_copy=np.bincount(copy, minlength=len(self.slots)).tolist(),
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
        if self.config.safety_mask == "own_lane":  # (the default: one compiled call)
            return own_lane_action_masks(snap, egos, prev)
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
        """The car the safety mask keeps its distance to, per ``EnvConfig.safety_mask`` (``front_cars``)."""
        return front_cars(self.snapshot, egos, self.config.safety_mask, self._controlled)

    def state(self, k: int) -> npt.NDArray[np.float32]:
        """Slot k's global state for the centralised critic (layout in ``env/state_layout.py``)."""
        return self.states(np.array([k]))[0]

    def state_slots(self, egos: IntArray) -> IntArray:
        """The state slot (``env/state_layout.py``) of the car at each row ``egos`` of ``snapshot``: its place
        in its scenario, or -1 past STATE_SLOTS (it has none)."""
        cars = self._cars
        car = self._car[egos]
        slot = car - cars.first[cars.copy[car]]
        out: IntArray = np.where(slot < STATE_SLOTS, slot, -1)
        return out

    def states(self, copies: IntArray) -> npt.NDArray[np.float32]:
        """``state(k)`` of each k of ``copies``, one row each, in one compiled call."""
        cars = self._cars
        return critic_states(
            self.snapshot,
            self._bounds,
            copies,
            self._car,
            cars.first,
            cars.b_type,
            cars.state == ACTIVE,
            self._prio_by_road,
        )

    # -- stepping: simulate -> observe -> score -> terminate -> info ----------------------------
    def step(self, actions: npt.ArrayLike) -> StepResult:
        """Apply one action per agent of the last ``observe()`` batch, advance SUMO one step, score it."""
        batch, agents = self._take_batch()
        before, rows_before = self.snapshot, self._cars.row
        applied, events = self._simulate(batch, agents, actions)
        acting = agents.acting
        code, ended, may_brake = self._observe_ends(batch, agents, events, applied)
        brakes = self._observe_brakes(batch, applied, before, rows_before, acting, may_brake)
        if self._paper_terms and not ended:  # (most steps: what ``score`` gives then, without its context)
            if not len(brakes.rows):
                scores = quiet_scores(len(batch), len(self.slots))
            else:
                impeded_by = impeding_vehicles(before, brakes.rows)
                scores = nobody_ended_scores(
                    batch.copy, batch.egos, len(before), len(self.slots), impeded_by, brakes.zone_per_copy
                )
        else:
            scores = self._score(batch, agents, code, before, brakes)
        reasons = self._terminate(batch, agents, code) if ended else ("",) * len(code)
        self._book(batch, agents, scores, brakes, events, acting)
        return StepResult(
            rewards=scores.rewards,
            reward_parts=scores.parts,
            end_reason=reasons,
            applied=np.asarray(applied, dtype=np.int64),
            joint_reward=scores.joint,
            collisions=[events.copies[k].collision_pairs for k in range(len(self.slots))],
            hard_brakes=brakes.per_copy,
            hard_brakes_merge_zone=brakes.zone_per_copy,
            hard_brake_ids=brakes.ids,
            part_names=self.config.reward.part_names,
        )

    def _score(
        self, batch: AgentBatch, agents: _Agents, code: IntArray, before: TrafficSnapshot, brakes: HardBrakes
    ) -> Scores:
        """The step's named reward terms (``score``)."""
        return score(
            StepContext(
                config=self.config.reward,
                copies=len(self.slots),
                copy=batch.copy,
                b_type=batch.b_type,
                b_prio=agents.origin_prio,
                egos=batch.egos,
                end_code=code,
                before=before,
                brakes=brakes.rows,
                zone_brakes=brakes.zone_per_copy,
                impeded_by=impeding_vehicles(before, brakes.rows),
            )
        )

    def _take_batch(self) -> tuple[AgentBatch, _Agents]:
        """The last ``observe()`` batch and its agents, which this step consumes."""
        if self._closed:
            raise SimulationError("step() after close(); create a new engine")
        batch, agents = self._batch, self._batch_agents
        if batch is None or agents is None:
            raise SimulationError("step() without observe() first")
        self._batch = self._batch_agents = None
        return batch, agents

    def _simulate(
        self, batch: AgentBatch, agents: _Agents, actions: npt.ArrayLike
    ) -> tuple[IntArray, BatchStepEvents]:
        """Apply the actions (a masked request replaced by the closest allowed action), advance SUMO one
        step and read where it left every car (collisions SUMO missed included). Returns the applied
        actions and SUMO's events."""
        requested = _checked_actions(batch, actions)
        applied = requested
        if len(batch):
            masks, prev = batch.masks, batch.prev_accel
            speed = self.snapshot.speed_mps
            out = np.empty((2, len(batch)))
            # (One compiled pass, most steps.)
            if _allowed_step(masks, requested, prev, speed, batch.egos, STEP_LENGTH_S, out):
                new_accel, next_speed = out[0], out[1]
            else:
                rows = np.arange(len(batch))
                allowed = masks[rows, requested].astype(bool)
                wanted = candidate_accelerations(prev)[rows, requested]
                applied = np.where(allowed, requested, closest_allowed_action(wanted, prev, masks))
                new_accel = next_acceleration(prev, applied)
                next_speed = _next_speeds(speed, batch.egos, new_accel, STEP_LENGTH_S)
            self.backend.set_speeds(agents.global_ids, next_speed)
            self._cars.accel[agents.car] = new_accel
        events = self.backend.step()
        self._time_s = events.time_s
        self._read_snapshot()
        self._cross_check(events)
        return applied, events

    def _observe_brakes(
        self,
        batch: AgentBatch,
        applied: IntArray,
        before: TrafficSnapshot,
        rows_before: IntArray,
        acting: npt.NDArray[np.bool_],
        may_brake: bool,
    ) -> HardBrakes:
        """The step's hard brakes: agents that chose the hard brake, then SUMO-driven cars of acting copies
        that braked hard on their own, each placed where it was when it decided."""
        k_count = len(self.slots)
        if not may_brake:  # (``_maybe_hard_brakes``: most steps)
            none = np.zeros(k_count, dtype=np.int64)
            return HardBrakes(np.zeros(0, dtype=np.int64), none, none.copy(), [[] for _ in range(k_count)])
        cars = self._cars
        accel = self.snapshot.accel_mps2
        most = len(batch.egos) + len(accel)
        rows, copy = np.empty(most, dtype=np.int64), np.empty(most, dtype=np.int64)
        per_copy = np.zeros((2, k_count), dtype=np.int64)
        m = _hard_brakes(
            batch.egos,
            applied == HARD_BRAKE,
            accel,
            self._car,
            acting,
            cars.copy,
            cars.state,
            rows_before,
            self._row_copy(before),
            before.dist_to_merge_m,
            MERGE_ZONE_RADIUS_M,
            rows,
            copy,
            np.empty(most, dtype=np.bool_),
            per_copy,
        )
        rows = rows[:m]
        ids: list[list[str]] = [[] for _ in range(k_count)]
        for r, k in zip(rows.tolist(), copy[:m].tolist(), strict=True):
            ids[k].append(before.ids[r])
        return HardBrakes(rows, per_copy[0], per_copy[1], ids)

    def _observe_ends(
        self, batch: AgentBatch, agents: _Agents, events: BatchStepEvents, applied: IntArray
    ) -> tuple[IntArray, int, bool]:
        """Each agent's end reason code, the first that holds: collided, removed, finished, else timeout
        (if time is up), else 0 (it goes on); how many ended; and whether the step may have hard brakes
        (``_maybe_hard_brakes``, checked in the same compiled call)."""
        collided = np.zeros(len(batch), dtype=np.bool_)
        if any(ev.collided for ev in events.copies):
            collided[:] = [
                a in events.copies[k].collided for a, k in zip(batch.ids, batch.copy.tolist(), strict=True)
            ]
        code, ended, may_brake = _step_ends(
            collided,
            self._cars.row,
            agents.car,
            self.snapshot.dist_to_merge_m,
            -FINISH_DISTANCE_PAST_MERGE_M,
            _REASON_CODE["timeout" if self.timed_out() else ""],
            applied,
            HARD_BRAKE,
            self.snapshot.accel_mps2,
        )
        return code, int(ended), bool(may_brake)

    def _terminate(self, batch: AgentBatch, agents: _Agents, code: IntArray) -> tuple[str, ...]:
        """End the agents whose code says so: their outcome's end reason, and a finished car leaves our
        control (SUMO drives it off). Returns every agent's end reason ('' while it goes on)."""
        codes = code.tolist()
        reasons = tuple(map(_REASON_BY_CODE.__getitem__, codes))
        copies = batch.copy.tolist()
        for i in [i for i, c in enumerate(codes) if c]:
            a, k, reason = batch.ids[i], copies[i], reasons[i]
            out = self.slots[k].outcome
            out.end_reasons[a] = reason
            self._cars.state[agents.car[i]] = ENDED
            self._agents = None
            if reason == "finished":
                out.finish_times_s[a] = self._time_s
                self.backend.release(a, k)
        return reasons

    def _book(
        self,
        batch: AgentBatch,
        agents: _Agents,
        scores: Scores,
        brakes: HardBrakes,
        events: BatchStepEvents,
        acting: npt.NDArray[np.bool_],
    ) -> None:
        """Into each slot's outcome: returns, counts, new arrivals, and whether its episode is over."""
        cars = self._cars
        k_count = len(self.slots)
        # An agent's entry in the returns from its first action on, in batch order; a zero reward leaves a
        # sum as it is (x + 0.0 == x: a sum is never -0.0), so only the others are added.
        # (One compiled pass for the counts; it marks the first-timers' cars scored.)
        rows, per_copy = np.empty((2, len(batch)), dtype=np.int64), np.zeros((2, k_count), dtype=np.int64)
        n_first, n_scored = _book_counts(
            agents.car,
            cars.scored,
            scores.rewards,
            scores.parts[:, _IMPEDE],
            batch.copy,
            cars.copy,
            cars.state,
            rows,
            per_copy,
        )
        if n_first or n_scored:
            copies = batch.copy.tolist()
            for i in rows[0, :n_first].tolist():
                self.slots[copies[i]].outcome.returns[batch.ids[i]] = 0.0
            scored = rows[1, :n_scored]
            for i, r in zip(scored.tolist(), scores.rewards[scored].tolist(), strict=True):
                self.slots[copies[i]].outcome.returns[batch.ids[i]] += r
        impedes, active_per_copy = per_copy.tolist()
        agents_per_copy = agents.per_copy
        hard_brakes, zone_brakes = brakes.per_copy.tolist(), brakes.zone_per_copy.tolist()
        acting_list = acting.tolist()
        timed_out = self.timed_out()
        copy_events = events.copies
        for k, slot in enumerate(self.slots):  # (counts that are 0 are not added: most are, most steps)
            if slot.over:
                continue
            ev = copy_events[k]
            # Collisions count in every running episode, also while it waits for its next car to enter.
            out = slot.outcome
            if ev.collision_pairs:
                out.collisions += len(ev.collision_pairs)
            if acting_list[k]:
                if hard_brakes[k]:  # (the merging zone's are some of them)
                    out.hard_brakes += hard_brakes[k]
                    out.hard_brakes_merge_zone += zone_brakes[k]
                out.decision_steps += 1
                out.agent_steps += agents_per_copy[k]
                if impedes[k]:
                    out.impedes += impedes[k]
            added = self._admit(k, ev) if ev.departed else 0
            active = active_per_copy[k] + added > 0
            if timed_out or not active or not slot.started:  # (else _settle has nothing to do)
                self._settle(k, active)

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
        self._loaded_ahead = None
        self.backend.clear_copy(k)

    def close(self) -> None:
        if self._backend is not None:
            self._backend.close()
            self._backend = None
        self._closed = True


# The engine and, re-exported from their modules, the names the packages above import from here.
__all__ = [
    "DEFAULT_MAX_EPISODE_S",
    "DEFAULT_SAFETY_MASK",
    "END_REASONS",
    "SAFETY_MASKS",
    "AgentBatch",
    "EnvConfig",
    "EpisodeOutcome",
    "MergeEngine",
    "Policy",
    "SafetyMask",
    "StepResult",
    "geometric_collisions",
    "is_perfect",
    "is_success",
    "placeholder_mask",
    "with_safety_mask",
]
