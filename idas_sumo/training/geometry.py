"""A generated merge drawn per training round: the ``[geometry]`` table of a training config.

With ``[geometry]`` each round of a run trains on a generated T-junction (``sim/netgen.py``) whose
angle, road lengths, speed limits and priority are drawn from the table's ranges by the run's own
seeded generator; every episode of the round runs on it, and the nets come from the net cache
(``sim/net_cache.cached_net``), keyed by their parameters. The draws lie on a grid (lengths to the
metre, angles to the degree, limits to 0.5 m/s), so a long run needs a bounded number of nets, not
one per round. Validation stays on the run's ``--net``, or, with ``validation_geometries``, runs on that
many merges drawn from the same ranges by the validation seed.

The default ranges leave out every held-out geometry of ``evaluate --suite geometry``
(``evaluation/geometry.py``), so that suite keeps measuring merges the training never saw: angles
20-40° (held out: 15° and 60°), approaches 230-330 m (held out: both 220 m and both 350 m), limits
main and outgoing 18-23 m/s and merging 12-17 m/s (held out: 25/18/25), and the main road always
first (held out: the zipper). ``tests/test_geometry_training.py`` checks it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from idas_sumo.errors import InputError
from idas_sumo.sim.netgen import ANGLE_BOUNDS_DEG, LENGTH_BOUNDS_M, SPEED_BOUNDS_MPS, NetParams

MAX_VALIDATION_GEOMETRIES = 1_000
"""The most validation merges a run may draw: each is a net built up front (about 0.3 s and 45 KB with its
multi-copy net) and a net switch of every worker at each validation; the shipped recipes use 8."""

__all__ = [
    "GEOMETRY_COLUMNS",
    "GRID",
    "GeometryConfig",
    "GeometryRangeError",
    "draw_geometry",
    "geometry_corners",
]

Range = tuple[float, float]


class GeometryRangeError(InputError, ValueError):
    """A bad range; a ValueError too so ``config.from_dict`` prefixes the file and table."""


GRID: dict[str, float] = {
    "main_length_m": 1.0,
    "merge_length_m": 1.0,
    "out_length_m": 1.0,
    "main_speed_mps": 0.5,
    "merge_speed_mps": 0.5,
    "out_speed_mps": 0.5,
    "angle_deg": 1.0,
}
"""Each drawn value's step, in the order the values are drawn (the ``NetParams`` field names)."""
_BOUNDS: dict[str, tuple[float, float, str]] = {
    "main_length_m": (*LENGTH_BOUNDS_M, "m"),
    "merge_length_m": (*LENGTH_BOUNDS_M, "m"),
    "out_length_m": (*LENGTH_BOUNDS_M, "m"),
    "main_speed_mps": (*SPEED_BOUNDS_MPS, "m/s"),
    "merge_speed_mps": (*SPEED_BOUNDS_MPS, "m/s"),
    "out_speed_mps": (*SPEED_BOUNDS_MPS, "m/s"),
    "angle_deg": (*ANGLE_BOUNDS_DEG, "degrees"),
}
_LENGTHS = ("main_length_m", "merge_length_m", "out_length_m")
_LIMITS = ("main_speed_mps", "merge_speed_mps", "out_speed_mps")
GEOMETRY_COLUMNS: tuple[str, ...] = (
    "stage",
    "episode",
    "global_episode",
    "episodes",
    *GRID,
    "priority",
    "net",
)
"""``geometries.csv``: one row per round (its first episode, in the stage and in the run, and how many
episodes it had), the geometry drawn and the net file's name in the cache."""


@dataclass(frozen=True)
class GeometryConfig:
    """``[geometry]``: the ranges, [low, high] inclusive, each on its grid (``GRID``)."""

    main_length_m: Range = (230.0, 330.0)
    """Main road, start to the merge point, m."""
    merge_length_m: Range = (230.0, 330.0)
    """Merging road, start to the merge point, m."""
    out_length_m: Range = (130.0, 200.0)
    """Road after the merge, m."""
    main_speed_mps: Range = (18.0, 23.0)
    merge_speed_mps: Range = (12.0, 17.0)
    out_speed_mps: Range = (18.0, 23.0)
    angle_deg: Range = (20.0, 40.0)
    """Angle between the merging road and the main road, degrees."""
    equal_priority_probability: float = 0.0
    """Chance of a zipper merge (equal priority, ``--priority equal``) in a round; else the main road
    has right of way."""
    equal_approaches_probability: float = 0.0
    """Ours: chance that a draw's merging road is as long as its main road (the two ranges must then be
    the same). Drawn independently, the approaches differ by 33 m on average, which puts the two roads'
    cars apart at the merge more often than on the T-junction or any held-out geometry, all of which have
    equal approaches (docs/results.md). 0 draws nothing for it, so runs without it draw as before."""
    validation_geometries: int = 0
    """Ours: > 0 spreads the validation scenarios over this many merges drawn from these ranges by the
    validation seed (the same merges at every validation), so that the kept weights are the ones that
    drive the trained distribution best; 0: validation on the run's own net. At most
    ``MAX_VALIDATION_GEOMETRIES``."""

    def __post_init__(self) -> None:
        for name, step in GRID.items():
            value: Any = getattr(self, name)
            lo_bound, hi_bound, unit = _BOUNDS[name]
            if len(value) != 2:
                raise GeometryRangeError(f"{name}: expected [low, high], got {len(value)} numbers")
            lo, hi = value
            if not lo <= hi:
                raise GeometryRangeError(f"{name}: low {lo:g} is above high {hi:g}")
            if not (lo_bound <= lo and hi <= hi_bound):
                raise GeometryRangeError(
                    f"{name}: [{lo:g}, {hi:g}] {unit} is outside [{lo_bound:g}, {hi_bound:g}]"
                )
            for end in (lo, hi):
                if not math.isclose(end / step, round(end / step), abs_tol=1e-9):
                    raise GeometryRangeError(
                        f"{name}: {end:g} is not on the {step:g} {unit} grid the draws lie on"
                    )
        if not 0 <= self.validation_geometries <= MAX_VALIDATION_GEOMETRIES:
            raise GeometryRangeError(
                f"validation_geometries must be in [0, {MAX_VALIDATION_GEOMETRIES}], got {self.validation_geometries}"
            )
        if not 0.0 <= self.equal_approaches_probability <= 1.0:
            raise GeometryRangeError(
                f"equal_approaches_probability must be in [0, 1], got {self.equal_approaches_probability:g}"
            )
        if self.equal_approaches_probability > 0.0 and self.main_length_m != self.merge_length_m:
            raise GeometryRangeError(
                "equal_approaches_probability needs main_length_m and merge_length_m to be the same range"
            )
        if not 0.0 <= self.equal_priority_probability <= 1.0:
            raise GeometryRangeError(
                f"equal_priority_probability must be in [0, 1], got {self.equal_priority_probability:g}"
            )

    def can_draw(self, params: NetParams) -> bool:
        """Whether ``params`` is one of this table's geometries (on the grid, in every range)."""
        for name, step in GRID.items():
            lo, hi = getattr(self, name)
            value = getattr(params, name)
            if not (lo <= value <= hi and math.isclose(value / step, round(value / step), abs_tol=1e-9)):
                return False
        if self.equal_approaches_probability == 1.0 and params.main_length_m != params.merge_length_m:
            return False
        if params.priority == "equal":
            return self.equal_priority_probability > 0.0
        return self.equal_priority_probability < 1.0


def draw_geometry(rng: np.random.Generator, geometry: GeometryConfig) -> NetParams:
    """One geometry from ``rng``: each value uniform over its grid points, in ``GRID``'s order, then
    the priority (always drawn, so the draws that follow do not depend on the probability), then, with
    ``equal_approaches_probability`` > 0, whether the merging road takes the main road's length."""
    values: dict[str, float] = {}
    for name, step in GRID.items():
        lo, hi = getattr(geometry, name)
        points = round((hi - lo) / step)
        values[name] = lo + step * int(rng.integers(0, points + 1))
    equal = float(rng.random()) < geometry.equal_priority_probability
    if (
        geometry.equal_approaches_probability > 0.0
        and float(rng.random()) < geometry.equal_approaches_probability
    ):
        values["merge_length_m"] = values["main_length_m"]
    return NetParams(**values, priority="equal" if equal else "main")


def geometry_corners(geometry: GeometryConfig) -> tuple[NetParams, NetParams]:
    """The two draws the road checks (``env/net_needs.py``) are hardest on: every road shortest with
    the limits highest (the starts and the finish must fit), and every road longest with the limits
    lowest (a car from the start must reach the finish in time)."""
    low = {name: getattr(geometry, name)[0] for name in GRID}
    high = {name: getattr(geometry, name)[1] for name in GRID}
    short = {**{k: low[k] for k in _LENGTHS}, **{k: high[k] for k in _LIMITS}}
    long = {**{k: high[k] for k in _LENGTHS}, **{k: low[k] for k in _LIMITS}}
    return NetParams(**short, angle_deg=low["angle_deg"]), NetParams(**long, angle_deg=high["angle_deg"])
