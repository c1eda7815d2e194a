"""One scenario on a single-simulation backend behind the calls the engine makes of a ``BatchBackend``."""

from __future__ import annotations

import itertools
from collections.abc import Sequence

import numpy as np
import numpy.typing as npt

from idas_sumo.env.scenario import Scenario
from idas_sumo.errors import SimulationError
from idas_sumo.sim.backend import Backend, StepEvents
from idas_sumo.sim.batch import BatchStates, BatchStepEvents
from idas_sumo.sim.frozen import built


class _SoloBackend:
    """One scenario on a single-simulation backend (in-process, a subprocess, or sumo-gui), behind the
    ``BatchBackend`` calls the engine makes: the K = 1 engine of the environments and of ``--gui``."""

    copies = 1

    def __init__(self, backend: Backend) -> None:
        self._backend = backend
        self._index: dict[str, int] = {}
        """Vehicle id -> its index in the scenario."""
        self._read_ids: tuple[str, ...] | None = None
        self._read_vehicle = np.zeros(0, dtype=np.int64)
        self._read_zeros = np.zeros(0, dtype=np.int64)
        self._read_bounds = np.array([0, 0])
        """Each car's index in the scenario for the id list ``_read_ids`` (kept while the same cars drive)."""

    def reset(self, scenarios: Sequence[Scenario], extra_args: Sequence[str] = ()) -> None:
        if len(scenarios) != 1:
            raise SimulationError(f"{len(scenarios)} scenarios for a single simulation (a bug)")
        self._backend.reset(scenarios[0], extra_args)
        self._index = {v.id: i for i, v in enumerate(scenarios[0].vehicles)}
        self._read_ids = None

    def global_id(self, copy: int, vehicle_id: str) -> str:
        return vehicle_id

    def step(self) -> BatchStepEvents:
        events: StepEvents = self._backend.step()
        return BatchStepEvents(events.time_s, [events])

    def vehicle_states(self) -> BatchStates:
        s = self._backend.vehicle_states()
        n = len(s.ids)
        if s.ids != self._read_ids:  # cars entered or left since the last read
            self._read_vehicle = np.fromiter(map(self._index.get, s.ids, itertools.repeat(-1)), np.int64, n)
            self._read_zeros = np.zeros(n, dtype=np.int64)
            self._read_bounds = np.array([0, n])
            for a in (self._read_vehicle, self._read_zeros, self._read_bounds):
                a.flags.writeable = False  # handed out with every read of the same cars
            self._read_ids = s.ids
        zeros = self._read_zeros
        return built(  # (``BatchStates(...)``, every field given)
            BatchStates,
            ids=s.ids,
            copy=zeros,
            vehicle=self._read_vehicle,
            edge=s.edge,
            edge_index=zeros,
            lane_pos_m=s.lane_pos_m,
            speed_mps=s.speed_mps,
            accel_mps2=s.accel_mps2,
            bounds=self._read_bounds,
            lane_index=s.lane_index,
        )

    def set_speeds(
        self, vehicle_ids: Sequence[str], speeds_mps: npt.ArrayLike, copy: npt.ArrayLike | None = None
    ) -> None:
        self._backend.set_speed_list(vehicle_ids, np.asarray(speeds_mps, dtype=np.float64).tolist())

    def release(self, vehicle_id: str, copy: int) -> None:
        self._backend.release(vehicle_id)

    def remove(self, vehicle_id: str, copy: int) -> None:
        self._backend.remove(vehicle_id)

    def clear_copy(self, copy: int) -> None:
        """Nothing to do: the next reset reloads the simulation."""

    def close(self) -> None:
        self._backend.close()
