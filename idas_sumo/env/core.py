"""The adapter between SUMO and the learning code: one episode of the merge, stepped by agent actions.

``MergeSimulation`` owns the backend, turns SUMO's raw vehicle states into a ``TrafficSnapshot``,
applies the masked actions as speed commands, and scores each step with the paper's named reward
parts. Superseded by ``env/engine.py`` (the environments run on ``env/single.py``); its last user is a
test in tests/test_training.py, and it goes when that moves.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import numpy.typing as npt

from idas_sumo.env.actions import (
    HARD_BRAKE,
    N_ACTIONS,
    MaskInputs,
    action_masks,
    candidate_accelerations,
    closest_allowed_action,
    effective_speed_limit,
    next_acceleration,
    safety_bound,
)
from idas_sumo.env.engine import DEFAULT_MAX_EPISODE_S, HARD_BRAKE_DETECT_MPS2, EnvConfig, placeholder_mask
from idas_sumo.env.layout import (
    ACCEL_SCALE_MPS2,
    B_TYPE_SCALE,
    DIST_SCALE_M,
    OBS_DIM,
    SPEED_SCALE_MPS,
    VISIBILITY_M,
)
from idas_sumo.env.observation import build_observations
from idas_sumo.env.rewards import (
    FINISH_DISTANCE_PAST_MERGE_M,
    IMPEDE_PENALTY,
    MERGE_ZONE_RADIUS_M,
    REWARD_PART_NAMES,
    collide_reward,
    finish_reward,
    flow_penalty,
    hard_brakes_in_merge_zone,
)
from idas_sumo.env.scenario import Road, Scenario, VehicleSpec
from idas_sumo.env.snapshot import (
    MAIN,
    MERGE,
    OUT,
    ROAD_NAMES,
    TrafficSnapshot,
    lane_relations,
    leader_speeds,
    leaders,
    other_road_leaders,
)
from idas_sumo.env.state_layout import STATE_DIM, STATE_FEATURES, STATE_SLOTS
from idas_sumo.errors import SimulationError
from idas_sumo.physics.idm import DEFAULT_IDM
from idas_sumo.sim.backend import STEP_LENGTH_S, VEHICLE_LENGTH_M, Backend, VehicleStates, make_backend
from idas_sumo.sim.netgen import MergeNet, read_merge_net

FloatArray = npt.NDArray[np.float64]


@dataclass
class StepOutcome:
    """Everything one step produced, per agent that acted in it."""

    rewards: dict[str, float]
    reward_parts: dict[str, dict[str, float]]
    joint_reward: float
    """Sum of the agents' rewards plus the shared flow penalty (the centralised critic's reward)."""
    terminated: dict[str, bool]
    truncated: dict[str, bool]
    end_reason: dict[str, str]
    """'finished', 'collided', 'removed' or 'timeout' for agents whose episode ended this step."""
    hard_brakes: list[str]
    hard_brakes_merge_zone: int
    collisions: list[tuple[str, str]]
    replaced_actions: dict[str, int]
    """Agents whose requested action was masked, and the action applied instead."""


class MergeSimulation:
    """One merge episode at a time on a SUMO backend (one per process)."""

    def __init__(
        self,
        net: MergeNet | str | Path,
        seed: int = 0,
        config: EnvConfig | None = None,
        gui: bool = False,
    ) -> None:
        self.net = net if isinstance(net, MergeNet) else read_merge_net(net)
        self.config = config or EnvConfig()
        self._seed = seed
        self._gui = gui
        self._backend: Backend | None = None  # chosen at first reset: in-process, or a subprocess if taken
        self._time_s = 0.0
        self.speed_limits_mps: dict[Road, float] = {
            "main": self.net.main.speed_limit_mps,
            "merge": self.net.merge.speed_limit_mps,
        }
        self.road_lengths_m: dict[Road, float] = {
            "main": self.net.main.length_m,
            "merge": self.net.merge.length_m,
        }
        self._edge_road = {
            self.net.main.edge_id: MAIN,
            self.net.merge.edge_id: MERGE,
            self.net.out.edge_id: OUT,
        }
        self._road_length_by_code = np.array([self.net.main.length_m, self.net.merge.length_m])
        self._via_length_by_code = np.array([self.net.main.via_length_m, self.net.merge.via_length_m])
        self._limit_by_code = np.array(
            [self.net.main.speed_limit_mps, self.net.merge.speed_limit_mps, self.net.out.speed_limit_mps]
        )
        self._origin: dict[str, int] = {}
        self._mask_cache: tuple[TrafficSnapshot, tuple[str, ...], npt.NDArray[np.int8]] | None = None
        self.scenario: Scenario | None = None
        self.snapshot = _empty_snapshot()
        self._spec: dict[str, VehicleSpec] = {}
        self._slot: dict[str, int] = {}
        self._accel: dict[str, float] = {}
        self._active: list[str] = []
        self._done: dict[str, str] = {}
        self._last_obs: dict[str, npt.NDArray[np.float32]] = {}
        self._closed = False

    # -- episode -------------------------------------------------------------------------------
    def reset(self, scenario: Scenario, sumo_args: Sequence[str] = ()) -> None:
        if self._closed:
            raise SimulationError("this environment is closed; create a new one")
        self.scenario = scenario
        self._spec = {v.id: v for v in scenario.vehicles}
        self._origin = {v.id: MAIN if v.road == "main" else MERGE for v in scenario.vehicles}
        self._mask_cache = None
        self._slot = {v.id: i for i, v in enumerate(scenario.vehicles) if i < STATE_SLOTS}
        self._accel = {}
        self._active = []
        self._done = {}
        self._last_obs = {}
        if self._backend is None:
            self._backend = make_backend(self.net, seed=self._seed, gui=self._gui)
        self.backend.reset(scenario, sumo_args)
        events = self.backend.step()  # insertion step: vehicles appear where the scenario puts them
        self._time_s = events.time_s
        self._read_snapshot()
        self._admit(events.departed)
        self._run_until_an_agent_enters()

    def _run_until_an_agent_enters(self) -> None:
        """Nobody to act yet but controlled cars still to come: let time run to the next entry."""
        while not self._active and self._waiting_agents() and not self.timed_out():
            idle = self.backend.step()
            self._time_s = idle.time_s
            self._admit(idle.departed)
            self._read_snapshot()

    @property
    def backend(self) -> Backend:
        if self._backend is None:
            raise SimulationError("step() before reset()")
        return self._backend

    @property
    def time_s(self) -> float:
        """Simulated seconds since the scenario started (the insertion step ends at 0.2 s)."""
        return self._time_s

    @property
    def active_agents(self) -> list[str]:
        """Controlled vehicles on the road that still act (in scenario order)."""
        return list(self._active)

    @property
    def finished_agents(self) -> dict[str, str]:
        """Agents whose episode ended, with the reason."""
        return dict(self._done)

    def _waiting_agents(self) -> list[str]:
        """Controlled vehicles that have not entered yet."""
        assert self.scenario is not None
        return [a for a in self.scenario.controlled_ids if a not in self._done and a not in self._active]

    @property
    def episode_over(self) -> bool:
        """Every controlled vehicle finished, collided or left, or time ran out."""
        return self.timed_out() or (not self._active and not self._waiting_agents())

    def _admit(self, departed: list[str]) -> None:
        for vid in departed:
            spec = self._spec.get(vid)
            if spec is not None and spec.controlled and vid not in self._done and vid not in self._active:
                self._active.append(vid)
                self._accel[vid] = 0.0
        order = {v.id: i for i, v in enumerate(self.scenario.vehicles)} if self.scenario else {}
        self._active.sort(key=lambda v: order[v])

    def _read_snapshot(self) -> None:
        self.snapshot = self._snapshot_from(self.backend.vehicle_states())

    def _snapshot_from(self, states: VehicleStates) -> TrafficSnapshot:
        n = len(states.ids)
        origin = np.fromiter((self._origin[vid] for vid in states.ids), dtype=np.int64, count=n)
        edge_road = np.fromiter((self._edge_road.get(e, -1) for e in states.edge), dtype=np.int64, count=n)
        pos = states.lane_pos_m
        incoming = (edge_road == MAIN) | (edge_road == MERGE)
        # Internal junction lanes (edge_road -1) lie past the merge point: they count as the outgoing road.
        road = np.where(incoming, edge_road, OUT)
        dist = np.where(
            incoming,
            self._road_length_by_code[np.where(incoming, edge_road, 0)] - pos,
            np.where(edge_road == OUT, -(self._via_length_by_code[origin] + pos), -pos),
        )
        out_limit = self._limit_by_code[OUT]
        own_limit = effective_speed_limit(self._limit_by_code[road], dist, out_limit)
        limit = np.where(road == OUT, out_limit, own_limit)
        return TrafficSnapshot(
            ids=states.ids,
            road=road.astype(np.int64),
            dist_to_merge_m=dist,
            speed_mps=states.speed_mps.copy(),
            accel_mps2=states.accel_mps2.copy(),
            length_m=np.full(n, VEHICLE_LENGTH_M),
            speed_limit_mps=limit,
        )

    def b_prio(self, road: npt.NDArray[np.int64]) -> FloatArray:
        assert self.scenario is not None
        s = self.scenario
        table = np.array([s.main_prio, s.merge_prio, max(s.main_prio, s.merge_prio)], dtype=np.float64)
        return np.asarray(table[road], dtype=np.float64)

    # -- observation ---------------------------------------------------------------------------
    def observe(
        self, agent_ids: list[str] | None = None
    ) -> tuple[npt.NDArray[np.float32], npt.NDArray[np.int8]]:
        """(observations, action masks) for the given active agents (default: all), in that order."""
        ids = self._active if agent_ids is None else agent_ids
        if not ids:
            return np.zeros((0, OBS_DIM), dtype=np.float32), np.zeros((0, N_ACTIONS), dtype=np.int8)
        egos = self.snapshot.index(ids)
        prev_accel = np.array([self._accel[a] for a in ids])
        b_type = np.array([self._spec[a].b_type for a in ids])
        obs = build_observations(
            self.snapshot, egos, prev_accel, self.b_prio(self.snapshot.road[egos]), b_type
        )
        finite = np.isfinite(obs).all(axis=1)
        if not finite.all():
            bad = ids[int(np.argmin(finite))]
            raise SimulationError(
                f"non-finite observation for agent {bad!r} at t = {self.time_s:.1f} s (a bug)"
            )
        masks = self.masks(ids)
        for i, a in enumerate(ids):
            self._last_obs[a] = obs[i]
        return obs, masks

    def masks(self, agent_ids: list[str]) -> npt.NDArray[np.int8]:
        """(n, 7) action masks of these agents in the current snapshot (cached until the next step)."""
        key = tuple(agent_ids)
        if (
            self._mask_cache is not None
            and self._mask_cache[0] is self.snapshot
            and self._mask_cache[1] == key
        ):
            return self._mask_cache[2]
        masks = self._compute_masks(agent_ids)
        self._mask_cache = (self.snapshot, key, masks)
        return masks

    def _compute_masks(self, agent_ids: list[str]) -> npt.NDArray[np.int8]:
        snap = self.snapshot
        egos = snap.index(agent_ids)
        gap, leader_speed, ease_in = self.front_cars(egos)
        return action_masks(
            MaskInputs(
                prev_accel_mps2=np.array([self._accel[a] for a in agent_ids]),
                speed_mps=snap.speed_mps[egos],
                speed_limit_mps=snap.speed_limit_mps[egos],
                gap_m=gap,
                leader_speed_mps=leader_speed,
                ease_in=ease_in,
            )
        )

    def front_cars(self, egos: npt.NDArray[np.int64]) -> tuple[FloatArray, FloatArray, npt.NDArray[np.bool_]]:
        """The car the safety mask keeps its distance to: (gap m, its speed m/s, ease_in; see MaskInputs).

        Ours: in a merge the car in front is not only the one ahead in the ego's lane. A car on the other
        incoming road that is closer to the merge point (projected, within sight of both) will be in front
        of the ego after the merge, so whichever of the two asks for the lower IDM acceleration counts.
        Level cars: the main-road car counts as ahead. With only the ego's own lane (the literal reading)
        the cars of the two roads met side by side at the merge point: 28 of the first 40 paper-suite
        scenarios had a collision with IDM driving every car, 26 with IDAS (docs/design-notes.md).
        """
        snap = self.snapshot
        leader, gap = leaders(snap, egos)
        # SUMO's own cars on the merge road give way to every main-road car at the junction (stage 1's
        # "merge always yields"); counting them as front cars of main-road cars deadlocked both.
        sumo_yielding = (snap.road == MERGE) & ~np.fromiter(
            (self._spec[v].controlled for v in snap.ids), dtype=np.bool_, count=len(snap)
        )
        merge_leader, merge_gap = other_road_leaders(
            snap,
            egos,
            max_ahead_m=np.inf,
            zone_m=VISIBILITY_M,
            level_counts_for_main=True,
            never_leading=sumo_yielding,
        )
        speed = snap.speed_mps[egos]
        leader_speed = leader_speeds(snap, egos, leader)
        merge_speed = leader_speeds(snap, egos, merge_leader)
        own_lane_bound = safety_bound(speed, gap, leader_speed)
        other_road = (merge_leader >= 0) & (safety_bound(speed, merge_gap, merge_speed) < own_lane_bound)
        ease_in = (
            other_road
            & (snap.dist_to_merge_m[egos] > MERGE_ZONE_RADIUS_M)
            & (own_lane_bound >= -DEFAULT_IDM.comfortable_decel_mps2)
        )
        return np.where(other_road, merge_gap, gap), np.where(other_road, merge_speed, leader_speed), ease_in

    def last_observation(self, agent_id: str) -> npt.NDArray[np.float32]:
        return self._last_obs[agent_id]

    def prev_accel(self, agent_id: str) -> float:
        return self._accel[agent_id]

    def spec(self, vehicle_id: str) -> VehicleSpec:
        return self._spec[vehicle_id]

    def slot(self, vehicle_id: str) -> int:
        return self._slot.get(vehicle_id, -1)

    def state(self) -> npt.NDArray[np.float32]:
        """Global state for the centralised critic (layout in ``env/state_layout.py``)."""
        state = np.zeros((STATE_SLOTS, STATE_FEATURES), dtype=np.float32)
        snap = self.snapshot
        prio = self.b_prio(snap.road)
        for i, vid in enumerate(snap.ids):
            slot = self._slot.get(vid)
            if slot is None:
                continue
            spec = self._spec[vid]
            state[slot] = (
                1.0,
                snap.road[i] == MAIN,
                snap.road[i] == MERGE,
                snap.road[i] == OUT,
                snap.dist_to_merge_m[i] / DIST_SCALE_M,
                snap.speed_mps[i] / SPEED_SCALE_MPS,
                snap.accel_mps2[i] / ACCEL_SCALE_MPS2,
                prio[i],
                spec.b_type / B_TYPE_SCALE,
                float(spec.controlled and vid in self._active),
            )
        return state.reshape(STATE_DIM)

    def agent_info(self, agent_id: str) -> dict[str, object]:
        """Raw physical values of an agent now (or at its last step on the road)."""
        if agent_id in self.snapshot.ids:
            i = int(self.snapshot.index([agent_id])[0])
            return {
                "speed_mps": float(self.snapshot.speed_mps[i]),
                "accel_mps2": float(self._accel.get(agent_id, self.snapshot.accel_mps2[i])),
                "dist_to_merge_m": float(self.snapshot.dist_to_merge_m[i]),
                "road": ROAD_NAMES[int(self.snapshot.road[i])],
            }
        return {
            "speed_mps": float("nan"),
            "accel_mps2": float("nan"),
            "dist_to_merge_m": float("nan"),
            "road": "gone",
        }

    # -- stepping ------------------------------------------------------------------------------
    def step(self, actions: Mapping[str, object]) -> StepOutcome:
        """Apply one action per active agent, advance SUMO one step, score it and end whoever is done."""
        if self._closed:
            raise SimulationError("step() after close(); create a new environment")
        if self.scenario is None:
            raise SimulationError("step() before reset()")
        acting = list(self._active)
        missing = [a for a in acting if a not in actions]
        if missing:
            raise ValueError(f"no action for active agents {missing}")
        before = self.snapshot
        replaced, hard_brakers = self._apply_actions(acting, actions) if acting else ({}, [])
        events = self.backend.step()
        self._time_s = events.time_s
        self._read_snapshot()
        hard_brakers += self._sumo_hard_brakes(before, self.snapshot)
        end_reason = self._end_reasons(acting, events.collided)
        parts, flow, merge_zone_brakes = self._reward_parts(acting, before, hard_brakers, end_reason)
        rewards = {a: parts[a]["finish"] + parts[a]["collide"] + parts[a]["impede"] for a in acting}
        self._end_agents(end_reason)
        self._admit(events.departed)
        self._run_until_an_agent_enters()
        return StepOutcome(
            rewards=rewards,
            reward_parts=parts,
            joint_reward=float(sum(rewards.values()) + flow),
            terminated={a: a in end_reason and end_reason[a] != "timeout" for a in acting},
            truncated={a: end_reason.get(a) == "timeout" for a in acting},
            end_reason=end_reason,
            hard_brakes=hard_brakers,
            hard_brakes_merge_zone=merge_zone_brakes,
            collisions=events.collision_pairs,
            replaced_actions=replaced,
        )

    def _apply_actions(
        self, acting: list[str], actions: Mapping[str, object]
    ) -> tuple[dict[str, int], list[str]]:
        """Command the next speeds of ``acting`` (non-empty) from their actions.

        A masked request becomes the allowed action with the closest (then lower) acceleration.
        Returns (agents whose action was replaced -> the action applied, agents that brake hard).
        """
        requested = np.array([_checked_action(a, actions[a], self.time_s) for a in acting], dtype=np.int64)
        masks = self.masks(acting)
        prev = np.array([self._accel[a] for a in acting])
        rows = np.arange(len(requested))
        allowed = masks[rows, requested].astype(bool)
        wanted = candidate_accelerations(prev)[rows, requested]
        applied = np.where(allowed, requested, closest_allowed_action(wanted, prev, masks))
        replaced = {a: int(app) for a, req, app in zip(acting, requested, applied, strict=True) if req != app}
        new_accel = next_acceleration(prev, applied)
        egos = self.snapshot.index(acting)
        next_speed = np.maximum(self.snapshot.speed_mps[egos] + new_accel * STEP_LENGTH_S, 0.0)
        self.backend.set_speeds({a: float(v) for a, v in zip(acting, next_speed, strict=True)})
        hard_brakers: list[str] = []
        for a, acc, act in zip(acting, new_accel, applied, strict=True):
            self._accel[a] = float(acc)
            if act == HARD_BRAKE:
                hard_brakers.append(a)
        return replaced, hard_brakers

    def _sumo_hard_brakes(self, before: TrafficSnapshot, after: TrafficSnapshot) -> list[str]:
        """SUMO-driven cars (robots, finished agents handed back) that braked hard on their own this step."""
        present_before = set(before.ids)
        return [
            vid
            for i, vid in enumerate(after.ids)
            if vid not in self._active
            and vid in present_before
            and after.accel_mps2[i] <= HARD_BRAKE_DETECT_MPS2
        ]

    def _end_reasons(self, acting: list[str], collided: set[str]) -> dict[str, str]:
        """Why each agent's episode ended this step: collided, removed, finished, else timeout (if time is up)."""
        after = self.snapshot
        in_sim = set(after.ids)
        end_reason: dict[str, str] = {}
        for a in acting:
            if a in collided:
                end_reason[a] = "collided"
            elif a not in in_sim:
                end_reason[a] = "removed"
            elif after.dist_to_merge_m[after.index([a])[0]] <= -FINISH_DISTANCE_PAST_MERGE_M:
                end_reason[a] = "finished"
        if self.timed_out():
            end_reason.update({a: "timeout" for a in acting if a not in end_reason})
        return end_reason

    def _reward_parts(
        self, acting: list[str], before: TrafficSnapshot, hard_brakers: list[str], end_reason: dict[str, str]
    ) -> tuple[dict[str, dict[str, float]], float, int]:
        """(each agent's named reward parts, the shared flow penalty, hard brakes in the merging zone).

        Hard brakes are placed where the braking car was when it decided (the step's start).
        """
        assert self.scenario is not None
        brake_idx = [int(before.index([v])[0]) for v in hard_brakers]
        brake_dist = before.dist_to_merge_m[brake_idx] if brake_idx else np.zeros(0)
        flow = flow_penalty(brake_dist)
        culprits = _impeding_vehicles(before, brake_idx)
        parts = {a: dict.fromkeys(REWARD_PART_NAMES, 0.0) for a in acting}
        for a in acting:
            parts[a]["flow"] = flow
            parts[a]["impede"] = IMPEDE_PENALTY * culprits.count(a)
            spec = self._spec[a]
            if end_reason.get(a) == "collided":
                # The priority of the road the car came from: collisions happen on the junction or
                # after it, where the snapshot's road is the outgoing one (priority max of both).
                prio = float(self.scenario.prio(spec.road))
                parts[a]["collide"] = float(collide_reward(prio, self.config.reward.collision_sign))
            elif end_reason.get(a) == "finished":
                parts[a]["finish"] = float(finish_reward(spec.b_type))
        return parts, flow, hard_brakes_in_merge_zone(brake_dist)

    def _end_agents(self, end_reason: dict[str, str]) -> None:
        """Agents whose episode ended stop acting; finished cars are handed back to SUMO's driver model."""
        for a, reason in end_reason.items():
            self._done[a] = reason
            self._active.remove(a)
            if reason == "finished":
                self.backend.release(a)

    def timed_out(self) -> bool:
        return self.time_s >= self.config.max_episode_s - 1e-9

    def close(self) -> None:
        if self._backend is not None:
            self._backend.close()
        self._closed = True


def _checked_action(agent: str, action: object, time_s: float) -> int:
    """An action index in [0, 7), or a ValueError naming the agent and the time."""
    value = action
    if isinstance(action, np.generic | np.ndarray) and np.ndim(action) == 0:
        value = action.item()  # numpy scalars and 0-d arrays (what many agents return)
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value < N_ACTIONS:
        raise ValueError(
            f"invalid action {action!r} for agent {agent!r} at t = {time_s:.1f} s: expected an int in [0, {N_ACTIONS})"
        )
    return value


def _impeding_vehicles(before: TrafficSnapshot, brake_idx: list[int]) -> list[str]:
    """For each hard-braking vehicle, the nearest vehicle ahead of it on either lane (within sight)."""
    if not brake_idx:
        return []
    egos = np.asarray(brake_idx, dtype=np.int64)
    same, other = lane_relations(before.road, egos)
    ahead = before.dist_to_merge_m[egos][:, None] - before.dist_to_merge_m[None, :]
    candidates = (same | other) & (ahead >= 0.0) & (ahead <= VISIBILITY_M)
    distance = np.where(candidates, ahead, np.inf)
    nearest = np.argmin(distance, axis=1)
    rows = np.arange(len(egos))
    return [before.ids[j] for r, j in zip(rows, nearest, strict=True) if np.isfinite(distance[r, j])]


def _empty_snapshot() -> TrafficSnapshot:
    z = np.zeros(0)
    return TrafficSnapshot((), np.zeros(0, dtype=np.int64), z, z, z, z, z)


__all__ = [
    "DEFAULT_MAX_EPISODE_S",
    "EnvConfig",
    "MergeSimulation",
    "StepOutcome",
    "placeholder_mask",
]
