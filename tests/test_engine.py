"""The episode engine (env/engine.py): K copies side by side give each scenario's numbers exactly.

``tests/data/engine_golden.json`` holds what the single-episode path (``MergeSimulation``, now gone)
produced on fixed paper-suite scenarios: per episode, a digest of every step's acting agents, masks,
rewards, reward parts and end reasons, plus the outcome counts. The engine must reproduce it with one
copy and with several.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import zlib
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pytest

from idas_sumo.baselines.policies import RuleBasedPolicy
from idas_sumo.env.config import EnvConfig
from idas_sumo.env.contracts import AgentBatch, Policy, StepResult
from idas_sumo.env.engine import MergeEngine
from idas_sumo.env.episodes import run_episodes
from idas_sumo.env.scenario import TrafficConfig
from idas_sumo.env.single import SingleEpisode
from idas_sumo.env.snapshot import MAIN, MERGE, OUT, TrafficSnapshot, lane_relations, leaders
from idas_sumo.evaluation.protocol import suite_cases
from idas_sumo.sim.netgen import read_merge_net

if TYPE_CHECKING:
    pass

GOLDEN = Path(__file__).parent / "data" / "engine_golden.json"
GOLDEN_SEED = 7
GOLDEN_SCENARIOS = 8
GOLDEN_MAX_EPISODE_S = 40.0
# The goldens pin the engine's mechanics as they were: the merge-aware mask and the first generator's
# traffic (2 to 8 cars per road, all at t = 0), not today's defaults (own-lane mask, staggered entries).
GOLDEN_TRAFFIC = TrafficConfig(n_vehicles=0, min_vehicles_per_road=2, max_vehicles_per_road=8)
GOLDEN_ENV = EnvConfig(max_episode_s=GOLDEN_MAX_EPISODE_S, safety_mask="merge_aware")


def golden_cases(net_path: Path) -> list:
    net = read_merge_net(net_path)
    limits = {"main": net.main.speed_limit_mps, "merge": net.merge.speed_limit_mps}
    return suite_cases("paper", GOLDEN_SCENARIOS, GOLDEN_SEED, limits, GOLDEN_TRAFFIC)


def jitter_actions(ids: list[str], t: float, masks: np.ndarray, idm: np.ndarray) -> np.ndarray:
    """An erratic driver that is the same in every run and every K: IDM's action, but one step in four
    an allowed action picked by a hash of the agent and the time (so the golden runs see hard brakes,
    impedes and timeouts)."""
    out = []
    for a, m, planned in zip(ids, masks, idm.tolist(), strict=True):
        h = zlib.crc32(f"{a}@{t:.1f}".encode())
        allowed = np.flatnonzero(m)
        out.append(int(allowed[(h // 4) % len(allowed)]) if h % 4 == 0 else planned)
    return np.array(out, dtype=np.int64)


def erratic(agent: str) -> bool:
    """Agents of the golden runs that drive with ``jitter_actions`` (the others: IDM; the ego: FSM+IDM)."""
    return agent[-1] in "13579"


class JitterPolicy:
    def act(self, batch: AgentBatch, rows: np.ndarray) -> np.ndarray:
        idm = RuleBasedPolicy("idm").act(batch, rows)
        return jitter_actions([batch.ids[r] for r in rows], batch.time_s, batch.masks[rows], idm)


def _digest_lines(lines: list[str]) -> str:
    return hashlib.sha256("\n".join(lines).encode()).hexdigest()


def step_line(
    t: float, ids: list[str], masks: np.ndarray, parts: dict[str, list[float]], reasons: list[str]
) -> str:
    """One step, canonically: time, then per agent id, mask bits, reward parts (finish collide impede flow), end."""
    cells = [f"{t:.3f}"]
    for i, a in enumerate(ids):
        bits = "".join(str(int(b)) for b in masks[i])
        values = " ".join(f"{v:.6f}" for v in parts[a])
        cells.append(f"{a}|{bits}|{values}|{reasons[i]}")
    return ";".join(cells)


class _Recorder:
    """Observer: step lines per job."""

    def __init__(self) -> None:
        self.lines: dict[int, list[str]] = {}

    def decided(self, engine: MergeEngine, jobs, batch: AgentBatch, actions) -> None:
        self._batch = batch

    def stepped(self, engine: MergeEngine, jobs, batch: AgentBatch, actions, result: StepResult) -> None:
        for k in np.unique(batch.copy).tolist():
            rows = np.flatnonzero(batch.copy == k)
            ids = [batch.ids[r] for r in rows]
            parts = {batch.ids[r]: result.reward_parts[r].tolist() for r in rows}
            reasons = [result.end_reason[r] for r in rows]
            line = step_line(batch.time_s, ids, batch.masks[rows], parts, reasons)
            self.lines.setdefault(jobs[k], []).append(line)

    def ended(self, engine: MergeEngine, slot: int, job: int, outcome) -> None:
        pass


def engine_records(net_path: Path, copies: int) -> list[dict[str, object]]:
    cases = golden_cases(net_path)
    engine = MergeEngine(net_path, copies=copies, config=GOLDEN_ENV)
    assert engine.copies == copies, "another simulation held libsumo: the copies did not run side by side"
    policies: list[Policy] = [RuleBasedPolicy("fsm_idm"), RuleBasedPolicy("idm"), JitterPolicy()]
    recorder = _Recorder()
    try:
        outcomes = run_episodes(
            engine,
            [c.scenario for c in cases],
            lambda job, agent: 0 if agent == cases[job].ego else (2 if erratic(agent) else 1),
            policies,
            recorder,
        )
    finally:
        engine.close()
    return [
        {
            "scenario": c.scenario.name,
            "steps": _digest_lines(recorder.lines.get(j, [])),
            "decision_steps": len(recorder.lines.get(j, [])),
            "collisions": o.collisions,
            "hard_brakes": o.hard_brakes,
            "hard_brakes_merge_zone": o.hard_brakes_merge_zone,
            "impedes": o.impedes,
            "end_reasons": dict(sorted(o.end_reasons.items())),
            "returns": {a: round(r, 6) for a, r in sorted(o.returns.items())},
            "start_time_s": round(o.start_time_s, 3),
            "end_time_s": round(o.end_time_s, 3),
        }
        for j, (c, o) in enumerate(zip(cases, outcomes, strict=True))
    ]


@pytest.mark.sumo
@pytest.mark.parametrize("copies", [1, 3])
def test_engine_reproduces_the_single_episode_path(net_path: Path, copies: int) -> None:
    golden = json.loads(GOLDEN.read_text())
    assert len(golden) == GOLDEN_SCENARIOS
    assert engine_records(net_path, copies) == golden


def _snapshot(road: list[int], dist: list[float], copy: list[int] | None) -> TrafficSnapshot:
    n = len(road)
    return TrafficSnapshot(
        ids=tuple(f"v{i}" for i in range(n)),
        road=np.array(road, dtype=np.int64),
        dist_to_merge_m=np.array(dist),
        speed_mps=np.full(n, 10.0),
        accel_mps2=np.zeros(n),
        length_m=np.full(n, 5.0),
        speed_limit_mps=np.full(n, 15.0),
        copy=None if copy is None else np.array(copy, dtype=np.int64),
    )


def test_relations_never_cross_copies() -> None:
    road = [MAIN, MAIN, MERGE, OUT]
    dist = [100.0, 80.0, 90.0, -10.0]
    one = _snapshot(road, dist, None)
    nb, same, other = lane_relations(one, np.array([0]))
    assert nb.cols[0].tolist() == [0, 1, 2, 3]
    assert same[0].tolist() == [False, True, False, True]
    assert other[0].tolist() == [False, False, True, False]
    # The same cars, but the leader and the merge-road car drive in another copy of the merge.
    split = _snapshot(road, dist, [0, 1, 1, 0])
    nb, same, other = lane_relations(split, np.array([0]))
    # Interleaved copies: every vehicle is a column, the other copy's masked out.
    assert nb.cols[0].tolist() == [0, 1, 2, 3]
    assert same[0].tolist() == [False, False, False, True]
    assert other[0].tolist() == [False, False, False, False]
    assert leaders(one, np.array([0]))[0].tolist() == [1]
    assert leaders(split, np.array([0]))[0].tolist() == [3]


def single_path_records(net_path: Path) -> list[dict[str, object]]:
    """The environments' single-episode path (``SingleEpisode``, a K = 1 engine), one scenario at a time.

    The golden file came from the old ``MergeSimulation`` on this loop; it keeps that value.
    """
    from idas_sumo.baselines.policies import fsm_idm_actions, idm_actions

    cases = golden_cases(net_path)
    sim = SingleEpisode(net_path, config=GOLDEN_ENV)
    records: list[dict[str, object]] = []
    try:
        for case in cases:
            sim.reset(case.scenario)
            start = sim.time_s
            lines: list[str] = []
            counts = {"collisions": 0, "hard_brakes": 0, "hard_brakes_merge_zone": 0, "impedes": 0}
            returns: dict[str, float] = {}
            while not sim.episode_over:
                agents = sim.active_agents
                t = sim.time_s
                _, masks = sim.observe(agents)
                egos = sim.snapshot.index(agents)
                prev = np.array([sim.prev_accel(a) for a in agents])
                idm = idm_actions(sim.snapshot, egos, prev, masks)
                fsm = fsm_idm_actions(sim.snapshot, egos, prev, masks)
                jit = jitter_actions(agents, t, masks, idm)
                chosen = np.where(
                    np.array([a == case.ego for a in agents]),
                    fsm,
                    np.where(np.array([erratic(a) for a in agents]), jit, idm),
                )
                out = sim.step({a: int(c) for a, c in zip(agents, chosen, strict=True)})
                parts = {
                    a: [out.reward_parts[a][p] for p in ("finish", "collide", "impede", "flow")]
                    for a in agents
                }
                reasons = [out.end_reason.get(a, "") for a in agents]
                lines.append(step_line(t, agents, masks, parts, reasons))
                counts["collisions"] += len(out.collisions)
                counts["hard_brakes"] += out.hard_brakes
                counts["hard_brakes_merge_zone"] += out.hard_brakes_merge_zone
                counts["impedes"] += sum(1 for p in out.reward_parts.values() if p["impede"] < 0)
                for a, r in out.rewards.items():
                    returns[a] = returns.get(a, 0.0) + r
            records.append(
                {
                    "scenario": case.scenario.name,
                    "steps": _digest_lines(lines),
                    "decision_steps": len(lines),
                    **counts,
                    "end_reasons": dict(sorted(sim.finished_agents.items())),
                    "returns": {a: round(r, 6) for a, r in sorted(returns.items())},
                    "start_time_s": round(start, 3),
                    "end_time_s": round(sim.time_s, 3),
                }
            )
    finally:
        sim.close()
    return records


@pytest.mark.sumo
def test_single_episode_path_gives_the_golden_file(net_path: Path) -> None:
    assert single_path_records(net_path) == json.loads(GOLDEN.read_text())


@pytest.mark.sumo
def test_evaluation_csvs_do_not_depend_on_copies_or_workers(tmp_path: Path, net_path: Path) -> None:
    from idas_sumo.cli import main

    outs = []
    base = ["evaluate", "--net", str(net_path), "--baseline", "all", "--others", "idm", "--scenarios", "6"]
    for copies, workers in ((1, 1), (4, 1), (2, 2)):
        out = tmp_path / f"k{copies}-w{workers}"
        args = [*base, "--seed", "3", "--trajectories", "--no-progress", "--out", str(out)]
        assert main([*args, "--copies", str(copies), "--workers", str(workers)]) == 0
        outs.append(out)
    names = ["episodes.csv", "summary.csv", "flow.csv", "trajectories.csv"]
    for other in outs[1:]:
        for name in names:
            assert (outs[0] / name).read_bytes() == (other / name).read_bytes(), (other.name, name)
    # Several methods and scenarios ran side by side: the comparison saw more than one job per SUMO run.
    assert len((outs[0] / "episodes.csv").read_text().splitlines()) == 1 + 5 * 6


def test_split_jobs_covers_every_job_once_in_order() -> None:
    from idas_sumo.evaluation.workers import split_jobs

    for n in (1, 2, 5, 500):
        for workers in (1, 2, 3, 7):
            shares = split_jobs(n, workers)
            assert [j for share in shares for j in share] == list(range(n))
            assert all(len(share) > 0 for share in shares)
            assert len(shares) == min(n, workers)


ROLLOUT_GOLDEN = Path(__file__).parent / "data" / "rollout_golden.json"


def rollout_tasks(net_path: Path) -> list:
    from idas_sumo.agents.rollout import RolloutTask

    cases = golden_cases(net_path)[:5]
    return [RolloutTask(c.scenario, action_seed=100 + i, deterministic=(i == 2)) for i, c in enumerate(cases)]


NOT_IN_GOLDEN = ("team_next_row",)
"""Fields the golden rollouts predate (``team_next_row``'s links are checked in tests/test_training.py)."""


def episode_digest(e: object) -> dict[str, object]:
    """Every array of an ``EpisodeData`` it carries as a digest, and its stats but ``success`` and ``perfect``
    (which took the evaluation's meaning when rollouts moved onto the engine)."""
    import dataclasses

    out: dict[str, object] = {}
    for f in dataclasses.fields(e):  # type: ignore[arg-type]
        value = getattr(e, f.name)
        if value is None or f.name in NOT_IN_GOLDEN:  # ``explored`` without exploration; fields added later
            continue
        if f.name == "stats":
            stats = dataclasses.asdict(value)
            stats.pop("success"), stats.pop("perfect")
            out["stats"] = json.loads(json.dumps(stats))
        else:
            array = np.ascontiguousarray(value)
            out[f.name] = f"{array.dtype}{array.shape}:" + hashlib.sha256(array.tobytes()).hexdigest()
    return out


@pytest.mark.sumo
def test_rollouts_match_their_golden_file_with_one_copy_or_three(net_path: Path) -> None:
    """The golden file holds these tasks' episodes with a randomly initialised actor: sampling and greedy
    episodes, timeouts, cut-off agents. (Its greedy episode dates from the single-episode rollout, now gone;
    the sampled ones were re-baselined when rollouts began drawing from per-episode Philox streams,
    agents/sampling.py.)"""
    from idas_sumo.agents.learner import Learner, LearnerConfig
    from idas_sumo.agents.rollout import collect_episodes

    golden = json.loads(ROLLOUT_GOLDEN.read_text())
    learner = Learner(LearnerConfig(), seed=3)
    tasks = rollout_tasks(net_path)
    for copies in (1, 3):
        engine = MergeEngine(net_path, copies=copies, config=GOLDEN_ENV)
        assert engine.copies == copies
        try:
            new = collect_episodes(engine, learner, tasks)
        finally:
            engine.close()
        assert [episode_digest(e) for e in new] == golden
        for e, t in zip(new, tasks, strict=True):  # success: the evaluation's meaning (EpisodeOutcome)
            finished = all(e.stats.end_reasons.get(a) == "finished" for a in t.scenario.controlled_ids)
            assert e.stats.success == (e.stats.collisions == 0 and finished)
    stats = [g["stats"] for g in golden]
    assert any(s["timed_out"] for s in stats)
    assert any("finished" in s["end_reasons"].values() for s in stats)


@pytest.mark.sumo
def test_episodes_loaded_ahead_are_those_a_reset_starts(
    net_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``preload_episodes`` (a rollout worker's next round, loaded while it waits) starts the first wave as
    ``collect_episodes`` does, which then does not load it again; other tasks, or tasks read since, load anew."""
    from idas_sumo.agents.learner import Learner, LearnerConfig
    from idas_sumo.agents.rollout import collect_episodes, preload_episodes
    from idas_sumo.sim.batch import BatchBackend

    loads: list[int] = []
    real_reset = BatchBackend.reset

    def counted_reset(self: BatchBackend, scenarios: Any, *args: Any) -> None:
        loads.append(len(scenarios))
        real_reset(self, scenarios, *args)

    monkeypatch.setattr(BatchBackend, "reset", counted_reset)
    golden = json.loads(ROLLOUT_GOLDEN.read_text())
    learner = Learner(LearnerConfig(), seed=3)
    tasks = rollout_tasks(net_path)
    engine = MergeEngine(net_path, copies=3, config=GOLDEN_ENV)
    try:
        preload_episodes(engine, tasks)
        assert loads == [3]
        assert [episode_digest(e) for e in collect_episodes(engine, learner, tasks)] == golden
        assert loads == [3, 2]  # the second wave's only
        preload_episodes(engine, tasks[1:])  # not the tasks collected next
        assert [episode_digest(e) for e in collect_episodes(engine, learner, tasks)] == golden
        assert loads == [3, 2, 3, 3, 2]
        preload_episodes(engine, tasks)
        engine.observe()  # read since it was loaded
        assert [episode_digest(e) for e in collect_episodes(engine, learner, tasks)] == golden
        assert loads == [3, 2, 3, 3, 2, 3, 3, 2]
    finally:
        engine.close()


def test_an_episodes_bank_takes_its_rows_of_each_step_then_the_bootstrap_rows() -> None:
    """``rollout._bank``: the observations of an episode's rows of the step log (two runs in step 0, one each
    in steps 1 and 2), then its bootstrap rows; an episode without rows has an empty bank."""
    from idas_sumo.agents.rollout import _bank
    from idas_sumo.env.layout import OBS_DIM

    steps = [np.full((n, OBS_DIM), float(s), dtype=np.float32) for s, n in enumerate((3, 4, 2))]
    for s, obs in enumerate(steps):
        obs[:, 0] = 10 * s + np.arange(len(obs))  # step s, row i: 10 s + i
    starts = np.array([0, 3, 7, 9])
    rows, step = np.array([0, 2, 3, 4, 7, 8]), np.array([0, 0, 1, 1, 2, 2])
    bank = _bank(steps, starts, step, rows, [np.full((1, OBS_DIM), -1.0, dtype=np.float32)])
    assert bank[:, 0].tolist() == [0, 2, 10, 11, 20, 21, -1]
    assert bank[:, 1].tolist() == [0, 0, 1, 1, 2, 2, -1]
    empty = np.zeros(0, dtype=np.int64)
    assert _bank(steps, starts, empty, empty, []).shape == (0, OBS_DIM)


def test_copies_side_by_side_see_what_each_copy_alone_sees() -> None:
    """Per-copy neighbourhoods (copies sorted, as the batch backend gives them) change no observation,
    leader or other-road leader: each copy's rows equal those of that copy simulated alone."""
    from idas_sumo.env.observation import build_observations
    from idas_sumo.env.snapshot import other_road_leaders

    rng = np.random.default_rng(7)
    sizes = [3, 0, 6, 1, 5]
    copy = np.repeat(np.arange(len(sizes)), sizes)
    n = len(copy)
    road = rng.integers(0, 3, n)
    dist = np.where(road == OUT, -rng.uniform(0, 80, n), rng.uniform(0, 150, n)).round(1)
    together = _snapshot(road.tolist(), dist.tolist(), copy.tolist())
    together = dataclasses.replace(together, speed_mps=rng.uniform(0, 20, n))
    egos = np.arange(n)
    obs = build_observations(together, egos, np.zeros(n), np.zeros(n), np.zeros(n))
    lead, gap = leaders(together, egos)
    other, other_gap = other_road_leaders(together, egos, max_ahead_m=50.0)
    start = 0
    for size in sizes:
        part = slice(start, start + size)
        alone = dataclasses.replace(
            together,
            ids=together.ids[part],
            road=together.road[part],
            dist_to_merge_m=together.dist_to_merge_m[part],
            speed_mps=together.speed_mps[part],
            accel_mps2=together.accel_mps2[part],
            length_m=together.length_m[part],
            speed_limit_mps=together.speed_limit_mps[part],
            copy=None,
        )
        own = np.arange(size)
        np.testing.assert_array_equal(
            obs[part], build_observations(alone, own, np.zeros(size), np.zeros(size), np.zeros(size))
        )
        alone_lead, alone_gap = leaders(alone, own)
        np.testing.assert_array_equal(lead[part], np.where(alone_lead >= 0, alone_lead + start, -1))
        np.testing.assert_array_equal(gap[part], alone_gap)
        alone_other, alone_other_gap = other_road_leaders(alone, own, max_ahead_m=50.0)
        np.testing.assert_array_equal(other[part], np.where(alone_other >= 0, alone_other + start, -1))
        np.testing.assert_array_equal(other_gap[part], alone_other_gap)
        start += size
    assert np.count_nonzero(obs[:, 5:]) > 0 and np.any(lead >= 0) and np.any(other >= 0)
