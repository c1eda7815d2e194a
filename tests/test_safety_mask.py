"""The safety-mask choice (own_lane, the paper's, default; merge_aware, a shield) and collisions as real
outcomes: SUMO's reports and the engine's geometric cross-check end the colliding agents' episodes."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from idas_sumo.env.actions import HARD_BRAKE, N_ACTIONS, candidate_accelerations
from idas_sumo.env.collisions import any_overlap
from idas_sumo.env.engine import AgentBatch, EnvConfig, MergeEngine, geometric_collisions
from idas_sumo.env.episodes import run_episodes
from idas_sumo.env.rewards import collide_reward
from idas_sumo.env.scenario import Scenario, VehicleSpec
from idas_sumo.env.snapshot import MAIN, MERGE, OUT, TrafficSnapshot
from idas_sumo.evaluation.protocol import EvalCase, eval_jobs, run_jobs

IntArray = np.ndarray

# Two cars that reach the merge point together: 100 m to go at 15 m/s on both roads (6.7 s).
LEVEL = Scenario(
    "level",
    (
        VehicleSpec("m", "main", 150.0, 15.0, b_type=0.0),
        VehicleSpec("g", "merge", 150.0, 15.0, b_type=0.0),
    ),
    main_prio=1,
    merge_prio=0,
)


class NeverBrakes:
    """Keeps its acceleration (Δa = 0) whenever the mask allows it, else the strongest allowed action:
    a policy that never brakes on its own within the mask."""

    def act(self, batch: AgentBatch, rows: IntArray) -> IntArray:
        masks = batch.masks[rows].astype(bool)
        out = np.full(len(rows), 2, dtype=np.int64)
        accel = candidate_accelerations(batch.prev_accel[rows])
        for i in range(len(rows)):
            if not masks[i, 2]:
                allowed = np.flatnonzero(masks[i, :HARD_BRAKE])
                out[i] = int(allowed[np.argmax(accel[i, allowed])]) if len(allowed) else HARD_BRAKE
        return out


def test_default_is_own_lane_and_a_wrong_value_is_refused() -> None:
    assert EnvConfig().safety_mask == "own_lane"
    with pytest.raises(ValueError, match="safety_mask"):
        EnvConfig(safety_mask="both")  # type: ignore[arg-type]


def _snapshot(road: list[int], dist: list[float], copy: list[int] | None = None) -> TrafficSnapshot:
    n = len(road)
    z = np.zeros(n)
    return TrafficSnapshot(
        ids=tuple(f"v{i}" for i in range(n)),
        road=np.array(road, dtype=np.int64),
        dist_to_merge_m=np.array(dist, dtype=np.float64),
        speed_mps=z,
        accel_mps2=z,
        length_m=np.full(n, 5.0),
        speed_limit_mps=np.full(n, 20.0),
        copy=None if copy is None else np.array(copy, dtype=np.int64),
    )


def _hits(
    road: list[int],
    dist: list[float],
    origin: list[int],
    copy: list[int] | None = None,
    joined_m: float = 0.0,
) -> list:
    return geometric_collisions(_snapshot(road, dist, copy), np.array(origin, dtype=np.int64), joined_m)


def test_geometric_collisions_hand_worked() -> None:
    # Same road, fronts 4.9 m apart (bodies of 5 m overlap by 0.1 m); 5.0 m apart only touch.
    assert _hits([MAIN, MAIN], [50.0, 54.9], [MAIN, MAIN]) == [(0, 1)]
    assert _hits([MAIN, MAIN], [50.0, 55.0], [MAIN, MAIN]) == []
    # Level on the two incoming roads: side by side, not overlapping (the conflict is at the merge point).
    assert _hits([MAIN, MERGE], [3.0, 3.0], [MAIN, MERGE]) == []
    # Both fronts past the merge point, whichever road they came from: one road, overlap.
    assert _hits([OUT, OUT], [-2.0, -1.0], [MAIN, MERGE]) == [(0, 1)]
    # With a 9.4 m junction the two roads' lanes join only 9.4 m past the merge point: before, side by side
    # (SUMO's junction check is the one that sees shapes touch there); after, one lane.
    assert _hits([OUT, OUT], [-2.0, -1.0], [MAIN, MERGE], joined_m=9.4) == []
    assert _hits([OUT, OUT], [-12.0, -10.0], [MAIN, MERGE], joined_m=9.4) == [(0, 1)]
    assert _hits([OUT, OUT], [-12.0, -9.0], [MAIN, MERGE], joined_m=9.4) == []
    assert _hits([OUT, OUT], [-2.0, -1.0], [MAIN, MAIN], joined_m=9.4) == [(0, 1)]
    # A car past the merge point and one behind it on the road it came from: the tail is on that road.
    assert _hits([OUT, MERGE], [-2.0, 1.0], [MERGE, MERGE]) == [(0, 1)]
    # ... but a car of the other road behind its tail is beside it, not in it.
    assert _hits([OUT, MAIN], [-2.0, 1.0], [MERGE, MAIN]) == []
    # Different copies never collide; three cars: every overlapping pair once.
    assert _hits([MAIN, MAIN], [50.0, 52.0], [MAIN, MAIN], copy=[0, 1]) == []
    assert _hits([MAIN, MAIN, MAIN], [50.0, 52.0, 54.0], [MAIN] * 3) == [(0, 1), (0, 2), (1, 2)]


def test_geometric_collisions_agree_with_the_pairwise_definition() -> None:
    """The sorted sweep finds exactly the pairs of the n x n definition (same incoming road of origin, or
    both past the point where the lanes joined; bodies overlapping; one copy), whatever the row order."""
    for trial in range(300):
        rng = np.random.default_rng(trial)
        n = int(rng.integers(0, 40))
        copies = int(rng.integers(1, 4))
        origin = rng.integers(0, 2, n)
        dist = np.round(rng.uniform(-30.0, 60.0, n), 1)
        road = np.where(dist < 0.0, OUT, origin)
        joined_m = rng.choice([0.0, 9.4], n)
        length = rng.choice([4.0, 5.0, 7.5], n)
        copy = rng.integers(0, copies, n)
        snap = TrafficSnapshot(
            tuple(f"v{i}" for i in range(n)),
            road,
            dist,
            np.zeros(n),
            np.zeros(n),
            length,
            np.full(n, 20.0),
            copy if copies > 1 else None,
        )
        expected = [
            (i, j)
            for i in range(n)
            for j in range(i + 1, n)
            if (origin[i] == origin[j] or (dist[i] < -joined_m[i] and dist[j] < -joined_m[j]))
            and (copies == 1 or copy[i] == copy[j])
            and dist[i] < dist[j] + length[j]
            and dist[j] < dist[i] + length[i]
        ]
        assert geometric_collisions(snap, origin, joined_m) == expected, trial
        # The engine's check of every step: any pair at all, with one joining point per origin.
        via = rng.choice([0.0, 9.4], 2)
        row_copy = copy if copies > 1 else np.zeros(n, dtype=np.int64)
        found = any_overlap(snap.by_distance.order, dist, row_copy, length, origin, via, snap.longest_m)
        assert found == bool(geometric_collisions(snap, origin, via[origin])), trial


@pytest.mark.sumo
def test_own_lane_mask_ignores_the_other_road_merge_aware_does_not(net_path: Path) -> None:
    masks = {}
    for mode in ("own_lane", "merge_aware"):
        engine = MergeEngine(net_path, config=EnvConfig(safety_mask=mode))  # type: ignore[arg-type]
        try:
            close = Scenario(
                "close",
                (VehicleSpec("m", "main", 240.0, 10.0), VehicleSpec("g", "merge", 236.0, 15.0)),
            )
            engine.reset([close])
            batch = engine.observe()
            masks[mode] = dict(zip(batch.ids, batch.masks.tolist(), strict=True))
            gap, _, ease_in = engine.front_cars(batch.egos)
            if mode == "own_lane":
                assert np.isinf(gap).all() and not ease_in.any()  # no car ahead in either lane
        finally:
            engine.close()
    # The merge car, 4 m behind the main car in projection and faster: the shield only leaves it braking.
    assert sum(masks["own_lane"]["g"][:HARD_BRAKE]) > 0
    assert masks["merge_aware"]["g"][:HARD_BRAKE] == [0] * HARD_BRAKE
    assert len(masks["own_lane"]["g"]) == N_ACTIONS


def _collide_run(net_path: Path, mode: str, copies: int = 1) -> list:
    engine = MergeEngine(net_path, copies=copies, config=EnvConfig(max_episode_s=20.0, safety_mask=mode))  # type: ignore[arg-type]
    try:
        return run_episodes(engine, [LEVEL] * copies, lambda j, a: 0, [NeverBrakes()])
    finally:
        engine.close()


@pytest.mark.sumo
@pytest.mark.parametrize("copies", [1, 2])
def test_cars_meeting_at_the_merge_point_collide_under_the_own_lane_mask(net_path: Path, copies: int) -> None:
    for outcome in _collide_run(net_path, "own_lane", copies):
        assert outcome.end_reasons == {"m": "collided", "g": "collided"}
        assert outcome.collisions >= 1
        assert not outcome.success
        assert outcome.returns["m"] == pytest.approx(float(collide_reward(1.0, "paper")))
        assert outcome.returns["g"] == pytest.approx(float(collide_reward(0.0, "paper")))
    # The shield makes the merge car fall in behind: no collision (this policy never speeds up again,
    # so the merge car does not finish in time; the point is the collision).
    (shielded,) = _collide_run(net_path, "merge_aware")
    assert shielded.collisions == 0 and "collided" not in shielded.end_reasons.values()
    assert shielded.end_reasons["m"] == "finished"


@pytest.mark.sumo
def test_the_evaluation_row_says_collided(net_path: Path) -> None:
    engine = MergeEngine(net_path, config=EnvConfig(max_episode_s=20.0))
    try:
        jobs = eval_jobs([EvalCase(LEVEL, "g", 0, ("g",))], ["never_brakes"])
        ((_, result),) = list(run_jobs(engine, jobs, {"never_brakes": NeverBrakes()}, NeverBrakes()))
    finally:
        engine.close()
    assert result.episode["success"] == 0 and result.episode["perfect"] == 0
    assert int(result.episode["collisions"]) >= 1  # type: ignore[call-overload]


@pytest.mark.sumo
def test_an_overlap_sumo_did_not_report_is_a_collision(
    net_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """SUMO neither removes colliding cars (collision action 'warn') nor reports them (silenced): the
    geometric cross-check alone ends both episodes, once the cars share the outgoing lane."""
    import libsumo

    from idas_sumo.sim.backend import SumoBackend

    sumo_args = SumoBackend._args

    def warn_only(self: SumoBackend, route_file: Path) -> list[str]:
        args = sumo_args(self, route_file)
        args[args.index("--collision.action") + 1] = "warn"
        return args

    monkeypatch.setattr(SumoBackend, "_args", warn_only)
    monkeypatch.setattr(libsumo.simulation, "getCollisions", lambda: [])
    (outcome,) = _collide_run(net_path, "own_lane")
    assert outcome.geometric_collisions >= 1
    assert outcome.collisions == outcome.geometric_collisions
    assert outcome.end_reasons == {"m": "collided", "g": "collided"}
    assert not outcome.success


@pytest.mark.sumo
def test_each_collision_counts_once(net_path: Path) -> None:
    """SUMO's report and the cross-check never count one pair twice: whichever sees the overlap first
    takes both cars off the road. Here SUMO is first: the level cars' shapes touch in the junction,
    before their lanes join (where the cross-check would count them)."""
    (outcome,) = _collide_run(net_path, "own_lane")
    assert outcome.collisions == 1
    assert outcome.geometric_collisions == 0


def test_cli_refuses_a_wrong_safety_mask(capsys: pytest.CaptureFixture[str]) -> None:
    from idas_sumo.cli import main

    for command in (["evaluate", "--baseline", "idm"], ["train"]):
        with pytest.raises(SystemExit) as err:
            main([*command, "--safety-mask", "shield"])
        assert err.value.code == 2
        lines = capsys.readouterr().err.strip().splitlines()
        assert len(lines) == 1 and "--safety-mask" in lines[0] and "own_lane" in lines[0]


def test_help_shows_the_default(capsys: pytest.CaptureFixture[str]) -> None:
    from idas_sumo.cli import main

    with pytest.raises(SystemExit):
        main(["evaluate", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "--safety-mask {own_lane,merge_aware}" in text
    assert "else own_lane)" in text


@pytest.mark.sumo
def test_evaluate_records_the_safety_mask(tmp_path: Path, net_path: Path) -> None:
    from idas_sumo.cli import main

    base = ["evaluate", "--net", str(net_path), "--baseline", "idm", "--others", "idm", "--scenarios", "2"]
    for mode in ("own_lane", "merge_aware"):
        out = tmp_path / mode
        assert main([*base, "--safety-mask", mode, "--no-progress", "--out", str(out)]) == 0
        settings = json.loads((out / "settings.json").read_text())
        assert settings["safety_mask"] == mode
        assert settings["traffic"]["n_vehicles"] == 8
    # Without the flag: the --config file's value.
    config = tmp_path / "c.toml"
    config.write_text('safety_mask = "merge_aware"\n')
    out = tmp_path / "from-config"
    assert main([*base, "--config", str(config), "--no-progress", "--out", str(out)]) == 0
    assert json.loads((out / "settings.json").read_text())["safety_mask"] == "merge_aware"


def test_train_config_carries_the_safety_mask(tmp_path: Path) -> None:
    from idas_sumo.training.config import TrainConfig, load_train_config

    assert TrainConfig().env.safety_mask == "own_lane"
    assert TrainConfig().with_overrides(safety_mask="merge_aware").as_dict()["safety_mask"] == "merge_aware"
    path = tmp_path / "t.toml"
    path.write_text('safety_mask = "merge_aware"\n')
    assert load_train_config(path).env.safety_mask == "merge_aware"
    from idas_sumo.resources import SCENARIO_DIR

    assert load_train_config(SCENARIO_DIR / "train_default.toml").env.safety_mask == "own_lane"


def test_train_flag_overrides_the_config(tmp_path: Path) -> None:
    import argparse

    from idas_sumo.training.cli import config_from_args

    path = tmp_path / "t.toml"
    path.write_text('safety_mask = "own_lane"\n')
    args = argparse.Namespace(config=path, safety_mask="merge_aware")
    assert config_from_args(args).env.safety_mask == "merge_aware"
    assert config_from_args(argparse.Namespace(config=path, safety_mask=None)).env.safety_mask == "own_lane"
