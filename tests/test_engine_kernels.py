"""The engine's compiled step loops against the numpy they replaced, on hand-picked and random inputs."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from idas_sumo.env.actions import next_acceleration
from idas_sumo.env.cars import ACTIVE, ENDED, WAITING
from idas_sumo.env.kernels import (
    _COLLIDED,
    _FINISHED,
    _REMOVED,
    _agent_values,
    _allowed_step,
    _end_codes,
    _first_outside,
    _hard_brakes,
    _next_speeds,
)
from idas_sumo.env.outcome import HARD_BRAKE_DETECT_MPS2
from idas_sumo.env.rewards import RewardConfig
from idas_sumo.env.scoring import StepContext, nobody_ended_scores, score
from idas_sumo.env.snapshot import MAIN, DistanceOrder, TrafficSnapshot
from idas_sumo.sim.frozen import built


def numpy_hard_brakes(*args: Any) -> tuple[np.ndarray, ...]:
    """What the step computed before ``_hard_brakes`` (its arguments, in its order)."""
    egos, agent_brake, accel, car_of_row, acting, car_copy, car_state, rows_before, copy, dist, zone_m = args
    braking = car_of_row[accel <= HARD_BRAKE_DETECT_MPS2]
    braking = braking[acting[car_copy[braking]] & (car_state[braking] != ACTIVE)]
    sumo_brakes = rows_before[braking]
    brakes = np.concatenate([egos[agent_brake], sumo_brakes[sumo_brakes >= 0]])
    brake_copy = copy[brakes]
    in_zone = np.abs(dist[brakes]) <= zone_m
    k = len(acting)
    return (
        brakes,
        brake_copy,
        in_zone,
        np.bincount(brake_copy, minlength=k),
        np.bincount(brake_copy[in_zone], minlength=k),
    )


def test_hard_brakes_match_numpy() -> None:
    rng = np.random.default_rng(2)
    for trial in range(200):
        k, n_cars = int(rng.integers(1, 5)), int(rng.integers(0, 40))
        car_copy = np.sort(rng.integers(0, k, n_cars))
        car_state = rng.choice(np.array([WAITING, ACTIVE, ENDED], dtype=np.int8), n_cars)
        rows_before = np.where(rng.random(n_cars) < 0.8, rng.permutation(n_cars), -1).astype(np.int64)
        n_before = n_cars
        on_road = np.flatnonzero(rng.random(n_cars) < 0.9)
        car_of_row = rng.permutation(on_road).astype(np.int64)
        accel = rng.choice([-4.5, -3.0, -3.0 + 1e-12, -2.0, 0.5, np.nan], len(car_of_row))
        egos = rng.permutation(n_before)[: int(rng.integers(0, n_before + 1))].astype(np.int64)
        agent_brake = rng.random(len(egos)) < 0.3
        acting = rng.random(k) < 0.7
        copy = rng.integers(0, k, n_before).astype(np.int64)
        dist = rng.choice([-60.0, -50.0, -49.9, 0.0, 50.0, 50.1, 120.0], n_before)
        args = (
            egos,
            agent_brake,
            accel,
            car_of_row,
            acting,
            car_copy,
            car_state,
            rows_before,
            copy,
            dist,
            50.0,
        )
        most = len(egos) + len(accel)
        rows, got_copy, in_zone = np.empty(most, np.int64), np.empty(most, np.int64), np.empty(most, np.bool_)
        per_copy = np.zeros((2, k), dtype=np.int64)
        m = _hard_brakes(*args, rows, got_copy, in_zone, per_copy)
        for got, want in zip(
            (rows[:m], got_copy[:m], in_zone[:m], *per_copy), numpy_hard_brakes(*args), strict=True
        ):
            assert got.dtype == want.dtype and got.tolist() == want.tolist(), trial


def test_end_codes_match_numpy() -> None:
    rng = np.random.default_rng(4)
    for trial in range(200):
        n, rows = int(rng.integers(0, 30)), int(rng.integers(1, 30))
        collided = rng.random(n) < 0.1
        row = np.where(rng.random(n) < 0.9, rng.integers(0, rows, n), -1).astype(np.int64)
        dist = rng.choice([-50.1, -50.0, -49.9, 0.0, 80.0, np.nan], rows)
        otherwise = int(rng.choice([0, 4]))
        present = row >= 0
        finished = np.zeros(n, dtype=np.bool_)
        finished[present] = dist[row[present]] <= -50.0
        want = np.where(
            collided, _COLLIDED, np.where(~present, _REMOVED, np.where(finished, _FINISHED, otherwise))
        )
        got = _end_codes(collided, row, dist, -50.0, otherwise)
        assert got.dtype == np.int64 and got.tolist() == want.tolist(), trial


@pytest.mark.parametrize("n_brakes", [0, 1, 7])
def test_impede_and_flow_parts_keep_the_former_kernels_arithmetic(n_brakes: int) -> None:
    """The impede and flow terms give, bit for bit (-0.0 included), what the former ``_penalty_parts`` kernel
    wrote: the copy's flow penalty, and -5 times the brakes each agent caused."""
    rng = np.random.default_rng(n_brakes)
    n, n_rows, k = 12, 20, 3
    copy = np.sort(rng.integers(0, k, n))
    egos = rng.permutation(n_rows)[:n].astype(np.int64)
    zone_brakes = rng.integers(0, 3, k)
    impeded_by = rng.integers(0, n_rows, n_brakes).astype(np.int64)
    want = np.zeros((n, 4))
    want[:, 3] = (-1.0 * zone_brakes)[copy]
    want[:, 2] = -5.0 * np.bincount(impeded_by, minlength=n_rows)[egos]
    z = np.zeros(n_rows)
    before = TrafficSnapshot(
        tuple(map(str, range(n_rows))), np.full(n_rows, MAIN), z, z, z, z + 5.0, z + 20.0
    )
    ctx = StepContext(
        config=RewardConfig(),
        copies=k,
        copy=copy,
        b_type=np.zeros(n),
        b_prio=np.zeros(n),
        egos=egos,
        end_code=np.zeros(n, dtype=np.int64),
        before=before,
        brakes=np.zeros(0, dtype=np.int64),
        zone_brakes=zone_brakes,
        impeded_by=impeded_by,
    )
    got = score(ctx).parts
    assert got.view(np.uint64).tolist() == want.view(np.uint64).tolist()
    # The engine's one-pass version of the same step: every output bit for bit.
    fast, slow = nobody_ended_scores(copy, egos, n_rows, k, impeded_by, zone_brakes), score(ctx)
    for a, b in ((fast.parts, slow.parts), (fast.rewards, slow.rewards), (fast.joint, slow.joint)):
        assert a.dtype == b.dtype and a.view(np.uint64).tolist() == b.view(np.uint64).tolist()


def test_action_checks_match_numpy() -> None:
    rng = np.random.default_rng(6)
    for trial in range(200):
        n = int(rng.integers(0, 20))
        actions = rng.integers(-1 if trial % 3 == 0 else 0, 8 if trial % 5 == 0 else 7, n).astype(np.int64)
        wrong = (actions < 0) | (actions >= 7)
        assert _first_outside(actions, 7) == (int(np.flatnonzero(wrong)[0]) if wrong.any() else -1), trial
        if not wrong.any():
            masks = (rng.random((n, 7)) < 0.9).astype(np.int8)
            prev = rng.choice([-4.5, -2.0, -0.1, 0.0, 0.3, 2.0], n)
            speed = rng.uniform(0.0, 3.0, 12)
            egos = rng.integers(0, 12, n).astype(np.int64)
            out = np.empty((2, n))
            ok = _allowed_step(masks, actions, prev, speed, egos, 0.2, out)
            accel, next_speed = out
            assert ok == bool(masks[np.arange(n), actions].astype(bool).all()), trial
            if ok:  # what the step computed before: next_acceleration, then _next_speeds
                want = next_acceleration(prev, actions)
                assert accel.view(np.uint64).tolist() == want.view(np.uint64).tolist(), trial
                want_speed = _next_speeds(speed, egos, want, 0.2)
                assert next_speed.view(np.uint64).tolist() == want_speed.view(np.uint64).tolist(), trial


def test_next_speeds_match_numpy() -> None:
    rng = np.random.default_rng(8)
    speed = np.concatenate([rng.uniform(0.0, 25.0, 40), [0.0, -0.0, 0.1, 0.8, np.nan, np.inf, 1e-17]])
    for trial in range(100):
        egos = rng.integers(0, len(speed), int(rng.integers(0, 30))).astype(np.int64)
        accel = rng.choice([-4.0, -2.0, -0.5, -0.0, 0.0, 0.3, 2.0, np.nan], len(egos))
        want = np.maximum(speed[egos] + accel * 0.2, 0.0)
        got = _next_speeds(speed, egos, accel, 0.2)
        assert got.view(np.uint64).tolist() == want.view(np.uint64).tolist(), trial


def test_distance_order_and_place_match_numpy() -> None:
    """``_sort_spans`` sorts each copy's rows as ``np.lexsort((dist, copy))`` does (ties, ±0, inf and NaN
    included), and ``_place_kernel`` gives ``Routes.place``'s former numpy formulas bit for bit."""
    from idas_sumo.env.routes import _place_kernel
    from idas_sumo.env.snapshot import MERGE, OUT, _sort_spans

    rng = np.random.default_rng(5)
    for t in range(400):
        # (spans up to 11 rows sort by insertion, longer ones by mergesort: both are checked)
        sizes = rng.integers(0, 12 if t % 3 else 50, size=rng.integers(1, 6))
        copy = np.repeat(np.arange(len(sizes)), sizes)
        pool = [0.0, -0.0, 1.5, 2.0, np.nan, np.inf, -np.inf, 3.25]
        dist = rng.choice(pool, size=len(copy)) if t % 2 else rng.normal(size=len(copy)).round(1)
        starts = np.searchsorted(copy, np.arange(len(sizes) + 1)).astype(np.int64)
        order, sorted_dist = _sort_spans(dist, starts)
        expected = np.lexsort((dist, copy))
        assert np.array_equal(order, expected)
        assert np.array_equal(sorted_dist.view(np.int64), dist[expected].view(np.int64))
    # place: 2 origins x 4 edge codes (the last: an edge on no route), lane-drop lanes on code 1.
    start_by = rng.uniform(-50.0, 300.0, size=(2, 4))
    incoming_by = start_by > 0.0
    limit_by = rng.choice([13.89, 16.67, 27.78], size=(2, 4))
    merged_lane = np.array([-1, 0, -1, -1])
    n = 500
    code = rng.integers(0, 4, size=n)
    origin = rng.integers(0, 2, size=n)
    lane_index = rng.integers(0, 2, size=n)
    lane_pos = np.where(rng.random(n) < 0.1, start_by[origin, code], rng.uniform(0.0, 300.0, size=n))
    got = _place_kernel(
        code, lane_pos, origin, lane_index, merged_lane, incoming_by, start_by, limit_by, 27.78, 100.0
    )
    merged = (origin == MERGE) & (lane_index == merged_lane[code])
    o = np.where(merged, 0, origin)
    incoming = incoming_by[o, code]
    dist = -(lane_pos - start_by[o, code])
    exempt = (dist >= 0.0) & (dist <= 100.0)
    own = np.where(exempt, np.maximum(limit_by[o, code], 27.78), limit_by[o, code])
    expected_out = (o, np.where(incoming, o, OUT), dist, np.where(incoming, own, limit_by[o, code]))
    for a, b in zip(got, expected_out, strict=True):
        assert np.array_equal(np.asarray(a).view(np.int64), np.asarray(b).astype(a.dtype).view(np.int64))


@pytest.mark.parametrize("copies", [1, 3])
def test_observe_own_lane_matches_the_separate_calls(copies: int) -> None:
    """The engine's one-call observe (own-lane mask) gives the rows, accelerations, priorities and masks
    of the separate numpy indexing and ``own_lane_action_masks`` it replaced, bit for bit; with the
    observations (``observe_own_lane_obs``) those of ``build_observations_checked`` too."""
    from idas_sumo.env.front_cars import observe_own_lane, observe_own_lane_obs, own_lane_action_masks
    from idas_sumo.env.layout import OBS_DIM
    from idas_sumo.env.observation import build_observations_checked

    rng = np.random.default_rng(11 + copies)
    for trial in range(60):
        sizes = rng.integers(1, 12, copies)
        n = int(sizes.sum())
        copy = np.repeat(np.arange(copies), sizes).astype(np.int64)
        bounds = np.concatenate(([0], np.cumsum(sizes))).astype(np.int64)
        dist = np.round(rng.uniform(-40.0, 150.0, n), 1)
        snap = TrafficSnapshot(
            tuple(f"v{i}" for i in range(n)),
            np.where(dist < 0.0, 2, rng.integers(0, 2, n)).astype(np.int64),
            dist,
            rng.uniform(0.0, 15.0, n),
            rng.uniform(-3.0, 2.0, n),
            rng.choice([4.0, 5.0], n),
            rng.choice([13.89, 16.67], n),
            copy if copies > 1 else None,
            bounds if copies > 1 else None,
        )
        car_row = rng.permutation(n).astype(np.int64)  # car c drives in row car_row[c]
        car_accel = rng.choice([-4.5, -1.0, 0.0, 0.3, 2.0], n)
        agent_car = np.sort(rng.choice(n, int(rng.integers(1, n + 1)), replace=False)).astype(np.int64)
        agent_copy = copy[car_row[agent_car]]
        prio = rng.uniform(0.0, 1.0, (copies, 3))
        egos, prev, b_prio, masks = observe_own_lane(
            snap, copy, car_row, car_accel, agent_car, agent_copy, prio
        )
        want_egos = car_row[agent_car]
        assert egos.tolist() == want_egos.tolist(), trial
        assert prev.view(np.uint64).tolist() == car_accel[agent_car].view(np.uint64).tolist(), trial
        want_prio = prio[agent_copy, snap.road[want_egos]]
        assert b_prio.view(np.uint64).tolist() == want_prio.view(np.uint64).tolist(), trial
        want_masks = own_lane_action_masks(snap, want_egos, car_accel[agent_car])
        assert masks.dtype == want_masks.dtype and masks.tolist() == want_masks.tolist(), trial
        # With the observations in the same call: the same four, and ``build_observations_checked``'s rows.
        b_type = rng.choice([0.0, 1.0], len(agent_car))
        obs = np.zeros((len(agent_car), OBS_DIM), dtype=np.float32)
        *same, finite, spread = observe_own_lane_obs(
            snap, copy, car_row, car_accel, agent_car, agent_copy, prio, b_type, obs
        )
        for got, want in zip(same, (egos, prev, b_prio, masks), strict=True):
            assert got.dtype == want.dtype and got.tobytes() == want.tobytes(), trial
        want_obs, want_finite = build_observations_checked(snap, want_egos, prev, b_prio, b_type)
        assert obs.tobytes() == want_obs.tobytes() and finite == want_finite, trial
        assert spread == np.ptp(snap.speed_mps), trial


def test_step_ends_matches_its_parts() -> None:
    """``_step_ends``: ``_end_codes`` of the agents' rows, how many ended, and whether any agent chose the
    hard brake or any car brakes at the detection threshold or harder."""
    from idas_sumo.env.kernels import _step_ends

    rng = np.random.default_rng(12)
    for trial in range(200):
        n_cars, n = int(rng.integers(1, 20)), int(rng.integers(0, 10))
        car_row = rng.integers(-1, 15, n_cars).astype(np.int64)
        agent_car = rng.integers(0, n_cars, n).astype(np.int64)
        collided = rng.random(n) < 0.1
        dist = rng.uniform(-30.0, 100.0, 15)
        applied = rng.integers(0, 7, n).astype(np.int64)
        accel = rng.choice([-4.5, -3.0, -2.9, 0.0, 1.0], int(rng.integers(0, 15)))
        otherwise = int(rng.integers(0, 2)) * 4
        code, ended, may = _step_ends(collided, car_row, agent_car, dist, -10.0, otherwise, applied, 5, accel)
        want = _end_codes(collided, car_row[agent_car], dist, -10.0, otherwise)
        assert code.tolist() == want.tolist() and ended == int(np.count_nonzero(want)), trial
        assert may == bool((applied == 5).any() or (accel <= HARD_BRAKE_DETECT_MPS2).any()), trial


def test_agent_values_match_numpy() -> None:
    """``MergeEngine.agent_values``' one compiled pass against the numpy gathers it replaced."""
    rng = np.random.default_rng(5)
    n_cars, n_rows = 12, 7
    car_row = rng.integers(-1, n_rows, n_cars)
    admitted = rng.random(n_cars) < 0.5
    car_accel, speed, accel, dist = rng.normal(size=n_cars), *rng.normal(size=(3, n_rows))
    road = rng.integers(0, 3, n_rows)
    car = rng.permutation(n_cars)[:9]
    rows = car_row[car]
    r = np.where(rows >= 0, rows, 0)
    want = (
        speed[r],
        np.where(admitted[car], car_accel[car], accel[r]),
        dist[r],
        np.where(rows >= 0, road[r], -1),
    )
    values, got_road = np.empty((3, len(car))), np.empty(len(car), dtype=np.int64)
    _agent_values(car, car_row, admitted, car_accel, speed, accel, dist, road, values, got_road)
    got = (*values, got_road)
    assert (rows < 0).any() and admitted[car].any() and not admitted[car].all()
    for g, w in zip(got, want, strict=True):
        np.testing.assert_array_equal(g, w)


def test_built_is_the_dataclass_made_by_its_init() -> None:
    """``sim.frozen.built`` gives what the frozen dataclass's own ``__init__`` gives, and refuses a record
    missing a field or with an unknown one."""
    order = np.arange(3)
    dist = np.array([1.0, 2.0, 3.0])
    starts = np.array([0, 3])
    made = built(DistanceOrder, order=order, sorted_dist=dist, starts=starts)
    assert made == DistanceOrder(order, dist, starts) and type(made) is DistanceOrder
    with pytest.raises(TypeError, match="exactly its fields"):
        built(DistanceOrder, order=order, sorted_dist=dist)
    with pytest.raises(TypeError, match="exactly its fields"):
        built(DistanceOrder, order=order, sorted_dist=dist, starts=starts, extra=1)
    with pytest.raises(AttributeError):  # still frozen
        made.order = order  # type: ignore[misc]


def test_critic_states_place_each_car_in_its_slot_with_hand_worked_features() -> None:
    """Copy 0 holds cars 0-17, copy 1 cars 18-23. On the road: copy 0's car 0 (slot 0, outgoing road) and
    car 17 (past the 16 slots: left out), copy 1's car 20 (slot 2, merge road, acting). The states come
    in the order asked for (copy 1, then copy 0)."""
    from idas_sumo.env.snapshot import MERGE, OUT
    from idas_sumo.env.state_layout import STATE_DIM, STATE_FEATURES, STATE_SLOTS, critic_states

    snap = TrafficSnapshot(
        ids=("v0", "v17", "v2"),
        road=np.array([OUT, MAIN, MERGE]),
        dist_to_merge_m=np.array([-25.0, 50.0, 125.0]),
        speed_mps=np.array([5.0, 1.0, 10.0]),
        accel_mps2=np.array([1.0, 0.0, -2.0]),
        length_m=np.full(3, 5.0),
        speed_limit_mps=np.full(3, 20.0),
    )
    bounds, first, car = np.array([0, 2, 3]), np.array([0, 18, 24]), np.array([0, 17, 20])
    b_type = np.zeros(24)
    b_type[0], b_type[20] = 2.0, 1.0
    acting = np.zeros(24, dtype=np.bool_)
    acting[20] = True
    prio_by_road = np.array([[1.0, 0.0, 1.0], [0.0, 1.0, 1.0]])
    states = critic_states(snap, bounds, np.array([1, 0]), car, first, b_type, acting, prio_by_road)

    assert states.shape == (2, STATE_DIM) and states.dtype == np.float32
    copy1, copy0 = states.reshape(2, STATE_SLOTS, STATE_FEATURES)
    # present, main, merge, out, 125 / 250 m, 10 / 20 m/s, -2 / 4 m/s², copy 1's b_prio on MERGE, 1 / 2, acting
    expected = np.array([1, 0, 1, 0, 0.5, 0.5, -0.5, 1.0, 0.5, 1], dtype=np.float32)
    np.testing.assert_array_equal(copy1[2], expected)
    assert not np.delete(copy1, 2, axis=0).any()
    expected = np.array([1, 0, 0, 1, -0.1, 0.25, 0.25, 1.0, 1.0, 0], dtype=np.float32)
    np.testing.assert_array_equal(copy0[0], expected)
    assert not copy0[1:].any(), "car 17 has no slot"
