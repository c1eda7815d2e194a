"""IDM and FSM+IDM baselines: maths against hand-worked numbers, leader choice, action selection."""

from __future__ import annotations

import numpy as np
import pytest

from idas_sumo.baselines.fsm_idm import (
    SIMILAR_DISTANCE_WINDOW_M,
    FSMParams,
    fsm_idm_acceleration,
    real_leader_idm_acceleration,
    virtual_leaders,
)
from idas_sumo.baselines.policies import (
    BASELINES,
    fsm_idm_actions,
    fsm_idm_smooth_actions,
    hard_brake_only_when_forced,
    idm_actions,
)
from idas_sumo.env.actions import (
    HARD_BRAKE,
    HARD_BRAKE_MPS2,
    N_ACTIONS,
    RELEASE_BRAKE,
    candidate_accelerations,
    closest_allowed_action,
    kinematic_mask,
)
from idas_sumo.env.snapshot import MAIN, MERGE, NO_LEADER, OUT, TrafficSnapshot
from idas_sumo.physics.idm import IDMParams, idm_acceleration, idm_acceleration_one

# Default IDM throughout: a = 2, b = 2 (so 2·sqrt(ab) = 4), s0 = 2 m, T = 1 s, delta = 4.
IDM = IDMParams()
LENGTH_M = 5.0


def make_snapshot(
    vehicles: list[tuple[int, float, float]], limit_mps: float = 20.0, length_m: float = LENGTH_M
) -> TrafficSnapshot:
    """vehicles: (road, dist_to_merge_m, speed_mps); ids are v0, v1, ... in that order."""
    n = len(vehicles)
    return TrafficSnapshot(
        ids=tuple(f"v{i}" for i in range(n)),
        road=np.array([v[0] for v in vehicles], dtype=np.int64),
        dist_to_merge_m=np.array([v[1] for v in vehicles], dtype=np.float64),
        speed_mps=np.array([v[2] for v in vehicles], dtype=np.float64),
        accel_mps2=np.zeros(n),
        length_m=np.full(n, length_m),
        speed_limit_mps=np.full(n, limit_mps),
    )


EGO = np.array([0])

# --------------------------------------------------------------------------------------------- IDM


def test_idm_free_road() -> None:
    # v = 10, v0 = 20, no leader: a = 2·(1 − (10/20)^4) = 2·(1 − 0.0625) = 1.875
    assert idm_acceleration(10.0, 20.0, np.inf, 0.0, IDM) == pytest.approx(1.875)


def test_idm_no_leader_ignores_approach_rate() -> None:
    # gap = inf: the interaction term vanishes whatever the approach rate (same 1.875 as above).
    out = idm_acceleration([10.0, 10.0], 20.0, np.inf, [0.0, 50.0], IDM)
    np.testing.assert_allclose(out, [1.875, 1.875])


def test_idm_standstill_at_min_gap() -> None:
    # v = 0, s = s0 = 2: s* = 2 + 0 = 2, a = 2·(1 − 0 − (2/2)^2) = 0
    assert idm_acceleration(0.0, 20.0, 2.0, 0.0, IDM) == pytest.approx(0.0, abs=1e-12)


def test_idm_following_same_speed() -> None:
    # v = 10, leader 30 m ahead at 10 m/s (dv = 0): s* = 2 + 10·1 = 12,
    # a = 2·(1 − 0.0625 − (12/30)^2) = 2·(1 − 0.0625 − 0.16) = 1.555
    assert idm_acceleration(10.0, 20.0, 30.0, 0.0, IDM) == pytest.approx(1.555)


def test_idm_approaching() -> None:
    # v = 10, leader at 6 m/s (dv = 4), gap 30: s* = 2 + 10 + 10·4/4 = 22,
    # a = 2·(1 − 0.0625 − (22/30)^2) = 2·(1 − 0.0625 − 0.537777…) = 0.799444…
    expected = 2.0 * (1.0 - 0.0625 - (22.0 / 30.0) ** 2)
    assert expected == pytest.approx(0.799444, abs=1e-6)
    assert idm_acceleration(10.0, 20.0, 30.0, 4.0, IDM) == pytest.approx(expected)


def test_idm_opening_gap_clamps_dynamic_term() -> None:
    # v = 10, leader at 20 m/s (dv = −10), gap 30: v·T + v·dv/4 = 10 − 25 < 0 -> clamped, s* = 2,
    # a = 2·(1 − 0.0625 − (2/30)^2) = 1.866111…
    assert idm_acceleration(10.0, 20.0, 30.0, -10.0, IDM) == pytest.approx(2.0 * (1 - 0.0625 - 1 / 225))


def test_idm_of_one_vehicle_is_the_array_function() -> None:
    """``idm_acceleration_one`` (what the env's kernels compile) against the array function: bit for bit
    without a free-road term (desired speed inf), within rounding of the power with one."""
    rng = np.random.default_rng(5)
    n = 2000
    speed, gap, rate = rng.uniform(-1.0, 35.0, n), rng.uniform(-5.0, 200.0, n), rng.uniform(-20.0, 20.0, n)
    gap[::7] = np.inf
    speed[::5] = 0.0
    desired = rng.uniform(5.0, 30.0, n)
    scalars = (IDM.max_accel_mps2, IDM.comfortable_decel_mps2, IDM.min_gap_m, IDM.time_headway_s, IDM.delta)
    for v0, exact in ((np.full(n, np.inf), True), (desired, False)):
        one = np.array(
            [idm_acceleration_one(*case, *scalars) for case in zip(speed, v0, gap, rate, strict=True)]
        )
        array = idm_acceleration(speed, v0, gap, rate, IDM)
        if exact:
            assert one.view(np.uint64).tolist() == array.view(np.uint64).tolist()
        else:
            np.testing.assert_allclose(one, array, rtol=1e-14, atol=1e-14)
    assert idm_acceleration_one(10.0, 20.0, 30.0, 4.0, *scalars) == pytest.approx(
        2.0 * (1.0 - 0.0625 - (22.0 / 30.0) ** 2)
    )


# ----------------------------------------------------------------------------- FSM+IDM leader choice


def test_window_constant_is_documented_range() -> None:
    assert 15.0 <= SIMILAR_DISTANCE_WINDOW_M <= 20.0
    assert FSMParams().similar_distance_window_m == SIMILAR_DISTANCE_WINDOW_M


@pytest.mark.parametrize("window", [0.0, -1.0, float("inf"), float("nan")])
def test_fsm_params_reject_bad_window(window: float) -> None:
    with pytest.raises(ValueError, match="similar_distance_window_m"):
        FSMParams(similar_distance_window_m=window)


def test_other_road_car_just_ahead_is_chosen_and_restricts() -> None:
    # Ego on main 100 m before the merge, a merge car 10 m closer to it: projected gap 10 − 5 = 5 m.
    snap = make_snapshot([(MAIN, 100.0, 15.0), (MERGE, 90.0, 15.0)])
    leader, gap, speed = virtual_leaders(snap, EGO)
    assert leader.tolist() == [1]
    np.testing.assert_allclose(gap, [5.0])
    np.testing.assert_allclose(speed, [15.0])
    # Plain IDM sees a free road: 2·(1 − (15/20)^4) = 1.3671875.
    plain = real_leader_idm_acceleration(snap, EGO)
    np.testing.assert_allclose(plain, [2.0 * (1 - 0.75**4)])
    # FSM+IDM: s* = 2 + 15 = 17, a = 2·(1 − 0.31640625 − (17/5)^2) = −21.75281…
    fsm = fsm_idm_acceleration(snap, EGO)
    np.testing.assert_allclose(fsm, [2.0 * (1 - 0.75**4 - (17 / 5) ** 2)])
    assert fsm[0] < plain[0]


def test_merge_ego_sees_main_car_ahead() -> None:
    snap = make_snapshot([(MERGE, 60.0, 12.0), (MAIN, 50.0, 18.0)])
    leader, gap, _ = virtual_leaders(snap, EGO)
    assert leader.tolist() == [1]
    np.testing.assert_allclose(gap, [5.0])


@pytest.mark.parametrize(
    ("other_dist_m", "why"),
    [
        (105.0, "just behind"),
        (100.0, "side by side"),
        (100.0 - SIMILAR_DISTANCE_WINDOW_M - 0.5, "beyond the window"),
    ],
)
def test_other_road_car_not_ahead_or_too_far_is_ignored(other_dist_m: float, why: str) -> None:
    # The paper's documented FSM+IDM failure mode: cars behind or level with the ego are not leaders.
    snap = make_snapshot([(MAIN, 100.0, 15.0), (MERGE, other_dist_m, 15.0)])
    leader, gap, speed = virtual_leaders(snap, EGO)
    assert leader.tolist() == [NO_LEADER], why
    assert np.isinf(gap[0])
    assert speed[0] == 15.0  # own speed: no approach rate
    np.testing.assert_allclose(fsm_idm_acceleration(snap, EGO), real_leader_idm_acceleration(snap, EGO))


def test_window_edge_is_inclusive() -> None:
    snap = make_snapshot([(MAIN, 100.0, 15.0), (MERGE, 100.0 - SIMILAR_DISTANCE_WINDOW_M, 15.0)])
    leader, gap, _ = virtual_leaders(snap, EGO)
    assert leader.tolist() == [1]
    np.testing.assert_allclose(gap, [SIMILAR_DISTANCE_WINDOW_M - LENGTH_M])


def test_custom_window_is_used() -> None:
    snap = make_snapshot([(MAIN, 100.0, 15.0), (MERGE, 90.0, 15.0)])
    assert virtual_leaders(snap, EGO, window_m=5.0)[0].tolist() == [NO_LEADER]
    narrow = FSMParams(similar_distance_window_m=5.0)
    np.testing.assert_allclose(
        fsm_idm_acceleration(snap, EGO, narrow), real_leader_idm_acceleration(snap, EGO)
    )


def test_nearest_of_several_candidates_wins_and_same_road_is_not_virtual() -> None:
    snap = make_snapshot(
        [
            (MAIN, 100.0, 15.0),  # ego
            (MERGE, 85.0, 10.0),  # 15 m ahead
            (MERGE, 93.0, 11.0),  # 7 m ahead: nearest other-road car
            (MAIN, 95.0, 15.0),  # same road: a real leader, never a virtual one
            (OUT, 88.0, 15.0),  # outgoing road (constructed): real-leader business only
        ]
    )
    leader, gap, speed = virtual_leaders(snap, EGO)
    assert leader.tolist() == [2]
    np.testing.assert_allclose(gap, [2.0])
    np.testing.assert_allclose(speed, [11.0])


def test_overlapping_projection_gives_nonpositive_gap_and_hard_braking() -> None:
    # 2 m ahead in projection but 5 m long: gap −3 m; IDM clips it at 1 cm and demands a huge brake.
    snap = make_snapshot([(MAIN, 100.0, 15.0), (MERGE, 98.0, 15.0)])
    _, gap, _ = virtual_leaders(snap, EGO)
    np.testing.assert_allclose(gap, [-3.0])
    accel = fsm_idm_acceleration(snap, EGO)
    assert np.isfinite(accel[0]) and accel[0] < HARD_BRAKE_MPS2
    action = fsm_idm_actions(snap, EGO, np.array([0.0]), np.ones((1, N_ACTIONS), dtype=np.int8))
    assert action.tolist() == [HARD_BRAKE]


def test_ego_on_out_has_no_virtual_leader() -> None:
    # Constructed: an incoming-road car "ahead" in projection of an ego already past the merge point.
    snap = make_snapshot([(OUT, -10.0, 15.0), (MERGE, -12.0, 15.0), (MAIN, -15.0, 15.0)])
    leader, gap, _ = virtual_leaders(snap, EGO)
    assert leader.tolist() == [NO_LEADER]
    assert np.isinf(gap[0])


def test_out_car_ahead_is_a_real_leader_not_virtual() -> None:
    # Ego on main at 10 m, a car 20 m past the merge on OUT: bumper gap 30 − 5 = 25 m.
    snap = make_snapshot([(MAIN, 10.0, 10.0), (OUT, -20.0, 10.0)])
    assert virtual_leaders(snap, EGO)[0].tolist() == [NO_LEADER]
    # s* = 2 + 10 = 12, a = 2·(1 − 0.0625 − (12/25)^2) = 1.4142
    expected = 2.0 * (1 - 0.0625 - (12 / 25) ** 2)
    np.testing.assert_allclose(real_leader_idm_acceleration(snap, EGO), [expected])
    np.testing.assert_allclose(fsm_idm_acceleration(snap, EGO), [expected])


def test_fsm_takes_the_more_restrictive_leader() -> None:
    # Real leader 7 m ahead (gap 2 m) is tighter than the virtual one 18 m ahead (gap 13 m).
    snap = make_snapshot([(MAIN, 100.0, 15.0), (MAIN, 93.0, 15.0), (MERGE, 82.0, 15.0)])
    real = real_leader_idm_acceleration(snap, EGO)
    v = 15.0
    virtual = idm_acceleration(v, 20.0, 13.0, 0.0, IDM)
    assert real[0] < virtual
    np.testing.assert_allclose(fsm_idm_acceleration(snap, EGO), real)


def test_vectorised_over_egos_and_empty() -> None:
    snap = make_snapshot([(MAIN, 100.0, 15.0), (MERGE, 90.0, 15.0), (MERGE, 50.0, 10.0)])
    leader, _, _ = virtual_leaders(snap, np.array([0, 1, 2]))
    # v0 sees v1 ahead; v1 sees nobody (v0 is behind it); v2 is 50 m ahead of v0 — outside the window.
    assert leader.tolist() == [1, NO_LEADER, NO_LEADER]
    assert fsm_idm_acceleration(snap, np.array([], dtype=np.int64)).shape == (0,)
    with pytest.raises(ValueError, match="ego indices"):
        virtual_leaders(snap, np.array([3]))


# ------------------------------------------------------------------------- action selection


def test_closest_allowed_action_hand_cases() -> None:
    full = np.ones((1, N_ACTIONS), dtype=np.int8)
    # prev 0, target 0.15: +0.1 and +0.2 are both 0.05 away -> tie goes to the lower, +0.1 (action 3).
    assert closest_allowed_action([0.15], [0.0], full).tolist() == [3]
    # target 1.0 from 0: +0.2 is closest.
    assert closest_allowed_action([1.0], [0.0], full).tolist() == [4]
    # target −10: hard brake (−4) beats −0.2.
    assert closest_allowed_action([-10.0], [0.0], full).tolist() == [HARD_BRAKE]
    # the rule mask forbids speeding up: target 1.0 -> keep a = 0 (da0, action 2).
    no_accel = np.array([[1, 1, 1, 0, 0, 1, 0]], dtype=np.int8)
    assert closest_allowed_action([1.0], [0.0], no_accel).tolist() == [2]
    # da0 and release brake both give 0 m/s²: the lower index wins.
    assert closest_allowed_action([0.0], [0.0], full).tolist() == [2]
    # directly after a hard brake only hard brake / release are allowed (kinematic mask).
    after = kinematic_mask([HARD_BRAKE_MPS2]).astype(np.int8)
    assert closest_allowed_action([-3.0], [HARD_BRAKE_MPS2], after).tolist() == [HARD_BRAKE]
    assert closest_allowed_action([-1.0], [HARD_BRAKE_MPS2], after).tolist() == [RELEASE_BRAKE]
    # −2 is exactly between −4 (hard brake) and 0 (release): the tie goes to the safer hard brake.
    assert closest_allowed_action([-2.0], [HARD_BRAKE_MPS2], after).tolist() == [HARD_BRAKE]


def test_closest_allowed_action_never_returns_masked_action() -> None:
    rng = np.random.default_rng(0)
    n = 512
    for _ in range(20):
        prev = np.round(rng.choice(np.r_[np.arange(-20, 21) / 10.0, HARD_BRAKE_MPS2], size=n), 6)
        target = rng.uniform(-12.0, 4.0, size=n)
        mask = (rng.random((n, N_ACTIONS)) < rng.uniform(0.05, 0.9)).astype(np.int8)
        mask[np.arange(n), rng.integers(0, N_ACTIONS, size=n)] = 1  # every row allows something
        actions = closest_allowed_action(target, prev, mask)
        assert actions.dtype == np.int64 and actions.shape == (n,)
        assert np.all(mask[np.arange(n), actions] == 1)
        # ...and it is the closest allowed one.
        cand = candidate_accelerations(prev)
        dist = np.where(mask == 1, np.abs(cand - target[:, None]), np.inf)
        np.testing.assert_allclose(dist[np.arange(n), actions], dist.min(axis=1), atol=1e-9)


def test_closest_allowed_action_rejects_bad_input() -> None:
    with pytest.raises(ValueError, match="allow no action"):
        closest_allowed_action([0.0], [0.0], np.zeros((1, N_ACTIONS), dtype=np.int8))
    with pytest.raises(ValueError, match="expected"):
        closest_allowed_action([0.0, 0.0], [0.0], np.ones((2, N_ACTIONS), dtype=np.int8))
    with pytest.raises(ValueError, match="finite"):
        closest_allowed_action([np.nan], [0.0], np.ones((1, N_ACTIONS), dtype=np.int8))


# --------------------------------------------------------------------------------- policies


def test_idm_policy_ignores_other_road_fsm_does_not() -> None:
    snap = make_snapshot([(MAIN, 100.0, 15.0), (MERGE, 90.0, 15.0)])
    full = np.ones((1, N_ACTIONS), dtype=np.int8)
    prev = np.array([0.0])
    # Plain IDM sees a free road (target +1.37 m/s²) and speeds up by the largest step.
    assert idm_actions(snap, EGO, prev, full).tolist() == [4]
    assert idm_actions(snap, EGO, prev, full, IDMParams()).tolist() == [4]
    assert fsm_idm_actions(snap, EGO, prev, full).tolist() == [HARD_BRAKE]


def test_smooth_fsm_eases_down_where_fsm_brakes_hard() -> None:
    # The same virtual leader as above: FSM+IDM wants far below -4 m/s² and brakes hard; FSM+IDM-smooth,
    # with every Δa allowed, takes the strongest one instead (a = 0 - 0.2).
    snap = make_snapshot([(MAIN, 100.0, 15.0), (MERGE, 90.0, 15.0)])
    full = np.ones((1, N_ACTIONS), dtype=np.int8)
    prev = np.array([0.0])
    assert fsm_idm_actions(snap, EGO, prev, full).tolist() == [HARD_BRAKE]
    assert fsm_idm_smooth_actions(snap, EGO, prev, full).tolist() == [0]
    # Where the mask leaves only the hard brake (and at -2 m/s² the lower Δa steps are out of range), it
    # still brakes hard: the brake is taken away only while a Δa action is allowed.
    forced = np.array([[0, 0, 0, 0, 0, 1, 0]], dtype=np.int8)
    assert fsm_idm_smooth_actions(snap, EGO, prev, forced).tolist() == [HARD_BRAKE]


def test_hard_brake_only_when_forced_hand_cases() -> None:
    masks = np.array(
        [
            [1, 1, 1, 1, 1, 1, 0],  # every Δa allowed: the brake goes
            [1, 0, 0, 0, 0, 1, 0],  # one Δa left (the rule mask at the limit): the brake goes
            [0, 0, 0, 0, 0, 1, 1],  # only brake and release: both stay
            [0, 0, 0, 0, 0, 1, 0],  # only the brake: it stays
        ],
        dtype=np.int8,
    )
    out = hard_brake_only_when_forced(masks)
    assert out[:, HARD_BRAKE].tolist() == [0, 0, 1, 1]
    np.testing.assert_array_equal(np.delete(out, HARD_BRAKE, axis=1), np.delete(masks, HARD_BRAKE, axis=1))
    assert masks[0, HARD_BRAKE] == 1  # the caller's mask is not changed


def test_registry() -> None:
    assert set(BASELINES) == {"idm", "fsm_idm", "fsm_idm_smooth"}
    snap = make_snapshot([(MAIN, 100.0, 15.0), (MERGE, 90.0, 15.0)])
    full = np.ones((1, N_ACTIONS), dtype=np.int8)
    for name, policy in BASELINES.items():
        actions = policy(snap, EGO, np.array([0.0]), full, FSMParams())
        assert actions.shape == (1,), name


def test_other_road_leaders_for_the_safety_mask() -> None:
    from idas_sumo.env.snapshot import other_road_leaders

    # merge ego at 60 m; main cars at 50 m (ahead by 10 m: gap 10 - 5 = 5 m) and 30 m (further ahead).
    snap = make_snapshot([(MERGE, 60.0, 10.0), (MAIN, 50.0, 10.0), (MAIN, 30.0, 10.0)])
    leader, gap = other_road_leaders(snap, np.array([0]), max_ahead_m=np.inf, zone_m=100.0)
    assert leader.tolist() == [1] and gap.tolist() == [5.0]
    # Outside the zone (ego at 120 m from the merge point) nobody counts.
    far = make_snapshot([(MERGE, 120.0, 10.0), (MAIN, 50.0, 10.0)])
    assert other_road_leaders(far, np.array([0]), max_ahead_m=np.inf, zone_m=100.0)[0].tolist() == [NO_LEADER]
    # Level cars: with level_counts_for_main the merge car sees the main car (gap -5), never the reverse.
    level = make_snapshot([(MAIN, 40.0, 10.0), (MERGE, 40.0, 10.0)])
    leader, gap = other_road_leaders(level, np.array([0, 1]), np.inf, 100.0, level_counts_for_main=True)
    assert leader.tolist() == [NO_LEADER, 0] and gap.tolist() == [np.inf, -5.0]
    assert other_road_leaders(level, np.array([0, 1]), np.inf, 100.0)[0].tolist() == [NO_LEADER, NO_LEADER]
    # A flagged vehicle (a SUMO car that yields at the junction by itself) is nobody's leader.
    assert other_road_leaders(
        snap, np.array([0]), np.inf, 100.0, never_leading=np.array([False, True, False])
    )[0].tolist() == [2]
