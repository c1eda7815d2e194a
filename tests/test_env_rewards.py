"""The paper's four reward parts against hand-worked numbers, and how a step assigns them."""

from __future__ import annotations

import numpy as np
import pytest

from idas_sumo.env.actions import HARD_BRAKE, N_DELTA_ACTIONS
from idas_sumo.env.engine import EnvConfig, _impeding_vehicles
from idas_sumo.env.rewards import (
    FLOW_PENALTY_PER_HARD_BRAKE,
    RewardConfig,
    collide_reward,
    finish_reward,
    flow_penalty,
    hard_brakes_in_merge_zone,
)
from idas_sumo.env.scenario import Scenario, VehicleSpec
from idas_sumo.env.single import SingleEpisode
from idas_sumo.env.snapshot import MAIN, MERGE, OUT, TrafficSnapshot
from idas_sumo.errors import InputError


@pytest.mark.parametrize(("b_type", "expected"), [(-2.0, 5.0), (0.0, 12.5), (2.0, 20.0)])
def test_finish(b_type: float, expected: float) -> None:
    # (15·b_type + 50)/4: (-30 + 50)/4 = 5, 50/4 = 12.5, (30 + 50)/4 = 20.
    assert float(finish_reward(b_type)) == expected


@pytest.mark.parametrize(("b_type", "expected"), [(-2.0, 20.0), (0.0, 12.5), (2.0, 5.0)])
def test_finish_slope_cooperative_waits(b_type: float, expected: float) -> None:
    # (-15·b_type + 50)/4: (30 + 50)/4 = 20, 12.5, (-30 + 50)/4 = 5; the config's method gives the same.
    assert float(finish_reward(b_type, "cooperative_waits")) == expected
    assert float(RewardConfig(finish_slope="cooperative_waits").finish(b_type)) == expected
    assert float(RewardConfig().finish(b_type)) == float(finish_reward(b_type))


@pytest.mark.parametrize(
    ("prio", "sign", "expected"),
    [
        (0, "paper", -5.0),
        (1, "paper", -10.0),
        (0, "lower_priority_pays", -10.0),
        (1, "lower_priority_pays", -5.0),
    ],
)
def test_collide(prio: int, sign: str, expected: float) -> None:
    # paper: -5·b_prio - 5; lower_priority_pays: -5·(1 - b_prio) - 5.
    assert float(collide_reward(prio, sign)) == expected  # type: ignore[arg-type]


def test_flow_counts_hard_brakes_within_50_m() -> None:
    # Hard brakes at these distances to the merge point; |d| <= 50 counts: 10, -30, 50, -50 -> -4.
    assert flow_penalty([10.0, -30.0, 50.0, -50.0, 50.1, -60.0, 200.0]) == -4.0
    assert flow_penalty([]) == 0.0


def test_flow_penalty_is_minus_one_per_merge_zone_hard_brake() -> None:
    # StepOutcome.hard_brakes_merge_zone counts these brakes; the paper's flow penalty is -1 for each.
    distances = [10.0, -30.0, 50.0, -50.0, 50.1, -60.0, 200.0]
    assert hard_brakes_in_merge_zone(distances) == 4
    assert FLOW_PENALTY_PER_HARD_BRAKE == -1.0
    assert flow_penalty(distances) == -hard_brakes_in_merge_zone(distances)


def _snapshot(rows: list[tuple[str, int, float]]) -> TrafficSnapshot:
    n = len(rows)
    return TrafficSnapshot(
        ids=tuple(r[0] for r in rows),
        road=np.array([r[1] for r in rows], dtype=np.int64),
        dist_to_merge_m=np.array([r[2] for r in rows]),
        speed_mps=np.full(n, 10.0),
        accel_mps2=np.zeros(n),
        length_m=np.full(n, 5.0),
        speed_limit_mps=np.full(n, 20.0),
    )


def _blamed(snap: TrafficSnapshot, brake_rows: list[int]) -> list[str]:
    return [snap.ids[i] for i in _impeding_vehicles(snap, np.array(brake_rows, dtype=np.int64))]


def test_impede_goes_to_the_vehicle_directly_ahead() -> None:
    snap = _snapshot(
        [
            ("braker", MAIN, 60.0),
            ("ahead_far", MAIN, 20.0),
            ("ahead_near", MAIN, 48.0),
            ("behind", MAIN, 80.0),
            ("out_ahead", OUT, -10.0),
            ("merge_far", MERGE, 40.0),
        ]
    )
    assert _blamed(snap, [0]) == ["ahead_near"]
    # A car on the other road that is projected closer ahead (the merging car cutting in) is blamed.
    snap2 = _snapshot([("braker", MAIN, 60.0), ("ahead", MAIN, 40.0), ("cutter", MERGE, 55.0)])
    assert _blamed(snap2, [0]) == ["cutter"]
    # Nobody ahead within sight (100 m): nobody is blamed; no brakes, no culprits.
    snap3 = _snapshot([("braker", MAIN, 200.0), ("far", MAIN, 99.0), ("behind", MAIN, 230.0)])
    assert _blamed(snap3, [0]) == []
    assert _blamed(snap, []) == []
    # Two brakers, each blames its nearest car ahead on either road: "behind" (80 m) blames "braker";
    # "ahead_near" (48 m) blames "merge_far" (other road, 8 m ahead), not "out_ahead" (58 m ahead).
    assert _blamed(snap, [3, 2]) == ["braker", "merge_far"]


def _two_on_main(back_pos: float, gap_m: float = 20.0) -> Scenario:
    return Scenario(
        "impede",
        (
            VehicleSpec("back", "main", back_pos, 10.0, b_type=0.0),
            VehicleSpec("front", "main", back_pos + gap_m, 10.0, b_type=0.0),
        ),
    )


@pytest.mark.sumo
def test_step_assigns_impede_and_flow(net_path) -> None:  # type: ignore[no-untyped-def]
    sim = SingleEpisode(net_path, config=EnvConfig(max_episode_s=10.0))
    try:
        # Far from the merge point (back at 150 m from the start -> 100 m before the merge): impede, no flow.
        sim.reset(_two_on_main(150.0))
        out = sim.step({"back": HARD_BRAKE, "front": 2})
        assert out.hard_brakes == 1  # back's: front is the one impeding it
        assert out.reward_parts["front"]["impede"] == -5.0
        assert out.reward_parts["back"]["impede"] == 0.0
        assert out.reward_parts["back"]["flow"] == out.reward_parts["front"]["flow"] == 0.0
        assert out.rewards == {"back": 0.0, "front": -5.0}
        assert out.hard_brakes_merge_zone == 0
        assert out.joint_reward == -5.0

        # Inside the merging zone (back 30 m before the merge point): the shared flow penalty too.
        sim.reset(_two_on_main(220.0, gap_m=15.0))
        out = sim.step({"back": HARD_BRAKE, "front": 2})
        assert out.reward_parts["front"]["impede"] == -5.0
        assert out.reward_parts["back"]["flow"] == out.reward_parts["front"]["flow"] == -1.0
        assert out.hard_brakes_merge_zone == 1
        # flow is shared: it is not in an agent's own reward, once in the joint reward.
        assert out.rewards == {"back": 0.0, "front": -5.0}
        assert out.joint_reward == -6.0

        # No hard brake: no impede, no flow.
        sim.reset(_two_on_main(150.0))
        out = sim.step({"back": 2, "front": 2})
        assert out.hard_brakes == 0
        assert all(p["impede"] == 0.0 and p["flow"] == 0.0 for p in out.reward_parts.values())
    finally:
        sim.close()


@pytest.mark.sumo
def test_merge_zone_hard_brakes_are_counted_not_read_off_the_flow_penalty(
    net_path, monkeypatch: pytest.MonkeyPatch
) -> None:  # type: ignore[no-untyped-def]
    """Both cars brake hard within 50 m of the merge point: two merge-zone hard brakes, flow -2. The count
    is the count: a flow penalty of another size changes flow, not the number of brakes."""
    sim = SingleEpisode(net_path, config=EnvConfig(max_episode_s=10.0))
    try:
        sim.reset(_two_on_main(220.0, gap_m=15.0))
        out = sim.step({"back": HARD_BRAKE, "front": HARD_BRAKE})
        assert out.hard_brakes == 2
        assert out.hard_brakes_merge_zone == 2
        assert out.reward_parts["back"]["flow"] == -out.hard_brakes_merge_zone

        monkeypatch.setattr("idas_sumo.env.engine.FLOW_PENALTY_PER_HARD_BRAKE", -3.0)
        sim.reset(_two_on_main(220.0, gap_m=15.0))
        out = sim.step({"back": HARD_BRAKE, "front": HARD_BRAKE})
        assert out.reward_parts["back"]["flow"] == -6.0
        assert out.hard_brakes_merge_zone == 2
    finally:
        sim.close()


@pytest.mark.sumo
def test_collision_sign_config_is_used(net_path) -> None:  # type: ignore[no-untyped-def]
    # A fast car runs into a stopped one on the main road (prio 1): paper -10, other sign -5; the labelled
    # price variant (collide_scale) multiplies either.
    scenario = Scenario(
        "crash",
        (VehicleSpec("fast", "main", 100.0, 20.0), VehicleSpec("stopped", "main", 112.0, 0.0)),
        main_prio=1,
        merge_prio=0,
    )
    for sign, scale, expected in (
        ("paper", 1.0, -10.0),
        ("lower_priority_pays", 1.0, -5.0),
        ("paper", 4.0, -40.0),
    ):
        reward = RewardConfig(collision_sign=sign, collide_scale=scale)  # type: ignore[arg-type]
        sim = SingleEpisode(net_path, config=EnvConfig(reward=reward))
        try:
            sim.reset(scenario)
            collided = {}
            for _ in range(10):
                if not sim.active_agents:
                    break
                # Keep 'stopped' braking; drive 'fast' straight on (actions replaced by the safety mask
                # cannot stop a 20 m/s car in 7 m anyway).
                out = sim.step({a: HARD_BRAKE if a == "stopped" else 2 for a in sim.active_agents})
                collided.update({a: p["collide"] for a, p in out.reward_parts.items() if p["collide"]})
            assert collided == {"fast": expected, "stopped": expected}
        finally:
            sim.close()


@pytest.mark.parametrize("scale", [0.0, -1.0, float("nan"), float("inf")])
def test_collide_scale_must_be_a_positive_number(scale: float) -> None:
    with pytest.raises(InputError, match="collide_scale"):
        RewardConfig(collide_scale=scale)


@pytest.mark.sumo
def test_impede_blame_braker_if_unforced_charges_a_chosen_brake_to_the_braker(net_path) -> None:  # type: ignore[no-untyped-def]
    """The labelled variant (RewardConfig.impede_blame): a brake chosen while a Δa action was allowed is
    paid by the braker (-5), with or without a car ahead; a brake the mask forced still goes to the car
    ahead, as under the default."""
    variant = EnvConfig(max_episode_s=10.0, reward=RewardConfig(impede_blame="braker_if_unforced"))
    sim = SingleEpisode(net_path, config=variant)
    try:
        # Chosen: 20 m apart at the same speed, every Δa is allowed, and back brakes anyway.
        sim.reset(_two_on_main(150.0))
        _, masks = sim.observe(["back"])
        assert masks[0, :N_DELTA_ACTIONS].any()
        out = sim.step({"back": HARD_BRAKE, "front": 2})
        assert out.rewards == {"back": -5.0, "front": 0.0}
        assert out.hard_brakes == 1 and out.joint_reward == -5.0
        # Alone on the road: under the default nobody pays, under the variant the braker does.
        alone = Scenario("alone", (VehicleSpec("solo", "main", 100.0, 10.0, b_type=0.0),))
        sim.reset(alone)
        assert sim.step({"solo": HARD_BRAKE}).rewards == {"solo": -5.0}
        # Forced: 6 m behind a car 8 m/s slower, only the hard brake is allowed; the car ahead pays.
        forced = Scenario(
            "forced",
            (
                VehicleSpec("back", "main", 150.0, 16.0, b_type=0.0),
                VehicleSpec("front", "main", 161.0, 8.0, b_type=0.0),
            ),
        )
        sim.reset(forced)
        _, masks = sim.observe(["back"])
        assert not masks[0, :N_DELTA_ACTIONS].any()
        out = sim.step({"back": HARD_BRAKE, "front": 2})
        assert out.rewards == {"back": 0.0, "front": -5.0}
    finally:
        sim.close()
    default = SingleEpisode(net_path, config=EnvConfig(max_episode_s=10.0))
    try:
        default.reset(Scenario("alone", (VehicleSpec("solo", "main", 100.0, 10.0, b_type=0.0),)))
        assert default.step({"solo": HARD_BRAKE}).rewards == {"solo": 0.0}
    finally:
        default.close()


@pytest.mark.sumo
def test_brake_count_manoeuvre_prices_a_brake_once_while_the_statistics_count_every_step(net_path) -> None:  # type: ignore[no-untyped-def]
    """The labelled variant (RewardConfig.brake_count = 'manoeuvre'): a car that brakes hard two steps in a
    row costs the car ahead -5 and the merging zone -1 once, at the first step; the default prices both
    steps. The hard-brake counts (the evaluation's) stay per step under both."""
    for count, impede, flow in (
        ("step", [-5.0, -5.0], [-2.0, -2.0]),
        ("manoeuvre", [-5.0, 0.0], [-2.0, 0.0]),
    ):
        config = EnvConfig(max_episode_s=10.0, reward=RewardConfig(brake_count=count))  # type: ignore[arg-type]
        sim = SingleEpisode(net_path, config=config)
        try:
            sim.reset(_two_on_main(220.0, gap_m=15.0))  # both in the merging zone, back 15 m behind front
            seen_impede, seen_flow = [], []
            for _ in range(2):
                out = sim.step({"back": HARD_BRAKE, "front": HARD_BRAKE})
                assert out.hard_brakes == 2 and out.hard_brakes_merge_zone == 2
                seen_impede.append(out.reward_parts["front"]["impede"])
                seen_flow.append(out.reward_parts["back"]["flow"])
            assert seen_impede == impede, count
            assert seen_flow == flow, count
        finally:
            sim.close()
