"""The engine on any detected merge (a ``MergeSite``): the on-ramp net's acceleration lane, distances
along each car's route, lane keeping, K copies, and train/evaluate on user nets from the command line."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from conftest import run_cli

from idas_sumo.baselines.policies import RuleBasedPolicy
from idas_sumo.env.engine import AgentBatch, EnvConfig, EpisodeOutcome, MergeEngine, StepResult
from idas_sumo.env.episodes import run_episodes
from idas_sumo.env.scenario import Scenario, VehicleSpec
from idas_sumo.env.snapshot import MAIN, MERGE, OUT
from idas_sumo.sim.backend import STEP_LENGTH_S
from idas_sumo.sim.merge_detect import choose_merge
from idas_sumo.sim.sample_nets import build_sample_net

PACKAGE = Path(__file__).resolve().parents[1] / "idas_sumo"


@pytest.fixture(scope="module")
def nets(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    folder = tmp_path_factory.mktemp("site_nets")
    return {
        name: build_sample_net(name, folder / f"{name}.net.xml")
        for name in ("onramp", "two_merges", "crossing")
    }


class _Trace:
    """Every car's SUMO lane and the engine's view of it at each step (an ``EpisodeObserver``)."""

    def __init__(self) -> None:
        self.rows: list[tuple[float, str, str, float, int, float, float]] = []
        """(time, id, SUMO lane id, lane position, engine road, dist to merge, speed)."""
        self.teleports: list[str] = []

    def decided(self, engine: MergeEngine, jobs: object, batch: AgentBatch, actions: object) -> None:
        pass

    def stepped(
        self, engine: MergeEngine, jobs: object, batch: AgentBatch, actions: object, result: StepResult
    ) -> None:
        backend = engine.single_backend
        snap = engine.snapshot
        for i, vid in enumerate(snap.ids):
            self.rows.append(
                (
                    engine.time_s,
                    vid,
                    backend.raw_call("vehicle", "getLaneID", vid),
                    float(backend.raw_call("vehicle", "getLanePosition", vid)),
                    int(snap.road[i]),
                    float(snap.dist_to_merge_m[i]),
                    float(snap.speed_mps[i]),
                )
            )
        self.teleports += list(backend.raw_call("simulation", "getStartingTeleportIDList"))

    def ended(self, engine: MergeEngine, slot: int, job: int, outcome: EpisodeOutcome) -> None:
        pass


def _ramp_and_highway() -> Scenario:
    """A ramp car and a highway car that reach the acceleration lane side by side (the ramp car must
    find its gap), and a SUMO-driven highway car behind them."""
    return Scenario(
        "onramp",
        (
            VehicleSpec("h", "main", 420.0, 22.0),
            VehicleSpec("r", "merge", 230.0, 18.0),
            VehicleSpec("h2", "main", 300.0, 22.0, controlled=False),
        ),
    )


def _run(net: Path, scenario: Scenario) -> tuple[EpisodeOutcome, _Trace]:
    engine = MergeEngine(net, config=EnvConfig(max_episode_s=60.0))
    trace = _Trace()
    try:
        (outcome,) = run_episodes(engine, [scenario], lambda job, agent: 0, [RuleBasedPolicy("idm")], trace)
    finally:
        engine.close()
    return outcome, trace


@pytest.mark.sumo
def test_the_ramp_car_changes_onto_the_highway_lane_before_its_lane_ends(nets: dict[str, Path]) -> None:
    site = choose_merge(nets["onramp"])
    assert site.kind == "lane_drop"
    outcome, trace = _run(nets["onramp"], _ramp_and_highway())
    assert outcome.end_reasons == {"h": "finished", "r": "finished"}
    assert outcome.collisions == 0 and not trace.teleports and outcome.success
    accel = site.merge.lanes[-1]  # the acceleration lane: the ramp's lane on the shared edge
    main_lane = next(lane for lane in site.main.lanes if lane.edge_id == accel.edge_id)
    ramp_lanes = [row for row in trace.rows if row[1] == "r"]
    on_main = [row for row in ramp_lanes if row[2] == main_lane.lane_id]
    assert on_main, "the ramp car never reached the highway's lane of the acceleration edge"
    assert on_main[0][3] < accel.length_m - 1.0, "it changed only at the very end of its lane"
    # Past the merge point it drives the highway lane it changed onto, as the highway cars do.
    out_lane = site.out[-1].lane_id
    assert any(row[2] == out_lane for row in ramp_lanes)


@pytest.mark.sumo
def test_no_car_leaves_the_lanes_the_engine_measures(nets: dict[str, Path]) -> None:
    """SUMO's default lane-change mode sent a controlled highway car to the left lane at once (beside
    the ramp car): every car keeps its approach's lane, the ramp car's one change aside."""
    site = choose_merge(nets["onramp"])
    allowed = {lane.lane_id for side in ("main", "merge") for lane in site.route(side)}
    _, trace = _run(nets["onramp"], _ramp_and_highway())
    assert trace.rows
    strays = sorted({(vid, lane) for _, vid, lane, *_ in trace.rows if lane not in allowed})
    assert not strays, f"cars on lanes outside both routes: {strays}"


@pytest.mark.sumo
def test_distances_run_smoothly_along_each_route(nets: dict[str, Path]) -> None:
    """Each car's distance to the merge point falls by about its speed times the step on every step,
    across edges and junction lanes (a wrong table entry is a jump). Its road is its origin before the
    merge point, OUT after it; a ramp car that changed onto the highway's lane is a MAIN car from then."""
    site = choose_merge(nets["onramp"])
    highway_lanes = {site.main.lanes[-1].lane_id}
    _, trace = _run(nets["onramp"], _ramp_and_highway())
    origin = {"h": MAIN, "h2": MAIN, "r": MERGE}
    for vid, road in origin.items():
        rows = [row for row in trace.rows if row[1] == vid]
        assert len(rows) > 20
        dist = np.array([row[5] for row in rows])
        speed = np.array([row[6] for row in rows])
        roads = np.array([row[4] for row in rows])
        step = -np.diff(dist)
        # The distance covered in a step lies between the speeds at its two ends (times the step).
        lo = np.minimum(speed[:-1], speed[1:]) * STEP_LENGTH_S - 0.05
        hi = np.maximum(speed[:-1], speed[1:]) * STEP_LENGTH_S + 0.05
        bad = np.flatnonzero((step < lo) | (step > hi))
        assert not len(bad), f"{vid}: jumps at {[(rows[i][2], rows[i + 1][2], step[i]) for i in bad]}"
        expected = [
            OUT if d < 0 else MAIN if road == MAIN or lane in highway_lanes else MERGE
            for (_, _, lane, *_), d in zip(rows, dist, strict=True)
        ]
        assert roads.tolist() == expected, vid
        assert dist[0] > 0
        if vid != "h2":  # the episode ends when the controlled cars are through, maybe before h2 is
            assert dist[-1] < 0
    assert MAIN in [row[4] for row in trace.rows if row[1] == "r"], "the ramp car never counted as merged"


@pytest.mark.sumo
def test_highway_cars_see_a_ramp_car_that_changed_into_their_lane(nets: dict[str, Path]) -> None:
    """The paper suite's first on-ramp scenario (seed 2019), IDM driving every car with the paper's
    own-lane mask: while a ramp car that had changed lanes stayed a merge-road car, the highway car
    behind it did not see it and ran into it (2 collisions); as a main-road car it is kept clear of."""
    from idas_sumo.evaluation.protocol import EvalConfig, suite_cases

    engine = MergeEngine(nets["onramp"], config=EnvConfig(max_episode_s=60.0))
    try:
        case = suite_cases(
            "paper", 1, 2019, engine.speed_limits_mps, EvalConfig().traffic, engine.road_lengths_m
        )[0]
        (outcome,) = run_episodes(engine, [case.scenario], lambda job, agent: 0, [RuleBasedPolicy("idm")])
    finally:
        engine.close()
    assert outcome.collisions == 0
    assert set(outcome.end_reasons.values()) == {"finished"}


@pytest.mark.sumo
def test_copies_run_the_on_ramp_as_one_episode_each(nets: dict[str, Path], tmp_path: Path) -> None:
    """Two copies of the on-ramp net in one SUMO run give each scenario the outcome it has alone."""
    scenarios = [
        _ramp_and_highway(),
        Scenario("later", (VehicleSpec("a", "main", 100.0, 25.0), VehicleSpec("b", "merge", 60.0, 15.0))),
    ]

    def outcomes(copies: int) -> list[tuple[dict[str, str], int, dict[str, float]]]:
        engine = MergeEngine(nets["onramp"], copies=copies, config=EnvConfig(max_episode_s=60.0))
        try:
            got = run_episodes(engine, scenarios, lambda job, agent: 0, [RuleBasedPolicy("idm")])
        finally:
            engine.close()
        return [(o.end_reasons, o.collisions, o.finish_times_s) for o in got]

    alone = outcomes(1)
    assert alone == outcomes(2)
    assert all(reasons and set(reasons.values()) == {"finished"} for reasons, _, _ in alone)


@pytest.mark.sumo
def test_evaluate_and_train_run_on_the_on_ramp_net(nets: dict[str, Path], tmp_path: Path) -> None:
    net = str(nets["onramp"])
    out = tmp_path / "ev"
    result = run_cli(
        "evaluate", "--baseline", "idas", "--net", net, "--scenarios", "3", "--no-progress", "--out", str(out)
    )
    assert result.returncode == 0, result.stderr
    assert len((out / "episodes.csv").read_text().splitlines()) == 1 + 3
    config = tmp_path / "smoke.toml"
    config.write_text(
        "stage = 'robot'\nrobot_episodes = 2\nepisodes_per_update = 2\ncheckpoint_every = 2\nmax_episode_s = 60.0\n"
    )
    runs = tmp_path / "run"
    result = run_cli("train", "--net", net, "--config", str(config), "--out", str(runs), "--no-progress")
    assert result.returncode == 0, result.stderr
    assert (runs / "robot.pt").is_file()


@pytest.mark.sumo
def test_junction_picks_one_of_several_merges_and_bad_choices_are_one_line(
    nets: dict[str, Path], tmp_path: Path
) -> None:
    two = str(nets["two_merges"])
    ev = ["evaluate", "--baseline", "idm", "--scenarios", "2", "--no-progress", "--suite", "paper"]
    several = run_cli(*ev, "--net", two, "--out", str(tmp_path / "a"))
    assert several.returncode == 2
    lines = several.stderr.strip().splitlines()
    assert len(lines) == 1 and "2 merges (j1, j2)" in lines[0] and "--junction" in lines[0]
    unknown = run_cli(*ev, "--net", two, "--junction", "nope", "--out", str(tmp_path / "b"))
    assert unknown.returncode == 2 and "--junction nope: no merge at that junction" in unknown.stderr
    none = run_cli(*ev, "--net", str(nets["crossing"]), "--out", str(tmp_path / "c"))
    assert none.returncode == 2 and "no merge" in none.stderr and "Traceback" not in none.stderr
    chosen = run_cli(*ev, "--net", two, "--junction", "j2", "--out", str(tmp_path / "d"))
    assert chosen.returncode == 0, chosen.stderr
    # The same net and junction as a MergeEngine's config: episodes run on j2's roads.
    engine = MergeEngine(two, config=EnvConfig(max_episode_s=30.0, junction="j2"))
    try:
        assert engine.site.junction_id == "j2"
        assert engine.site == choose_merge(two, "j2")
    finally:
        engine.close()


def test_nothing_in_env_or_sim_names_the_t_junctions_edges() -> None:
    """The engine, backends and checks know a net only through its MergeSite. netgen.py writes the
    T-junction (and keeps ``read_merge_net``, its adapter), so it alone may name its edges."""
    pattern = re.compile(r"\.(main|merge|out)\.edge_id\b|merge_point|\bedges=\"main\b|\"main_0\"|\"out_0\"")
    found = [
        f"{path.relative_to(PACKAGE)}:{n}: {line.strip()}"
        for folder in ("env", "sim")
        for path in sorted((PACKAGE / folder).glob("*.py"))
        if path.name != "netgen.py"
        for n, line in enumerate(path.read_text().splitlines(), 1)
        if pattern.search(line)
    ]
    assert not found, found
