"""Audit of what reaches the stage-2 learner from real episodes (issue 36, stage-2 collapse).

Collects stage-2 episodes (the shipped recipe's intelligent-world traffic, 8 learning cars) with a
policy (default: the shipped IDAS-V, the recipe's init), records them exactly as training does
(``collect_episodes`` -> ``batch_from_episodes``) and checks the learning signal row by row:

- collisions: does each collided car's last row carry done = 1 and r_collide, for both cars?
- timeouts: done / next_valid of the rows a timeout cut off (V bootstraps them; does Q?)
- the horizon of Q's target: Q(s, a) regresses to the joint reward summed along the agent's own rows
  only; the joint return of the episode goes on after the agent leaves. How large is that tail, and
  how does it depend on how the agent left (finished / collided / cut off)?
- masks: how often the mask leaves the hard brake alone; release brake allowed; standstill cars.

    python experiments/stage2_collapse/probe_signal.py [--episodes 64] [--policy idas_sumo/policies/idas_v.pt]
"""

from __future__ import annotations

import argparse
from collections import Counter
from pathlib import Path

import numpy as np
import torch

from idas_sumo.agents.learner import Learner
from idas_sumo.agents.rollout import RolloutTask, batch_from_episodes, collect_episodes
from idas_sumo.env.actions import HARD_BRAKE, RELEASE_BRAKE
from idas_sumo.env.engine import MergeEngine
from idas_sumo.env.scenario import generate_scenario, start_room_m
from idas_sumo.resources import SCENARIO_DIR
from idas_sumo.sim.merge_detect import choose_merge
from idas_sumo.training.checkpoint import load_checkpoint
from idas_sumo.training.config import load_train_config
from idas_sumo.training.curriculum import plan_stages

NET = Path(__file__).resolve().parents[2] / "idas_sumo" / "sumo_nets" / "tjunction.net.xml"


def collect(policy: Path, episodes: int, seed: int, copies: int = 16):
    config = load_train_config(SCENARIO_DIR / "train_smooth_stage2_full.toml")
    plan = plan_stages(config)[0]
    learner = Learner(plan.learner, seed=0)
    learner.load_state_dict(load_checkpoint(policy).learner, load_optimisers=False)
    site = choose_merge(NET, None)
    limits = {"main": site.main.road.speed_limit_mps, "merge": site.merge.road.speed_limit_mps}
    rng = np.random.default_rng(seed)
    tasks = [
        RolloutTask(
            scenario=generate_scenario(
                rng, plan.traffic, limits, name=f"probe-{i}", start_room_m=start_room_m(site)
            ),
            action_seed=seed * 100_000 + i,
        )
        for i in range(episodes)
    ]
    engine = MergeEngine(site, copies=copies, seed=seed, config=config.env)
    try:
        data = collect_episodes(engine, learner, tasks)
    finally:
        engine.close()
    return data, plan, learner


def discounted_tail(values: np.ndarray, gamma: float) -> np.ndarray:
    out = np.zeros_like(values, dtype=np.float64)
    acc = 0.0
    for i in range(len(values) - 1, -1, -1):
        acc = values[i] + gamma * acc
        out[i] = acc
    return out


def horizon_audit(data, gamma: float) -> dict[str, list[float]]:
    """Per agent-step: G_agent (joint reward along the agent's own rows, what Q's λ=1 target is) and
    G_team (joint reward to the episode's end). Grouped by how the agent ended."""
    by_end: dict[str, list[float]] = {}
    first_row_gap: dict[str, list[float]] = {}
    for e in data:
        n = len(e)
        if not n:
            continue
        # the episode's joint reward per step: rows of one step share it; steps are contiguous rows
        step_of_row = np.zeros(n, dtype=np.int64)
        # reconstruct step boundaries from the state rows (equal within a step) is fragile: use next_row
        # chains instead, every agent's rows are consecutive steps, so step index = first step + position.
        # Steps are recorded in order; a new step starts where a row's agent repeats or order restarts.
        seen: set[int] = set()
        step = 0
        agent_of = {}
        # agent identity: follow next_row chains
        agent = -np.ones(n, dtype=np.int64)
        k = 0
        for i in range(n):
            if agent[i] < 0:
                j = i
                while j >= 0:
                    agent[j] = k
                    j = int(e.next_row[j])
                k += 1
        for i in range(n):
            if int(agent[i]) in seen:
                step += 1
                seen = set()
            seen.add(int(agent[i]))
            step_of_row[i] = step
        # a new step also starts when a new agent appears after... (agents appear in stable order)
        joint_per_step = np.zeros(step + 1)
        joint_per_step[step_of_row] = e.joint_reward
        team = discounted_tail(joint_per_step, gamma)
        for a in range(k):
            rows = np.flatnonzero(agent == a)
            own = discounted_tail(e.joint_reward[rows].astype(np.float64), gamma)
            last = rows[-1]
            end = (
                "collided"
                if e.reward[last] < -4 and e.done[last]
                else ("finished" if e.done[last] else "cut_off")
            )
            if e.done[last] and e.reward[last] > 0:
                end = "finished"
            gap = team[step_of_row[rows]] - own
            by_end.setdefault(end, []).extend(gap.tolist())
            first_row_gap.setdefault(end, []).append(float(gap[0]))
    return {"per_row": by_end, "first_row": first_row_gap}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=64)
    parser.add_argument("--policy", type=Path, default=Path("idas_sumo/policies/idas_v.pt"))
    parser.add_argument("--seed", type=int, default=7)
    args = parser.parse_args()
    data, plan, learner = collect(args.policy, args.episodes, args.seed)
    gamma = plan.learner.gamma
    batch = batch_from_episodes(data, central=True)
    print(f"{len(data)} episodes, {len(batch.action)} agent-steps, gamma {gamma}")

    # collisions: each collided car's last row
    ends = Counter()
    collided_rows_ok = collided_cars = 0
    collisions = 0
    for e in data:
        collisions += e.stats.collisions
        for vid, reason in e.stats.end_reasons.items():
            ends[reason] += 1
    done = batch.done.numpy()
    rew = batch.reward.numpy()
    nv = batch.next_valid.numpy()
    nr = batch.next_row.numpy()
    last = nr < 0
    print("end reasons (agents):", dict(ends), "collision pairs:", collisions)
    print(f"rows done=1: {int(done.sum())}; with r<=-5 (collide): {int(((rew <= -5) & (done == 1)).sum())}")
    print(
        f"last rows: {int(last.sum())}; done=1 {int((last & (done == 1)).sum())}; cut off (done 0): {int((last & (done == 0)).sum())}"
    )
    print(f"cut-off rows next_valid: {nv[last & (done == 0)].tolist()[:10]} (0 = Q target not bootstrapped)")

    # masks
    mask = batch.mask.numpy()
    act = batch.action.numpy()
    only_brake = mask.sum(1) == 1
    print(
        f"rows whose mask allows the hard brake alone: {only_brake.mean():.3%}; hard brakes chosen: {(act == HARD_BRAKE).mean():.3%}, "
        f"of them forced {(only_brake & (act == HARD_BRAKE)).sum()}/{(act == HARD_BRAKE).sum()}"
    )
    print(
        f"release allowed: {mask[:, RELEASE_BRAKE].mean():.3%}; action histogram:",
        np.bincount(act, minlength=7).tolist(),
    )

    # Q horizon
    audit = horizon_audit(data, gamma)
    for end, gaps in audit["per_row"].items():
        g = np.asarray(gaps)
        f = np.asarray(audit["first_row"][end])
        print(
            f"end {end:9s}: agents {len(f):4d}, rows {len(g):6d}; team tail missing from Q's target "
            f"(G_team - G_agent): per row mean {g.mean():+.2f} (sd {g.std():.2f}), at first row mean {f.mean():+.2f}"
        )
    # joint reward composition
    parts = Counter()
    for e in data:
        for k, v in e.stats.reward_parts.items():
            parts[k] += v / len(data)
    print("reward parts per episode:", {k: round(v, 2) for k, v in parts.items()})


if __name__ == "__main__":
    main()
