"""How the centralised critic Q of a stage-2 checkpoint rates a hard brake, next to what followed.

    python scripts/critic_brake_probe.py --config scenarios/train_shipped_stage2_safety.toml \
        runs/idas_s2_safe_seed0/intelligent_best.pt [more checkpoints]

For each checkpoint: sample ``--episodes`` intelligent-world episodes of the config's traffic (scenarios of
``--seed``, never an evaluation seed; the policy samples its actions as in training, every car on it) and print

* per action: how often it was taken, Q(s, a) minus the discounted joint return that followed along the agent's
  own steps (γ of the config; a car cut off by the time limit is not bootstrapped), and COMA's advantage;
* over the rows where both a hard brake and Δa = 0 are allowed: Q(s, hard brake) − Q(s, Δa = 0) in the 10 steps
  before the agent's own collision (split by whether the agent is ahead of or behind the other road's car it
  meets at the merge: under the own-lane mask a brake helps the one behind, and the one ahead is hit from behind
  if it brakes) and elsewhere, and the share of rows where Q prefers the brake;
* at a standstill (the agent's speed under 0.1 m/s): Q(Δa = +0.1 or +0.2) − Q(Δa = 0) where allowed, and the
  policy's probabilities of them;
* how the agents that ever hard-braked ended, against those that never did.

The config must be the run's own: its rewards (a ``collide_scale``, say) are what Q was trained on. docs/results.md
("Declared: a collision priced above the brakes it saves") quotes its output.
"""

from __future__ import annotations

import idas_sumo  # noqa: F401  (first: its OMP_WAIT_POLICY must be set before torch loads)

# isort: split
import argparse
import dataclasses
from pathlib import Path

import numpy as np
import numpy.typing as npt
import torch

from idas_sumo.agents.learner import Learner
from idas_sumo.agents.rollout import RolloutTask, batch_from_episodes, collect_episodes
from idas_sumo.env.actions import DELTA_ACCEL_MPS2, HARD_BRAKE
from idas_sumo.env.engine import MergeEngine
from idas_sumo.env.layout import SPEED_SCALE_MPS
from idas_sumo.env.scenario import generate_scenario
from idas_sumo.env.state_layout import STATE_FEATURE_NAMES, STATE_FEATURES, STATE_SLOTS
from idas_sumo.resources import DEFAULT_NET_NAME, resolve_user_path
from idas_sumo.training.checkpoint import load_checkpoint
from idas_sumo.training.config import TrainConfig, load_train_config

KEEP_ACCEL = DELTA_ACCEL_MPS2.index(0.0)  # the action Δa = 0
BEFORE_COLLISION_STEPS = 10  # 2 s at 5 Hz
STANDSTILL_SPEED = 0.1 / SPEED_SCALE_MPS  # 0.1 m/s in the state's scale


def probe(config: TrainConfig, net: Path, checkpoint: Path, episodes: int, seed: int) -> None:
    learner_config = dataclasses.replace(config.learner, use_central_critic=True)
    learner = Learner(learner_config)
    learner.load_state_dict(load_checkpoint(checkpoint).learner, load_optimisers=False)
    engine = MergeEngine(net, copies=16, config=config.env_config())
    rng = np.random.default_rng(seed)
    try:
        tasks = [
            RolloutTask(generate_scenario(rng, config.intelligent_traffic, engine.speed_limits_mps), 1000 + i)
            for i in range(episodes)
        ]
        b = batch_from_episodes(collect_episodes(engine, learner, tasks))
    finally:
        engine.close()
    assert b.next_row is not None and b.joint_reward is not None
    n = b.action.shape[0]
    next_row = b.next_row.numpy()
    assert np.all((next_row < 0) | (next_row > np.arange(n))), "an agent's next row comes after it"
    joint = b.joint_reward.numpy().astype(np.float64)
    reward, done = b.reward.numpy(), b.done.numpy() > 0
    action = b.action.numpy()
    # Backwards over the rows: the discounted joint return along each agent's steps, steps to its end, how it ended.
    ret = np.zeros(n)
    to_end = np.zeros(n, dtype=np.int64)
    collides = np.zeros(n, dtype=np.bool_)
    braked = np.zeros(n, dtype=np.bool_)
    collision_price = -5.0 * config.reward.collide_scale  # r_collide ≤ this; a finish reward is ≥ 5
    for i in range(n - 1, -1, -1):
        j = next_row[i]
        ret[i] = joint[i] + (learner_config.gamma * ret[j] if j >= 0 else 0.0)
        braked[i] = action[i] == HARD_BRAKE or (j >= 0 and braked[j])
        if j >= 0:
            to_end[i], collides[i] = to_end[j] + 1, collides[j]
        else:
            collides[i] = bool(done[i] and reward[i] <= collision_price + 1e-6)
    with torch.no_grad():
        probs = learner.actor.distribution(b.obs, b.mask).probs
        q = learner.central(b.state, b.others_actions, b.slot.long()).numpy()
    q_taken = q[np.arange(n), action]
    advantage = q_taken - (q * probs.numpy()).sum(axis=1)
    print(f"{checkpoint}: {episodes} episodes, {n} agent-steps")
    print("  action  taken %  Q(s,a) - return  COMA advantage")
    for a in range(q.shape[1]):
        taken = action == a
        if taken.any():
            print(
                f"  {a:6d}  {100 * taken.mean():7.1f}  {np.mean(q_taken[taken] - ret[taken]):15.2f}"
                f"  {np.mean(advantage[taken]):14.3f}"
            )
    mask = b.mask.numpy().astype(np.bool_)
    both = mask[:, HARD_BRAKE] & mask[:, KEEP_ACCEL]
    gap = q[:, HARD_BRAKE] - q[:, KEEP_ACCEL]
    before = collides & (to_end < BEFORE_COLLISION_STEPS)
    ahead = _ahead_of_other_road(b.state.numpy(), b.slot.numpy())
    for name, rows in (
        ("before a collision, ahead of the other road's nearest car", both & before & (ahead == 1)),
        ("before a collision, behind it", both & before & (ahead == 0)),
        ("before a collision, past the merge or alone", both & before & (ahead < 0)),
        ("elsewhere", both & ~before),
    ):
        if rows.any():
            print(
                f"  Q(brake) - Q(Δa=0), {name}: {rows.sum()} rows, mean {gap[rows].mean():.2f} (sd {gap[rows].std():.2f}), "
                f"Q prefers the brake in {100 * np.mean(gap[rows] > 0):.0f} %"
            )
    speed = b.state.numpy().reshape(n, STATE_SLOTS, STATE_FEATURES)[
        np.arange(n), b.slot.numpy(), STATE_FEATURE_NAMES.index("speed")
    ]
    stopped = both & (speed < STANDSTILL_SPEED)
    if stopped.any():
        for name, a in (("+0.1", KEEP_ACCEL + 1), ("+0.2", KEEP_ACCEL + 2)):
            go = stopped & mask[:, a]
            if go.any():
                lift = q[:, a] - q[:, KEEP_ACCEL]
                print(
                    f"  at a standstill ({stopped.sum()} rows): Q(Δa={name}) - Q(Δa=0) over {go.sum()} rows where "
                    f"allowed, mean {lift[go].mean():.2f}, Q prefers it in {100 * np.mean(lift[go] > 0):.0f} %; "
                    f"policy P(Δa={name}) {probs.numpy()[go, a].mean():.3f}, P(Δa=0) {probs.numpy()[go, KEEP_ACCEL].mean():.3f}"
                )
    first = np.ones(n, dtype=np.bool_)
    first[next_row[next_row >= 0]] = False
    for did in (False, True):
        ends = [_end(i, next_row, collides, done) for i in np.flatnonzero(first & (braked == did))]
        if ends:
            shares = {e: 100 * ends.count(e) / len(ends) for e in ("finished", "collided", "cut off")}
            print(
                f"  agents that {'did' if did else 'never'} hard-brake: {len(ends)}; "
                + ", ".join(f"{e} {v:.0f} %" for e, v in shares.items())
            )


def _ahead_of_other_road(
    state: npt.NDArray[np.float32], slot: npt.NDArray[np.int64]
) -> npt.NDArray[np.int64]:
    """Per row: 1 when the agent is nearer the merge point than the other incoming road's car whose distance to
    it is closest to its own (the car it meets there), 0 when farther, -1 when it is past the merge or that road
    is empty."""
    vehicles = state.reshape(state.shape[0], STATE_SLOTS, STATE_FEATURES)
    col = {
        name: STATE_FEATURE_NAMES.index(name) for name in ("present", "on_main", "on_merge", "dist_to_merge")
    }
    rows = np.arange(state.shape[0])
    own = vehicles[rows, slot]
    out = np.full(state.shape[0], -1, dtype=np.int64)
    for road, other in (("on_main", "on_merge"), ("on_merge", "on_main")):
        mine = own[:, col[road]] > 0
        candidates = (vehicles[:, :, col["present"]] > 0) & (vehicles[:, :, col[other]] > 0)
        gap = np.abs(vehicles[:, :, col["dist_to_merge"]] - own[:, None, col["dist_to_merge"]])
        gap = np.where(candidates, gap, np.inf)
        nearest = gap.argmin(axis=1)
        found = mine & np.isfinite(gap[rows, nearest])
        partner_dist = vehicles[rows, nearest, col["dist_to_merge"]]
        out[found] = (own[found, col["dist_to_merge"]] < partner_dist[found]).astype(np.int64)
    return out


def _end(
    row: int, next_row: npt.NDArray[np.int64], collides: npt.NDArray[np.bool_], done: npt.NDArray[np.bool_]
) -> str:
    while next_row[row] >= 0:
        row = int(next_row[row])
    return "collided" if collides[row] else ("finished" if done[row] else "cut off")


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("checkpoints", nargs="+", type=Path)
    parser.add_argument("--config", required=True, type=resolve_user_path, help="the runs' training config")
    parser.add_argument("--net", type=resolve_user_path, default=DEFAULT_NET_NAME)
    parser.add_argument("--episodes", type=int, default=64)
    parser.add_argument("--seed", type=int, default=77, help="scenario seed (not an evaluation seed)")
    args = parser.parse_args()
    config = load_train_config(args.config)
    for checkpoint in args.checkpoints:
        probe(config, args.net, checkpoint, args.episodes, args.seed)


if __name__ == "__main__":
    main()
