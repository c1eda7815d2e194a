"""The three action masks against hand-worked numbers, and a masked action is never applied."""

from __future__ import annotations

import numpy as np
import pytest

from idas_sumo.env.actions import (
    HARD_BRAKE,
    N_ACTIONS,
    RELEASE_BRAKE,
    MaskInputs,
    action_masks,
    candidate_accelerations,
    effective_speed_limit,
    kinematic_mask,
    next_acceleration,
    peak_speed_gain,
    rule_mask,
    safety_bound,
    safety_mask,
)
from idas_sumo.env.parallel import GONE
from idas_sumo.physics.idm import IDMParams, idm_acceleration

INF = np.inf


def masks_for(prev: float, v: float, limit: float, gap: float = INF, leader_v: float = 0.0) -> list[int]:
    m = action_masks(
        MaskInputs(
            prev_accel_mps2=np.array([prev]),
            speed_mps=np.array([v]),
            speed_limit_mps=np.array([limit]),
            gap_m=np.array([gap]),
            leader_speed_mps=np.array([leader_v]),
        )
    )
    assert m.dtype == np.int8 and m.shape == (1, N_ACTIONS)
    return m[0].tolist()


def test_action_accelerations() -> None:
    # Δa = -0.2, -0.1, 0, +0.1, +0.2 on top of a_prev = 0.5; hard brake -4; release 0.
    np.testing.assert_allclose(candidate_accelerations([0.5])[0], [0.3, 0.4, 0.5, 0.6, 0.7, -4.0, 0.0])
    # The 0.1 grid stays exact after many small steps.
    a = np.zeros(1)
    for _ in range(30):
        a = next_acceleration(a, [3])
    assert a[0] == 3.0
    with pytest.raises(ValueError):
        next_acceleration([0.0], [N_ACTIONS])


def test_speed_limit_hand_worked() -> None:
    # v = 14.9 m/s on the 15 m/s road, a_prev = 0.5. Peak speed while easing off at 0.2 m/s² per step:
    #   Δa -0.2 -> a 0.3: steps at 0.3, 0.1 -> +0.08 -> 14.98 ok
    #   Δa -0.1 -> a 0.4: steps at 0.4, 0.2 -> +0.12 -> 15.02 too fast
    #   Δa  0   -> a 0.5: steps at 0.5, 0.3, 0.1 -> +0.18 -> 15.08 too fast (and +0.1, +0.2 more so)
    # Hard brake is never masked; release (a = 0) keeps 14.9.
    assert rule_mask([0.5], [14.9], [15.0])[0].tolist() == [True, False, False, False, False, True, True]
    # Release brake is only allowed right after a hard brake (kinematic mask), so the full mask drops it.
    assert masks_for(0.5, 14.9, 15.0) == [1, 0, 0, 0, 0, 1, 0]
    np.testing.assert_allclose(peak_speed_gain([0.0, 0.2, 0.3, 2.0, -1.0]), [0.0, 0.04, 0.08, 2.2, -0.2])


def test_full_throttle_towards_the_limit_never_needs_a_hard_brake() -> None:
    # Always take the strongest allowed Δa action from 10 m/s on a 20 m/s road: the rule mask makes the
    # agent ease off in time, so it reaches the limit without exceeding it and without a forced hard brake.
    a, v = 0.0, 10.0
    for _ in range(200):
        mask = masks_for(a, v, 20.0)
        assert any(mask[:5]), f"only the hard brake left at v = {v:.2f}, a = {a:.1f}"
        action = max(i for i in range(5) if mask[i])
        a = float(next_acceleration([a], [action])[0])
        v += a * 0.2
        assert v <= 20.0 + 1e-9
    assert v == pytest.approx(20.0, abs=0.05)


def test_merge_exemption_within_100_m() -> None:
    # The merge car (15 m/s road) may go up to the outgoing road's 20 m/s within 100 m of the merge point.
    limits = effective_speed_limit([15.0, 15.0, 15.0, 15.0, 20.0], [250.0, 100.1, 100.0, 0.0, 50.0], 20.0)
    np.testing.assert_allclose(limits, [15.0, 15.0, 20.0, 20.0, 20.0])
    # So at 14.9 m/s, 80 m from the merge point, accelerating is no longer masked by the rule.
    limit = float(effective_speed_limit(15.0, 80.0, 20.0))
    assert masks_for(0.5, 14.9, limit) == [1, 1, 1, 1, 1, 1, 0]
    # Already above 20 m/s inside the exemption: only slowing enough helps (v + a·dt <= 20 needs a <= -1).
    assert masks_for(-1.0, 20.2, limit)[:5] == [1, 1, 1, 0, 0]


def test_idm_safety_bound_hand_worked() -> None:
    # v = 10, gap = 12, leader at 10 m/s (dv = 0): s* = s0 + v·T = 2 + 10·1 = 12 m,
    # bound = a_max·(1 - (s*/s)²) = 2·(1 - 1) = 0 m/s².
    np.testing.assert_allclose(safety_bound([10.0], [12.0], [10.0]), [0.0], atol=1e-12)
    # From a_prev = 0: Δa ≤ 0 allowed, Δa > 0 masked; hard brake allowed.
    assert safety_mask([0.0], [10.0], [12.0], [10.0])[0].tolist() == [
        True,
        True,
        True,
        False,
        False,
        True,
        True,
    ]
    # Closing in: v = 10, leader 5 m/s, gap 20: s* = 2 + 10 + 10·5/(2·√(2·2)) = 24.5,
    # bound = 2·(1 - (24.5/20)²) = -1.00125 m/s².
    np.testing.assert_allclose(safety_bound([10.0], [20.0], [5.0]), [-1.00125])
    # No leader: no bound.
    assert safety_bound([10.0], [INF], [0.0])[0] == INF


def numpy_safety_bound(
    speed: np.ndarray, gap: np.ndarray, leader_speed: np.ndarray, params: IDMParams
) -> np.ndarray:
    """The safety bound as numpy's IDM computes it (the compiled ``safety_bound`` must match it bit for bit)."""
    bound = idm_acceleration(speed, np.inf, gap, speed - leader_speed, params)
    return np.where(np.isinf(gap), np.inf, bound)


@pytest.mark.filterwarnings("ignore::RuntimeWarning")  # numpy's warnings on the inf and NaN inputs
@pytest.mark.parametrize("params", [IDMParams(), IDMParams(2.5, 3.0, 1.5, 1.2, 3.0)])
def test_compiled_safety_bound_is_numpys_idm_bit_for_bit(params: IDMParams) -> None:
    rng = np.random.default_rng(3)
    special = [0.0, -0.0, 0.01, 0.005, 1e-300, 1e300, -3.0, INF, -INF, np.nan]
    # Hand-picked: every pair of special values for speed and gap, leader speeds around the speed.
    grid_v, grid_gap = (a.ravel() for a in np.meshgrid(special, special))
    cases = [
        (grid_v, grid_gap, grid_v),
        (grid_v, grid_gap, np.zeros_like(grid_v)),
        (grid_v, grid_gap, grid_gap),
    ]
    for _ in range(20):
        n = 5000
        speed, gap, leader = (
            rng.uniform(-1.0, 35.0, n),
            rng.uniform(-5.0, 200.0, n),
            rng.uniform(-1.0, 35.0, n),
        )
        for values in (speed, gap, leader):
            odd = rng.random(n) < 0.1
            values[odd] = rng.choice(special, int(odd.sum()))
        speed[rng.random(n) < 0.1] = 0.0
        gap[rng.random(n) < 0.2] = INF
        cases.append((speed, gap, leader))
    for speed, gap, leader in cases:
        compiled = safety_bound(speed, gap, leader, params)
        expected = numpy_safety_bound(speed, gap, leader, params)
        # NaN where numpy has NaN (the sign of a NaN from ``** delta`` differs between libm and numpy's SIMD
        # power), every other value bit for bit (signed zeros included).
        nan = np.isnan(expected)
        assert np.isnan(compiled).tolist() == nan.tolist()
        assert compiled[~nan].view(np.uint64).tolist() == expected[~nan].view(np.uint64).tolist()


def test_safety_bound_broadcasts_its_arguments() -> None:
    bound = safety_bound(np.array([[10.0], [5.0]]), np.array([12.0, 20.0, INF]), 10.0)
    expected = numpy_safety_bound(
        np.array([[10.0], [5.0]]), np.array([12.0, 20.0, INF]), np.array(10.0), IDMParams()
    )
    assert bound.shape == (2, 3) and bound.tolist() == expected.tolist()
    assert safety_bound(10.0, 12.0, 10.0).shape == (1,)


@pytest.mark.parametrize("params", [IDMParams(), IDMParams(2.5, 3.0, 1.5, 1.2, 3.0)])
def test_action_masks_are_the_three_masks_intersected(params: IDMParams) -> None:
    """``action_masks`` (one compiled call) against the three masks computed apart, on random agents."""
    rng = np.random.default_rng(9)
    for trial in range(50):
        n = int(rng.integers(0, 40))
        prev = rng.choice([-4.0, -2.0, -1.9, -0.2, 0.0, 0.1, 1.9, 2.0], n) + rng.choice([0.0, 1e-7], n)
        speed, limit = rng.uniform(0.0, 22.0, n), rng.choice([15.0, 20.0], n)
        gap = np.where(rng.random(n) < 0.3, INF, rng.uniform(0.0, 60.0, n))
        leader, ease_in = rng.uniform(0.0, 22.0, n), rng.random(n) < 0.2
        masks = action_masks(MaskInputs(prev, speed, limit, gap, leader, ease_in), params)
        expected = (
            kinematic_mask(prev)
            & rule_mask(prev, speed, limit)
            & safety_mask(prev, speed, gap, leader, params, ease_in=ease_in)
        )
        assert masks.dtype == np.int8 and masks.shape == (n, N_ACTIONS)
        assert masks.tolist() == expected.astype(np.int8).tolist(), trial
    # Scalars broadcast to every agent, as the separate masks do.
    one = action_masks(MaskInputs(np.array([0.0, 0.2]), 10.0, 20.0, 12.0, 10.0), params)  # type: ignore[arg-type]
    assert (
        one.tolist()
        == (
            kinematic_mask([0.0, 0.2])
            & rule_mask([0.0, 0.2], 10.0, 20.0)
            & safety_mask([0.0, 0.2], 10.0, 12.0, 10.0, params)
        )
        .astype(np.int8)
        .tolist()
    )


def test_hard_brake_is_never_masked() -> None:
    # Emergency: v = 10, stopped leader 10 m ahead: s* = 2 + 10 + 10·10/(2·2) = 37,
    # bound = 2·(1 - (37/10)²) = -25.38 m/s², beyond the comfortable -2: every Δa action (a ∈ [-0.2, 0.2])
    # exceeds it, release is not allowed (no hard brake before): hard brake is the only action left.
    assert masks_for(0.0, 10.0, 20.0, gap=10.0, leader_v=0.0) == [0, 0, 0, 0, 0, 1, 0]
    # Closing in with a comfortable bound (-1.00125 >= -2): no Δa reaches it from a_prev = 0, but the
    # strongest Δa step (-0.2) stays allowed so the agent brakes towards the bound at the jerk limit.
    assert masks_for(0.0, 10.0, 20.0, gap=20.0, leader_v=5.0) == [1, 0, 0, 0, 0, 1, 0]
    # Already at the kinematic edge (a_prev = -2): -2.2 and -2.1 would leave [-2, 2] (the relaxation never
    # overrides the kinematic mask); -2.0, -1.9 and -1.8 all lie under the bound -1.00125.
    assert masks_for(-2.0, 10.0, 20.0, gap=20.0, leader_v=5.0) == [0, 0, 1, 1, 1, 1, 0]
    # Over the limit, touching the leader, at the kinematic edge: still hard brake.
    assert masks_for(2.0, 30.0, 15.0, gap=0.0, leader_v=0.0)[HARD_BRAKE] == 1
    rng = np.random.default_rng(0)
    n = 500
    m = action_masks(
        MaskInputs(
            prev_accel_mps2=rng.choice([-4.0, -2.0, -1.0, 0.0, 1.5, 2.0], n),
            speed_mps=rng.uniform(0, 30, n),
            speed_limit_mps=rng.choice([15.0, 20.0], n),
            gap_m=np.where(rng.random(n) < 0.3, INF, rng.uniform(0, 50, n)),
            leader_speed_mps=rng.uniform(0, 25, n),
        )
    )
    assert (m[:, HARD_BRAKE] == 1).all()


def test_release_only_right_after_hard_brake() -> None:
    k = kinematic_mask([-4.0, -3.9, 0.0, -2.0])
    assert k[:, RELEASE_BRAKE].tolist() == [True, False, False, False]
    # Right after a hard brake (a = -4) every Δa leaves [-2, 2]: hard brake again or release.
    assert masks_for(-4.0, 10.0, 20.0) == [0, 0, 0, 0, 0, 1, 1]


def test_kinematic_range_outside_hard_braking() -> None:
    assert kinematic_mask([1.9])[0, :5].tolist() == [True, True, True, True, False]  # 2.1 > 2
    assert kinematic_mask([2.0])[0, :5].tolist() == [True, True, True, False, False]
    assert kinematic_mask([-1.9])[0, :5].tolist() == [False, True, True, True, True]  # -2.1 < -2
    assert kinematic_mask([-2.0])[0, :5].tolist() == [False, False, True, True, True]
    # Random walks over allowed Δa actions never leave [-2, 2].
    rng = np.random.default_rng(1)
    a = np.zeros(64)
    for _ in range(200):
        allowed = kinematic_mask(a)[:, :5]
        choice = np.array([rng.choice(np.flatnonzero(row)) for row in allowed])
        a = next_acceleration(a, choice)
        assert (a >= -2.0 - 1e-9).all() and (a <= 2.0 + 1e-9).all()


@pytest.mark.sumo
def test_masked_actions_are_never_sampled_or_applied(small_budget) -> None:  # type: ignore[no-untyped-def]
    from idas_sumo.env import MergeParallelEnv
    from idas_sumo.env.engine import EnvConfig
    from idas_sumo.env.scenario import TrafficConfig

    env = MergeParallelEnv(
        seed=3,
        traffic=TrafficConfig(
            n_vehicles=small_budget.n_vehicles, max_vehicles_per_road=small_budget.max_vehicles_per_road
        ),
        config=EnvConfig(max_episode_s=small_budget.max_episode_s),
    )
    rng = np.random.default_rng(3)
    try:
        steps = 0
        for episode in range(2):
            obs, _ = env.reset(seed=episode)
            while env.agents:
                actions = {}
                for a in env.agents:
                    mask = obs[a]["action_mask"]
                    assert mask[HARD_BRAKE] == 1
                    actions[a] = int(rng.choice(np.flatnonzero(mask)))
                prev = {a: env.sim.prev_accel(a) for a in actions}
                obs, _, _, _, infos = env.step(actions)
                outcome = env.last_outcome
                assert outcome is not None
                assert outcome.replaced_actions == {}
                assert not any("replaced_action" in infos[a] for a in actions)
                for a, act in actions.items():  # the acceleration driven is the sampled action's
                    if infos[a]["road"] == GONE:  # collided and removed
                        continue
                    assert infos[a]["accel_mps2"] == pytest.approx(
                        float(next_acceleration([prev[a]], [act])[0])
                    )
                steps += 1
        assert steps > 20

        # A requested masked action is replaced by an allowed one and reported.
        obs, _ = env.reset(seed=0)
        agent = env.agents[0]
        mask = obs[agent]["action_mask"]
        assert mask[RELEASE_BRAKE] == 0  # a_prev = 0: no hard brake before
        actions = {a: HARD_BRAKE for a in env.agents}
        actions[agent] = RELEASE_BRAKE
        _, _, _, _, infos = env.step(actions)
        assert "replaced_action" in infos[agent]
        replaced = infos[agent]["replaced_action"]
        assert mask[replaced] == 1
        assert env.last_outcome is not None and env.last_outcome.replaced_actions == {agent: replaced}
    finally:
        env.close()


def test_ease_in_keeps_the_strongest_step_for_a_far_other_road_front_car() -> None:
    # The emergency above (bound -25.38): with ease_in (the front car is on the other road and the merge
    # point still more than 50 m away) the -0.2 step stays allowed next to the hard brake.
    strict = safety_mask([0.0], [10.0], [10.0], [0.0])[0].tolist()
    eased = safety_mask([0.0], [10.0], [10.0], [0.0], ease_in=np.array([True]))[0].tolist()
    assert strict == [False, False, False, False, False, True, False]
    assert eased == [True, False, False, False, False, True, False]
    # Never below the kinematic floor: from -2 the -0.2 step would give -2.2, so keeping -2 (Δa = 0) is
    # the strongest step left; from -1.9 it is -0.1. Without ease_in both are left with the hard brake.
    at_floor = safety_mask(
        [-2.0, -1.9], [10.0, 10.0], [10.0, 10.0], [0.0, 0.0], ease_in=np.array([True, True])
    )
    assert at_floor.tolist() == [
        [False, False, True, False, False, True, False],
        [False, True, False, False, False, True, False],
    ]
    strict_at_floor = safety_mask([-2.0, -1.9], [10.0, 10.0], [10.0, 10.0], [0.0, 0.0])
    assert strict_at_floor[:, :5].sum() == 0
    # During a hard brake every Δa step lies below -2: ease_in adds none of them.
    assert safety_mask([-4.0], [10.0], [10.0], [0.0], ease_in=np.array([True]))[0, :5].sum() == 0
