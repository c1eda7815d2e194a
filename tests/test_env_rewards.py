"""The paper's four reward parts against hand-worked numbers, and how a step assigns them."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from idas_sumo.config import load_toml
from idas_sumo.env import scoring
from idas_sumo.env.actions import HARD_BRAKE
from idas_sumo.env.config import EnvConfig
from idas_sumo.env.engine import MergeEngine
from idas_sumo.env.rewards import RewardConfig, collide_reward, finish_reward
from idas_sumo.env.scenario import Scenario, VehicleSpec
from idas_sumo.env.scoring import StepContext, impeding_vehicles, register_reward_term
from idas_sumo.env.single import SingleEpisode
from idas_sumo.env.snapshot import MAIN, MERGE, OUT, TrafficSnapshot
from idas_sumo.errors import InputError


@pytest.mark.parametrize(("b_type", "expected"), [(-2.0, 5.0), (0.0, 12.5), (2.0, 20.0)])
def test_finish(b_type: float, expected: float) -> None:
    # (15·b_type + 50)/4: (-30 + 50)/4 = 5, 50/4 = 12.5, (30 + 50)/4 = 20.
    assert float(finish_reward(b_type)) == expected


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
    return [snap.ids[i] for i in impeding_vehicles(snap, np.array(brake_rows, dtype=np.int64))]


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

        monkeypatch.setattr("idas_sumo.env.scoring.FLOW_PENALTY_PER_HARD_BRAKE", -3.0)
        sim.reset(_two_on_main(220.0, gap_m=15.0))
        out = sim.step({"back": HARD_BRAKE, "front": HARD_BRAKE})
        assert out.reward_parts["back"]["flow"] == -6.0
        assert out.hard_brakes_merge_zone == 2
    finally:
        sim.close()


@pytest.mark.sumo
def test_collision_sign_config_is_used(net_path) -> None:  # type: ignore[no-untyped-def]
    # A fast car runs into a stopped one on the main road (prio 1): paper -5·1 - 5 = -10, the other sign
    # -5·(1 - 1) - 5 = -5; both cars came from the main road, so both pay it.
    scenario = Scenario(
        "crash",
        (VehicleSpec("fast", "main", 100.0, 20.0), VehicleSpec("stopped", "main", 112.0, 0.0)),
        main_prio=1,
        merge_prio=0,
    )
    for sign, expected in (("paper", -10.0), ("lower_priority_pays", -5.0)):
        reward = RewardConfig(collision_sign=sign)  # type: ignore[arg-type]
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


@pytest.mark.sumo
def test_a_finish_pays_the_drivers_type_once(net_path) -> None:  # type: ignore[no-untyped-def]
    """A car of b_type 2 that crosses the finish line (50 m past the merge point) gets (15·2 + 50)/4 = 20 in
    its finish part and its reward, once; the steps before pay nothing."""
    scenario = Scenario("finish", (VehicleSpec("car", "main", 240.0, 20.0, b_type=2.0),))
    sim = SingleEpisode(net_path, config=EnvConfig(max_episode_s=20.0))
    try:
        sim.reset(scenario)
        finish_parts = []
        while sim.active_agents:
            out = sim.step({"car": 2})
            finish_parts.append(out.reward_parts["car"]["finish"])
        assert out.end_reason == {"car": "finished"}
        assert finish_parts[-1] == 20.0 and out.rewards == {"car": 20.0} and out.joint_reward == 20.0
        assert set(finish_parts[:-1]) == {0.0}
    finally:
        sim.close()


@pytest.mark.sumo
def test_a_term_registered_from_outside_is_scored_in_its_own_column(
    net_path, monkeypatch: pytest.MonkeyPatch
) -> None:  # type: ignore[no-untyped-def]
    """The registry is the extension point: a term registered by name and named in ``extra_terms`` is called
    with the step's context; its part lands in its own column of ``reward_parts``, an individual one in the
    agent's reward, a shared one once per copy in the joint reward. The paper's parts are as without it."""
    monkeypatch.setattr(scoring, "_TERMS", dict(scoring._TERMS))
    seen: list[StepContext] = []

    def brake_tax(ctx: StepContext) -> np.ndarray:
        seen.append(ctx)
        return -0.5 * np.isin(ctx.egos, ctx.brakes)  # -0.5 for each agent that braked hard

    register_reward_term("brake_tax", brake_tax)
    register_reward_term("per_copy", lambda ctx: np.full(ctx.copies, -0.25), shared=True)
    with pytest.raises(ValueError, match="registered already"):
        register_reward_term("brake_tax", brake_tax)
    config = EnvConfig(max_episode_s=10.0, reward=RewardConfig(extra_terms=("brake_tax", "per_copy")))
    sim = SingleEpisode(net_path, config=config)
    try:
        sim.reset(_two_on_main(150.0))
        out = sim.step({"back": HARD_BRAKE, "front": 2})
        assert len(seen) == 1 and seen[0].brakes.tolist() == [seen[0].egos[0]]
        assert out.reward_parts["back"] == {
            "finish": 0.0,
            "collide": 0.0,
            "impede": 0.0,
            "flow": 0.0,
            "brake_tax": -0.5,
            "per_copy": -0.25,
        }
        assert out.reward_parts["front"]["impede"] == -5.0 and out.reward_parts["front"]["brake_tax"] == 0.0
        assert out.rewards == {"back": -0.5, "front": -5.0}
        assert out.joint_reward == -5.5 - 0.25
    finally:
        sim.close()


def test_an_unregistered_term_is_refused_before_any_simulation(net_path) -> None:  # type: ignore[no-untyped-def]
    config = EnvConfig(reward=RewardConfig(extra_terms=("no_such_term",)))
    with pytest.raises(InputError, match="unknown reward term 'no_such_term'; registered: finish, collide"):
        MergeEngine(net_path, config=config)


@pytest.mark.parametrize(
    ("table", "key", "former"),
    [
        ("reward", "impede_blame", "car_ahead"),
        ("reward", "brake_count", "step"),
        ("reward", "collide_scale", 1.0),
        ("reward", "timeout", "free"),
        ("reward", "finish_slope", "paper"),
        (None, "standstill", "keeps_command"),
    ],
)
def test_retired_switches_load_at_their_former_default_and_refuse_a_variant(
    tmp_path, table: str | None, key: str, former: object
) -> None:  # type: ignore[no-untyped-def]
    """A TOML (or a checkpoint's stored config) holding a retired switch at its former default loads as if
    it were not there; any other value is refused with one line that names the key."""
    from idas_sumo.training.config import load_train_config

    def write(name: str, value: object | None) -> Path:
        line = "" if value is None else f"{key} = {value!r}".replace("'", '"') + "\n"
        path = tmp_path / f"{name}.toml"
        path.write_text(f"[{table}]\n{line}" if table else line)
        return path

    assert load_train_config(write("former", former)) == load_train_config(write("without", None))
    variant = {"impede_blame": "braker_if_unforced", "brake_count": "manoeuvre", "collide_scale": 20.0}
    with pytest.raises(InputError) as err:
        load_train_config(write("variant", variant.get(key, "other")))
    assert "\n" not in str(err.value) and key in str(err.value) and "retired" in str(err.value)


def test_a_brake_count_manoeuvre_toml_is_refused_with_one_line(tmp_path: Path) -> None:
    from idas_sumo.training.config import load_train_config

    path = tmp_path / "manoeuvre.toml"
    path.write_text('[reward]\nbrake_count = "manoeuvre"\n')
    assert load_toml(path) == {"reward": {"brake_count": "manoeuvre"}}
    with pytest.raises(InputError) as err:
        load_train_config(path)
    assert str(err.value) == (
        f"{path}.reward.brake_count: 'manoeuvre' is a retired experiment variant (experiments/README.md); "
        "this build runs only 'step'"
    )


def test_the_shipped_idas_checkpoint_still_loads_its_training_config() -> None:
    """idas.pt stores the config it was trained with, retired switches at their defaults included."""
    from idas_sumo.resources import POLICY_DIR
    from idas_sumo.training.checkpoint import load_checkpoint

    checkpoint = load_checkpoint(POLICY_DIR / "idas.pt")
    assert checkpoint.config.env.reward == RewardConfig()
    assert checkpoint.config.env.reward.part_names == ("finish", "collide", "impede", "flow")
