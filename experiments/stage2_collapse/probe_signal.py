"""Audit of what reaches the stage-2 learner from real episodes (issue 36, the stage-2 collapse).

Collects stage-2 episodes (the shipped recipe's intelligent-world traffic: 8 learning cars, 40 s) with a policy
(default: the shipped IDAS-V, the recipe's starting point), records them as training does (``collect_episodes``,
``batch_from_episodes``) and checks the learning signal row by row:

- collisions: does each collided car's last row carry done = 1 and its r_collide, for both cars of a pair?
- r_flow: in the joint reward only, never in an agent's own reward?
- timeouts: the rows a timeout cut off (V bootstraps them; Q's target does not);
- masks: how often the mask leaves the hard brake alone; how often release brake is allowed;
- the horizon of Q's target: with ``q_horizon = "agent"`` Q(s, a) sums the joint reward along its agent's own
  rows only, so the joint reward that comes after the agent has left is missing from its target. How large is
  that tail, and what is one more step on the road worth to Q's target (the joint reward of a step after an
  exit) against what it costs J1 (the own finish reward discounted one step more)?

    python experiments/stage2_collapse/probe_signal.py [--episodes 64] [--policy experiments/policies/idas_v_smooth.pt]
"""

from __future__ import annotations

import argparse
from collections import Counter
from pathlib import Path

import numpy as np

from idas_sumo.agents.learner import Learner
from idas_sumo.agents.rollout import EpisodeData, RolloutTask, batch_from_episodes, collect_episodes
from idas_sumo.env.actions import HARD_BRAKE, RELEASE_BRAKE
from idas_sumo.env.engine import MergeEngine
from idas_sumo.env.layout import SPEED_SCALE_MPS
from idas_sumo.env.scenario import generate_scenario, start_room_m
from idas_sumo.sim.merge_detect import choose_merge
from idas_sumo.training.checkpoint import load_checkpoint
from idas_sumo.training.config import load_train_config
from idas_sumo.training.curriculum import plan_stages

ROOT = Path(__file__).resolve().parents[2]
NET = ROOT / "idas_sumo" / "sumo_nets" / "tjunction.net.xml"
RECIPE = ROOT / "experiments" / "stage2_collapse" / "stage2_from_idas_v.toml"


def collect(policy: Path, episodes: int, seed: int, copies: int = 16) -> tuple[list[EpisodeData], float]:
    config = load_train_config(RECIPE)
    plan = plan_stages(config)[0]
    learner = Learner(plan.learner, seed=0)
    learner.load_state_dict(load_checkpoint(policy).learner, load_optimisers=False)
    site = choose_merge(NET, None)
    limits = {"main": site.main.road.speed_limit_mps, "merge": site.merge.road.speed_limit_mps}
    rng = np.random.default_rng(seed)
    room = start_room_m(site)
    tasks = [
        RolloutTask(generate_scenario(rng, plan.traffic, limits, f"probe-{i}", room), seed * 100_000 + i)
        for i in range(episodes)
    ]
    engine = MergeEngine(site, copies=copies, seed=seed, config=config.env)
    try:
        return collect_episodes(engine, learner, tasks), plan.learner.gamma
    finally:
        engine.close()


def discounted_tail(values: np.ndarray, gamma: float) -> np.ndarray:
    out = np.zeros(len(values))
    acc = 0.0
    for i in range(len(values) - 1, -1, -1):
        acc = values[i] + gamma * acc
        out[i] = acc
    return out


def steps_and_agents(e: EpisodeData) -> tuple[np.ndarray, np.ndarray]:
    """Each row's step (from ``team_next_row``: rows of a step share it) and agent (``next_row`` chains)."""
    team = e.team_next_row
    assert team is not None
    step = np.cumsum(np.r_[0, (team[1:] != team[:-1]).astype(np.int64)])
    agent = -np.ones(len(e), dtype=np.int64)
    k = 0
    for i in range(len(e)):
        if agent[i] < 0:
            j = i
            while j >= 0:
                agent[j] = k
                j = int(e.next_row[j])
            k += 1
    return step, agent


def horizon_audit(data: list[EpisodeData], gamma: float) -> None:
    missing: dict[str, list[float]] = {}
    after_exit: list[
        float
    ] = []  # the joint reward of each step that follows an agent's exit (first 25 steps)
    gaps = links = 0
    joint_total = own_total = 0.0
    for e in data:
        if not len(e):
            continue
        step, agent = steps_and_agents(e)
        joint = np.zeros(step[-1] + 1)
        joint[step] = e.joint_reward
        team_return = discounted_tail(joint, gamma)
        joint_total += float(joint.sum())
        own_total += float(e.reward.sum())
        for a in range(agent.max() + 1):
            rows = np.flatnonzero(agent == a)
            own = discounted_tail(e.joint_reward[rows].astype(np.float64), gamma)
            last = rows[-1]
            end = "cut_off" if not e.done[last] else ("collided" if e.reward[last] < 0 else "finished")
            missing.setdefault(end, []).extend((team_return[step[rows]] - own).tolist())
            after_exit.extend(joint[step[last] + 1 : step[last] + 26].tolist())
            t = e.team_next_row[last]
            if t >= 0:
                links += 1
                gaps += int(not np.isin(agent[step == step[last] + 1], agent[step == step[last]]).any())
    print(
        f"joint reward, once per step: {joint_total:.1f} = own rewards {own_total:.1f} + flow {joint_total - own_total:.1f}"
    )
    print("Q's target with q_horizon 'agent': the discounted joint reward after its agent left (team - own):")
    for end, values in missing.items():
        v = np.asarray(values)
        print(
            f"  agents that {end:9s}: {len(v):6d} rows, missing tail mean {v.mean():+7.2f} (sd {v.std():.2f})"
        )
    per_step = float(np.mean(after_exit))
    print(
        f"  joint reward per step in the 25 steps after an agent's exit: {per_step:+.3f} (n = {len(after_exit)})"
    )
    print(f"  links past an agent's last row: {links}; of them to a step with none of its agents: {gaps}")


def signal_audit(data: list[EpisodeData]) -> None:
    batch = batch_from_episodes(data, central=True)
    assert batch.next_valid is not None and batch.joint_reward is not None
    ends: Counter[str] = Counter()
    pairs = 0
    for e in data:
        pairs += e.stats.collisions
        ends.update(e.stats.end_reasons.values())
    done, rew, nxt = batch.done.numpy(), batch.reward.numpy(), batch.next_row.numpy()
    last = nxt < 0
    collided_last = last & (done == 1) & (rew < 0)
    print(f"{len(data)} episodes, {len(rew)} agent-steps; end reasons {dict(ends)}; collision pairs {pairs}")
    print(
        f"  last rows {int(last.sum())}: done {int((last & (done == 1)).sum())} (with r < 0: {int(collided_last.sum())}),"
        f" cut off {int((last & (done == 0)).sum())}; collided agents {ends['collided']}"
    )
    cut = last & (done == 0)
    print(f"  cut-off rows: Q bootstraps {int(batch.next_valid.numpy()[cut].sum())} of {int(cut.sum())}")
    parts = {k: sum(e.stats.reward_parts[k] for e in data) for k in data[0].stats.reward_parts}
    own_sum = float(rew.sum())
    print(
        f"  own rewards sum {own_sum:.1f} = finish + collide + impede {parts['finish'] + parts['collide'] + parts['impede']:.1f}"
        f" (flow {parts['flow']:.1f} only in the joint reward)"
    )
    mask, act = batch.mask.numpy(), batch.action.numpy()
    only_brake = mask.sum(1) == 1
    speed = batch.obs[:, 0].numpy() * SPEED_SCALE_MPS
    print(
        f"  mask = hard brake alone: {only_brake.mean():.3%} of rows; hard brakes {int((act == HARD_BRAKE).sum())},"
        f" forced {int((only_brake & (act == HARD_BRAKE)).sum())}; release allowed {mask[:, RELEASE_BRAKE].mean():.3%}"
    )
    print(
        f"  actions {np.bincount(act, minlength=7).tolist()}; speed mean {speed.mean():.2f} m/s, < 0.5 m/s {np.mean(speed < 0.5):.3%}"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=64)
    parser.add_argument("--policy", type=Path, default=ROOT / "experiments" / "policies" / "idas_v_smooth.pt")
    parser.add_argument("--seed", type=int, default=7)
    args = parser.parse_args()
    data, gamma = collect(args.policy, args.episodes, args.seed)
    signal_audit(data)
    horizon_audit(data, gamma)
    finish = 12.5  # r_finish at b_type 0
    print(
        f"  J1's price of one step more on the road, (1 - γ)·r_finish at b_type 0: {(1 - gamma) * finish:.3f}"
    )


if __name__ == "__main__":
    main()
