"""The engine's tables: per slot its episode, per car its per-step state as arrays over all copies."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from idas_sumo.env.outcome import EpisodeOutcome
from idas_sumo.env.scenario import Scenario, VehicleSpec
from idas_sumo.env.snapshot import MAIN, MERGE, TrafficSnapshot

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]
BoolArray = npt.NDArray[np.bool_]


@dataclass
class _Slot:
    """One copy's episode (its cars' per-step state is in the engine's ``_Cars``)."""

    scenario: Scenario
    spec: dict[str, VehicleSpec]
    order: dict[str, int]
    """Vehicle id -> its index in the scenario."""
    outcome: EpisodeOutcome
    over: bool = False
    started: bool = False

    @staticmethod
    def of(scenario: Scenario) -> _Slot:
        """A fresh episode of ``scenario`` (its first STATE_SLOTS cars have a row in the critic's state:
        ``MergeEngine.state_slots``)."""
        return _Slot(
            scenario=scenario,
            spec={v.id: v for v in scenario.vehicles},
            order={v.id: i for i, v in enumerate(scenario.vehicles)},
            outcome=EpisodeOutcome(scenario),
        )


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
    origin_prio: FloatArray
    """Each agent's b_prio of the road it started on (the reward's collision term)."""
    acting: BoolArray
    """Per slot: whether it has an agent."""
    per_copy: list[int]
    """Per slot: how many agents."""


def _empty_snapshot() -> TrafficSnapshot:
    z = np.zeros(0)
    return TrafficSnapshot((), np.zeros(0, dtype=np.int64), z, z, z, z, z)
