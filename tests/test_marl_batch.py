"""The batched multi-agent env: slots fill and empty as the engine's episodes run; masks; the TorchRL example."""

from __future__ import annotations

import importlib.util
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from idas_sumo.env.engine import EnvConfig, MergeEngine
from idas_sumo.env.episodes import run_episodes
from idas_sumo.env.marl_batch import MergeMarlBatch, slots_for
from idas_sumo.env.scenario import Scenario, TrafficConfig, generate_scenario
from idas_sumo.resources import DEFAULT_NET

pytestmark = [pytest.mark.sumo, pytest.mark.usefixtures("no_leaked_simulation")]

WORLDS = 2
WAVES = 2


def _keep_or_first(masks: np.ndarray) -> np.ndarray:
    """Keep the acceleration where allowed, else the first allowed action (row by row)."""
    return np.where(masks[..., 2], 2, np.argmax(masks, axis=-1)).astype(np.int64)


class KeepOrFirst:
    def act(self, batch: Any, rows: np.ndarray) -> np.ndarray:
        return _keep_or_first(batch.masks[rows].astype(bool))


def _scenarios(budget: Any, n: int) -> list[Scenario]:
    traffic = TrafficConfig(n_vehicles=budget.n_vehicles, max_vehicles_per_road=budget.max_vehicles_per_road)
    rng = np.random.default_rng(5)
    limits = MergeEngine(DEFAULT_NET).speed_limits_mps  # no SUMO started: only the net's limits are read
    return [generate_scenario(rng, traffic, limits, name=f"s{i}") for i in range(n)]


def _run_batch(
    env: MergeMarlBatch, waves: int
) -> tuple[dict[int, dict[str, float]], dict[int, dict[str, str]], int]:
    """Drive every slot with ``_keep_or_first`` for ``waves`` waves. Returns, per episode (job), each car's
    summed slot reward and how its slot ended, and how many slot-steps acted."""
    returns: dict[int, dict[str, float]] = defaultdict(dict)
    ends: dict[int, dict[str, str]] = defaultdict(dict)
    state = env.reset()
    acted = 0
    while env.wave <= waves:
        jobs = list(env.jobs)
        ids = [env.engine.slots[k].scenario.controlled_ids for k in range(env.num_worlds)]
        # inactive slots: zero observation, only action 0 allowed
        assert not state.obs[~state.active].any()
        assert (state.action_mask[~state.active].sum(axis=-1) == 1).all()
        assert state.action_mask[~state.active][:, 0].all()
        assert state.active.any() or state.world_over.all()
        actions = _keep_or_first(state.action_mask)
        assert np.take_along_axis(state.action_mask, actions[..., None], axis=-1).all()
        before = state.active
        acted += int(before.sum())
        state = env.step(actions)
        done = state.terminated | state.truncated
        # a car the timeout cut off hands back where it was (still on the road: never all zeros)
        assert np.array_equal(state.final_obs.any(axis=-1), state.truncated)
        assert not (done & ~before).any() and not state.reward[~before].any()
        for k, s in zip(*np.nonzero(before), strict=True):
            j, vid = jobs[k], ids[k][s]
            returns[j][vid] = returns[j].get(vid, 0.0) + float(state.reward[k, s])
            if done[k, s]:
                ends[j][vid] = "timeout" if state.truncated[k, s] else "ended"
                assert not state.active[k, s], "a slot acts again after its car ended"
    return returns, ends, acted


def test_slots_follow_the_engine_episodes(small_budget: Any) -> None:
    scenarios = _scenarios(small_budget, WORLDS * WAVES)
    config = EnvConfig(max_episode_s=small_budget.max_episode_s)
    env = MergeMarlBatch(WORLDS, scenarios=scenarios, config=config)
    try:
        assert env.shape == (WORLDS, max(len(s.controlled_ids) for s in scenarios))
        returns, ends, acted = _run_batch(env, WAVES)
        outcomes = [env.outcomes[j % WORLDS][j // WORLDS] for j in range(len(scenarios))]
    finally:
        env.close()
    engine = MergeEngine(DEFAULT_NET, copies=WORLDS, config=config)
    try:
        expected = run_episodes(engine, scenarios, lambda j, a: 0, [KeepOrFirst()])
    finally:
        engine.close()
    assert acted == sum(o.agent_steps for o in expected) > 0
    for j, (got, want) in enumerate(zip(outcomes, expected, strict=True)):
        assert got.end_reasons == want.end_reasons and got.returns == want.returns, f"episode {j}"
        acting = set(returns[j])
        assert acting, f"episode {j}: no car acted"
        assert {a: want.returns[a] for a in acting} == pytest.approx(returns[j], abs=1e-9)
        assert {
            a: "timeout" if r == "timeout" else "ended" for a, r in want.end_reasons.items() if a in acting
        } == ends[j]


def test_slot_count_and_bad_actions(small_budget: Any) -> None:
    traffic = TrafficConfig(
        n_vehicles=small_budget.n_vehicles, max_vehicles_per_road=small_budget.max_vehicles_per_road
    )
    assert slots_for(traffic) == small_budget.n_vehicles
    assert slots_for(TrafficConfig(n_vehicles=8, max_controlled=3)) == 3
    env = MergeMarlBatch(2, traffic=traffic, config=EnvConfig(max_episode_s=small_budget.max_episode_s))
    try:
        first = env.reset(seed=3)
        with pytest.raises(ValueError, match="shape"):
            env.step(np.zeros((2, 1), dtype=np.int64))
        with pytest.raises(ValueError, match="integers"):
            env.step(np.zeros(env.shape))
        again = env.reset(seed=3)
        assert np.array_equal(first.obs, again.obs) and np.array_equal(first.active, again.active)
    finally:
        env.close()


EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "torchrl_mappo.py"
needs_torchrl = pytest.mark.skipif(
    importlib.util.find_spec("torchrl") is None, reason="torchrl not installed (the torchrl extra)"
)


@needs_torchrl
def test_torchrl_env_steps_as_the_numpy_batch(small_budget: Any) -> None:
    """The TorchRL env's per-slot rewards, ends and observations are the numpy batch's, step for step: a
    slot's "reset" after its car ended does not move SUMO."""
    import torch
    from torchrl.envs.utils import check_env_specs

    from idas_sumo.env.torchrl_env import GROUP, MergeTorchRLEnv

    steps = 120  # past the 20 s timeout: cars end, the wave changes
    scenarios = _scenarios(small_budget, WORLDS * WAVES)
    config = EnvConfig(max_episode_s=small_budget.max_episode_s)

    def policy(td: Any) -> Any:
        return td.set(
            (GROUP, "action"), torch.from_numpy(_keep_or_first(td.get((GROUP, "action_mask")).numpy()))
        )

    env = MergeTorchRLEnv(WORLDS, scenarios=scenarios, config=config)
    try:
        check_env_specs(env)
        data = env.rollout(steps, policy, break_when_any_done=False)
    finally:
        env.close()
    marl = MergeMarlBatch(WORLDS, scenarios=scenarios, config=config)
    try:
        state = marl.reset()
        for t in range(steps):  # the slots a step ended show zeros again at the next (their "reset")
            assert np.array_equal(data[GROUP, "observation"][:, t].numpy(), state.obs), f"step {t}"
            state = marl.step(_keep_or_first(state.action_mask))
            nxt = data["next", GROUP]
            assert np.array_equal(nxt["reward"][:, t, :, 0].numpy(), state.reward.astype(np.float32))
            assert np.array_equal(nxt["truncated"][:, t, :, 0].numpy(), state.truncated)
            assert np.array_equal(nxt["terminated"][:, t, :, 0].numpy(), state.terminated)
        assert data["next", GROUP, "done"].any() and marl.wave == 2
    finally:
        marl.close()


@pytest.mark.skipif(
    importlib.util.find_spec("torchrl") is None, reason="torchrl not installed (the torchrl extra)"
)
def test_torchrl_mappo_example_never_takes_a_masked_action(small_budget: Any) -> None:
    spec = importlib.util.spec_from_file_location("torchrl_mappo", EXAMPLE)
    assert spec is not None and spec.loader is not None
    example = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(example)
    stats = example.main(
        ["--frames", "256", "--worlds", "4", "--frames-per-batch", "128", "--episode-s", "20", "--cars", "4"]
    )
    # main asserts at every step that each sampled action is allowed by its slot's mask
    assert stats["masked_actions"] == 0
    assert stats["agent_steps"] > 0 and stats["frames"] >= 256
