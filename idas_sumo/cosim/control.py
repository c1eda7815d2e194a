"""The automated cars of a co-simulation, driven with the engine's own pieces.

The episode engine (env/engine.py) runs scenarios whose every car it knows in advance; in a
co-simulation SUMO inserts the cars. So this adapter reads every car SUMO has on the road each step,
places it relative to the merge point as the engine does (``Routes.place``), builds the engine's
``TrafficSnapshot``, gives each automated car the engine's masks (``front_cars``, ``action_masks``) and
asks the policy for all of them in one ``AgentBatch``: the same observation, masks, actions and speed
command an agent gets in an episode. SUMO-driven cars are other cars in the snapshot like any other.

The merge's lanes are those the engine models: each approach's lane to the merge point and the lane
it goes on in (``MergeSite.route``). On a net with multi-lane roads the other lanes' cars are not in the
snapshot (as in an episode, where no car drives there), and an automated car that SUMO inserted on
another lane is driven by SUMO until it is on one of the merge's lanes. From then on it drives with
the engine's lane-keeping mode, from acceleration 0 (as an agent does when it enters), and is handed back to SUMO's model once it is ``FINISH_DISTANCE_PAST_MERGE_M`` past the merge point (where an
episode's agent finishes). Its driver type is ``b_type`` (0: neutral, by default); its priority is its
road's (1 on the main road, the merging road 0, or 1 too where both roads have the same SUMO priority).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from idas_sumo.env.actions import (
    DEFAULT_SAFETY_MASK,
    MaskInputs,
    SafetyMask,
    action_masks,
    candidate_accelerations,
    closest_allowed_action,
    next_acceleration,
)
from idas_sumo.env.collisions import geometric_collisions
from idas_sumo.env.contracts import AgentBatch, Policy
from idas_sumo.env.front_cars import front_cars
from idas_sumo.env.outcome import HARD_BRAKE_DETECT_MPS2
from idas_sumo.env.rewards import FINISH_DISTANCE_PAST_MERGE_M
from idas_sumo.env.routes import Routes
from idas_sumo.env.snapshot import MAIN, MERGE, OUT, TrafficSnapshot
from idas_sumo.sim.backend import STEP_LENGTH_S, VEHICLE_LENGTH_M
from idas_sumo.sim.batch import BatchStates
from idas_sumo.sim.flows import FlowStates
from idas_sumo.sim.merge_detect import MergeSite

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]


@dataclass
class StepCounts:
    """What the adapter counted in one step (the engine's own counts, beside SUMO's)."""

    hard_brakes: int = 0
    """Cars that started braking at ``HARD_BRAKE_DETECT_MPS2`` or harder in this step."""
    crossed: int = 0
    """Cars that passed the merge point in this step (first seen on the road after it)."""
    geometric_collisions: int = 0
    """Pairs with an automated car whose bodies overlap, that SUMO did not report (both removed)."""


@dataclass(frozen=True)
class Commands:
    """The adapter's orders for the next step."""

    take: tuple[str, ...]
    """Automated cars that come under control now (before their first speed command)."""
    ids: tuple[str, ...]
    speeds_mps: FloatArray
    release: tuple[str, ...]
    remove: tuple[str, ...]


def _origin(ids: tuple[str, ...]) -> IntArray:
    """Each car's incoming road from its flow's name (SUMO names a flow's cars ``FLOW.N``)."""
    return np.fromiter((MERGE if v.startswith("merge.") else MAIN for v in ids), np.int64, len(ids))


def _rows(snap: TrafficSnapshot, rows: IntArray) -> TrafficSnapshot:
    """The snapshot of only these rows."""
    return TrafficSnapshot(
        ids=tuple(snap.ids[i] for i in rows.tolist()),
        road=snap.road[rows],
        dist_to_merge_m=snap.dist_to_merge_m[rows],
        speed_mps=snap.speed_mps[rows],
        accel_mps2=snap.accel_mps2[rows],
        length_m=snap.length_m[rows],
        speed_limit_mps=snap.speed_limit_mps[rows],
    )


class AutomatedDriver:
    """Drives a co-simulation's automated cars with ``policy``, one batch per step, and counts the step
    (every car: also with no automated car, where ``policy`` may be None and nothing is commanded)."""

    def __init__(
        self,
        site: MergeSite,
        policy: Policy | None,
        safety_mask: SafetyMask = DEFAULT_SAFETY_MASK,
        b_type: float = 0.0,
    ) -> None:
        self.policy = policy
        self.safety_mask: SafetyMask = safety_mask
        self.b_type = b_type
        self._routes = Routes(site)
        equal = site.main.road.priority == site.merge.road.priority
        self._prio_by_road = np.array([1.0, 1.0 if equal else 0.0, 1.0])  # MAIN, MERGE, OUT
        self.accel: dict[str, float] = {}
        """The acceleration each automated car under control drives with (m/s²)."""
        self.waiting: set[str] = set()
        """Automated cars on the road not yet on the merge's lanes (SUMO drives them until they are)."""
        self._lanes: dict[str, set[int]] = {}
        for side in ("main", "merge"):
            for lane in site.route(side):
                self._lanes.setdefault(lane.edge_id, set()).add(lane.lane_index)
        self._shared_lanes = bool(site.shared_lanes)
        self._braking: set[str] = set()
        self._crossed: set[str] = set()
        self.snapshot: TrafficSnapshot | None = None

    def take(self, vehicle_ids: list[str]) -> None:
        """Automated cars that departed this step: each comes under control (at acceleration 0) from the
        first step it is on the merge's lanes."""
        self.waiting.update(vehicle_ids)

    def _snapshot(self, states: FlowStates) -> tuple[TrafficSnapshot, IntArray]:
        n = len(states.ids)
        batch_states = BatchStates(
            ids=states.ids,
            copy=np.zeros(n, dtype=np.int64),
            vehicle=np.zeros(n, dtype=np.int64),
            edge=states.edge,
            edge_index=np.full(n, -1, dtype=np.int64),
            lane_pos_m=states.lane_pos_m,
            speed_mps=states.speed_mps,
            accel_mps2=states.accel_mps2,
            bounds=np.array([0, n], dtype=np.int64),
            lane_index=states.lane_index if self._shared_lanes else None,
        )
        origin, road, dist, limit = self._routes.place(batch_states, _origin(states.ids))
        snap = TrafficSnapshot(
            ids=states.ids,
            road=road,
            dist_to_merge_m=dist,
            speed_mps=states.speed_mps,
            accel_mps2=states.accel_mps2,
            length_m=np.full(n, VEHICLE_LENGTH_M),
            speed_limit_mps=limit,
        )
        return snap, origin

    def _on_lanes(self, states: FlowStates) -> IntArray | None:
        """The rows of the cars on the merge's lanes (None: all of them, on a merge of one-lane roads)."""
        if states.lane_index is None:
            return None
        lanes = self._lanes
        return np.array(
            [
                i
                for i, (edge, lane) in enumerate(zip(states.edge, states.lane_index.tolist(), strict=True))
                if lane in lanes.get(edge, ())
            ],
            dtype=np.int64,
        )

    def step(self, states: FlowStates, time_s: float) -> tuple[Commands, StepCounts]:
        """Read the step's traffic; count; the speeds of the automated cars for the next step."""
        snap, origin = self._snapshot(states)
        counts = self._count(snap)  # every car, on the merge's lanes or not
        rows = self._on_lanes(states)
        if rows is not None:
            snap, origin = _rows(snap, rows), origin[rows]
        self.snapshot = snap
        on_road = set(states.ids)
        self.waiting &= on_road
        if len(self.accel) > len(on_road) or self.waiting:
            self.accel = {v: a for v, a in self.accel.items() if v in on_road}
        new = tuple(v for v in snap.ids if v in self.waiting)
        for vid in new:
            self.waiting.discard(vid)
            self.accel[vid] = 0.0
        controlled = np.fromiter((v in self.accel for v in snap.ids), np.bool_, len(snap))
        remove = self._overlaps(snap, origin, controlled)
        counts.geometric_collisions = len(remove) // 2
        finished = controlled & (snap.dist_to_merge_m < -FINISH_DISTANCE_PAST_MERGE_M)
        release = tuple(snap.ids[i] for i in np.flatnonzero(finished).tolist())
        for vid in (*release, *remove):
            self.accel.pop(vid, None)
        gone = set(remove)
        egos = np.array(
            [i for i in np.flatnonzero(controlled & ~finished).tolist() if snap.ids[i] not in gone],
            dtype=np.int64,
        )
        ids = tuple(snap.ids[i] for i in egos.tolist())
        speeds = self._act(snap, egos, ids, controlled, time_s) if len(egos) else np.zeros(0)
        return Commands(new, ids, speeds, release, tuple(remove)), counts

    def _count(self, snap: TrafficSnapshot) -> StepCounts:
        hard = {snap.ids[i] for i in np.flatnonzero(snap.accel_mps2 <= HARD_BRAKE_DETECT_MPS2).tolist()}
        onsets = len(hard - self._braking)
        self._braking = hard
        out = {snap.ids[i] for i in np.flatnonzero(snap.road == OUT).tolist()}
        crossed = len(out - self._crossed)
        self._crossed |= out
        return StepCounts(hard_brakes=onsets, crossed=crossed)

    def _overlaps(
        self, snap: TrafficSnapshot, origin: IntArray, controlled: npt.NDArray[np.bool_]
    ) -> list[str]:
        """Cars of pairs with an automated car whose bodies overlap (the engine's geometric check, for the
        collisions SUMO's own check misses with its speed checks off); SUMO-driven pairs are SUMO's."""
        if not controlled.any():
            return []
        pairs = geometric_collisions(snap, origin, self._routes.via_length_m[origin])
        out: list[str] = []
        for i, j in pairs:
            if controlled[i] or controlled[j]:
                out += [snap.ids[i], snap.ids[j]]
        return list(dict.fromkeys(out))

    def _act(
        self,
        snap: TrafficSnapshot,
        egos: IntArray,
        ids: tuple[str, ...],
        controlled: npt.NDArray[np.bool_],
        time_s: float,
    ) -> FloatArray:
        prev = np.array([self.accel[v] for v in ids], dtype=np.float64)
        gap, leader_speed, ease_in = front_cars(snap, egos, self.safety_mask, controlled)
        masks = action_masks(
            MaskInputs(
                prev_accel_mps2=prev,
                speed_mps=snap.speed_mps[egos],
                speed_limit_mps=snap.speed_limit_mps[egos],
                gap_m=gap,
                leader_speed_mps=leader_speed,
                ease_in=ease_in,
            )
        )
        n = len(egos)
        batch = AgentBatch(
            ids=ids,
            copy=np.zeros(n, dtype=np.int64),
            egos=egos,
            prev_accel=prev,
            masks=masks,
            snapshot=snap,
            b_prio=self._prio_by_road[snap.road[egos]],
            b_type=np.full(n, self.b_type),
            time_s=time_s,
        )
        if self.policy is None:
            raise ValueError("automated cars on the road and no policy to drive them")
        actions = np.asarray(self.policy.act(batch, np.arange(n)), dtype=np.int64)
        rows = np.arange(n)
        allowed = masks[rows, actions].astype(bool)
        if not allowed.all():  # as the engine: a masked request becomes the closest allowed action
            wanted = candidate_accelerations(prev)[rows, actions]
            actions = np.where(allowed, actions, closest_allowed_action(wanted, prev, masks))
        accel = next_acceleration(prev, actions)
        for vid, a in zip(ids, accel.tolist(), strict=True):
            self.accel[vid] = a
        return np.maximum(snap.speed_mps[egos] + accel * STEP_LENGTH_S, 0.0)


__all__ = ["AutomatedDriver", "Commands", "StepCounts"]
