"""The compiled relations and grids against a plain reference: every (ego, vehicle) pair, in snapshot order.

``nearest_ahead`` walks each copy's vehicles sorted by distance and stops early, and ``build_grids`` only
looks at the vehicles within sight; both must give exactly what checking every pair gives, ties (equal
distances: the first row wins) and overlapping bodies (the last one drawn wins) included.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from idas_sumo.env.layout import (
    CELL_M,
    GRID_CELLS,
    N_CHANNELS,
    N_SCALARS,
    RELATIVE_SPEED_SCALE_MPS,
    SCALAR_SCALES,
    VISIBILITY_M,
)
from idas_sumo.env.observation import build_grids, build_observations_checked
from idas_sumo.env.snapshot import (
    MAIN,
    NO_LEADER,
    OUT,
    TrafficSnapshot,
    leader_speeds,
    leaders,
    leaders_and_speeds,
    nearest_ahead,
)


def random_snapshot(
    rng: np.random.Generator, layout: str, n_copies: int, per_copy: int, stretch_m: float = 320.0
) -> TrafficSnapshot:
    n = n_copies * per_copy
    copy = np.repeat(np.arange(n_copies), per_copy)
    if layout == "interleaved":
        copy = rng.permutation(copy)
    # Whole metres (on the default, short stretch: many cars level with each other, many bodies overlapping).
    dist = np.round(rng.uniform(-60.0, stretch_m - 60.0, n))
    return TrafficSnapshot(
        ids=tuple(f"v{i}" for i in range(n)),
        road=rng.integers(0, 3, n).astype(np.int64),
        dist_to_merge_m=dist,
        speed_mps=rng.uniform(0.0, 25.0, n),
        accel_mps2=np.zeros(n),
        length_m=rng.choice([5.0, 12.0], n),
        speed_limit_mps=np.full(n, 20.0),
        copy=None if layout == "one world" else copy,
    )


def same_lane(ego_road: int, road: int) -> bool:
    return road in (ego_road, OUT) if ego_road != OUT else road == OUT


def copy_of(snap: TrafficSnapshot, i: int) -> int:
    return 0 if snap.copy is None else int(snap.copy[i])


def reference_nearest(
    snap: TrafficSnapshot, e: int, any_lane: bool, level_counts: bool, max_ahead_m: float
) -> tuple[int, float]:
    best, nearest = math.inf, NO_LEADER
    for j in range(len(snap)):
        if j == e or copy_of(snap, j) != copy_of(snap, e):
            continue
        if not (any_lane or same_lane(int(snap.road[e]), int(snap.road[j]))):
            continue
        ahead = snap.dist_to_merge_m[e] - snap.dist_to_merge_m[j]
        if (ahead > 0.0 or (level_counts and ahead == 0.0)) and ahead <= max_ahead_m and ahead < best:
            best, nearest = ahead, j
    return nearest, best


def reference_grid(snap: TrafficSnapshot, e: int) -> np.ndarray:
    grid = np.zeros((2, N_CHANNELS, GRID_CELLS), dtype=np.float32)
    for j in range(len(snap)):
        if j == e or copy_of(snap, j) != copy_of(snap, e):
            continue
        ahead_front = snap.dist_to_merge_m[e] - snap.dist_to_merge_m[j]
        first = math.floor((ahead_front - snap.length_m[j] + VISIBILITY_M) / CELL_M)
        last = math.floor((ahead_front + VISIBILITY_M) / CELL_M)
        if last < 0 or first >= GRID_CELLS:
            continue
        lane = 0 if same_lane(int(snap.road[e]), int(snap.road[j])) else 1
        cells = slice(max(first, 0), min(last, GRID_CELLS - 1) + 1)
        grid[lane, 0, cells] = 1.0
        grid[lane, 1, cells] = (snap.speed_mps[j] - snap.speed_mps[e]) / RELATIVE_SPEED_SCALE_MPS
    return grid


@pytest.mark.parametrize("layout", ["one world", "copies in order", "interleaved"])
def test_nearest_ahead_and_leaders_match_every_pair(layout: str) -> None:
    rng = np.random.default_rng(7)
    for trial in range(30):
        snap = random_snapshot(rng, layout, n_copies=1 if layout == "one world" else 3, per_copy=40)
        egos = rng.permutation(len(snap))[: int(rng.integers(1, len(snap)))].astype(np.int64)
        for any_lane, level_counts, max_ahead in (
            (False, False, np.inf),
            (True, True, 100.0),
            (True, False, 7.0),
        ):
            nearest, ahead = nearest_ahead(snap, egos, any_lane, level_counts, max_ahead)
            expected = [reference_nearest(snap, int(e), any_lane, level_counts, max_ahead) for e in egos]
            assert nearest.tolist() == [j for j, _ in expected], (trial, any_lane, level_counts)
            assert ahead.tolist() == [d for _, d in expected], (trial, any_lane, level_counts)
        leader, gap = leaders(snap, egos)
        assert leader.tolist() == nearest_ahead(snap, egos, False, False, np.inf)[0].tolist()
        has = leader != NO_LEADER
        own_ahead = snap.dist_to_merge_m[egos[has]] - snap.dist_to_merge_m[leader[has]]
        assert gap[has].tolist() == (own_ahead - snap.length_m[leader[has]]).tolist()
        assert np.all(np.isinf(gap[~has]))
        same_leader, same_gap, speed = leaders_and_speeds(snap, egos)
        assert same_leader.tolist() == leader.tolist() and same_gap.tolist() == gap.tolist()
        assert speed.tolist() == leader_speeds(snap, egos, leader).tolist()


@pytest.mark.parametrize("layout", ["one world", "copies in order", "interleaved"])
@pytest.mark.parametrize("stretch_m", [320.0, 3000.0])
def test_grids_match_every_pair(layout: str, stretch_m: float) -> None:
    # On the short stretch most of a copy is within sight, and the kernel walks the copy's rows (copies in
    # order); on the long one few cars are, and it sorts those (as it always does with interleaved copies).
    rng = np.random.default_rng(11)
    for trial in range(10):
        snap = random_snapshot(
            rng, layout, n_copies=1 if layout == "one world" else 2, per_copy=60, stretch_m=stretch_m
        )
        egos = rng.permutation(len(snap))[:20].astype(np.int64)
        grids = build_grids(snap, egos)
        for row, e in enumerate(egos):
            np.testing.assert_array_equal(grids[row], reference_grid(snap, int(e)), err_msg=f"trial {trial}")


def test_a_leader_level_with_the_ego_counts_only_when_asked() -> None:
    snap = TrafficSnapshot(
        ids=("ego", "level", "behind"),
        road=np.array([MAIN, MAIN, MAIN]),
        dist_to_merge_m=np.array([50.0, 50.0, 60.0]),
        speed_mps=np.zeros(3),
        accel_mps2=np.zeros(3),
        length_m=np.full(3, 5.0),
        speed_limit_mps=np.full(3, 20.0),
    )
    assert nearest_ahead(snap, np.array([0]), False, False, np.inf)[0].tolist() == [NO_LEADER]
    assert nearest_ahead(snap, np.array([0]), False, True, np.inf)[0].tolist() == [1]
    assert nearest_ahead(snap, np.array([2]), False, False, np.inf)[0].tolist() == [
        0
    ]  # the first of two level


def test_scalars_are_numpys_columns_and_their_finiteness_is_reported() -> None:
    """The compiled scalar columns against numpy's float64 division rounded to float32, huge and
    non-finite inputs included (float64 values beyond float32's range become inf)."""
    rng = np.random.default_rng(13)
    odd = [0.0, -0.0, 1e-40, 3.5e39, -1e300, np.inf, np.nan]
    for trial in range(40):
        snap = random_snapshot(rng, "copies in order", n_copies=2, per_copy=10)
        if trial % 2:
            speed = snap.speed_mps.copy()
            speed[rng.integers(0, len(speed))] = rng.choice(odd)
            snap = dataclasses.replace(snap, speed_mps=speed)
        egos = rng.permutation(len(snap))[: int(rng.integers(0, len(snap)))].astype(np.int64)
        n = len(egos)
        columns = [rng.uniform(-4.0, 4.0, n), rng.integers(0, 2, n).astype(float), rng.uniform(-2.0, 2.0, n)]
        for values in columns:
            if trial % 3 == 0 and n:
                values[rng.integers(0, n)] = rng.choice(odd)
        prev, b_prio, b_type = columns
        with np.errstate(over="ignore", invalid="ignore"):
            expected = np.zeros((n, N_SCALARS), dtype=np.float32)
            for j, values in enumerate(
                (snap.speed_mps[egos], prev, snap.dist_to_merge_m[egos], b_prio, b_type)
            ):
                expected[:, j] = values / SCALAR_SCALES[j]
        obs, finite = build_observations_checked(snap, egos, prev, b_prio, b_type)
        assert obs[:, :N_SCALARS].view(np.uint32).tolist() == expected.view(np.uint32).tolist(), trial
        assert finite == bool(np.isfinite(expected).all()), trial
        np.testing.assert_array_equal(
            obs[:, N_SCALARS:].reshape(-1, 2, 2, GRID_CELLS), build_grids(snap, egos)
        )
