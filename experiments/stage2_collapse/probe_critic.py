"""What a stage-2 checkpoint's critics say about each action, by speed (issue 36, the stage-2 collapse).

Collects episodes with the checkpoint's policy (the study's recipe and traffic), then for every agent-step and
every allowed action a' computes COMA's counterfactual advantage Q(s, (a⁻ⁿ, a')) - Σ π Q (what J2 would hand the
actor had the agent taken a'), and reports its mean per action for cars nearly at rest (< 2 m/s) and moving,
next to the policy's own probabilities and how the stopped cars' accelerations stand.

    python experiments/stage2_collapse/probe_critic.py CHECKPOINT [--episodes 32]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch
from probe_signal import RECIPE, collect

from idas_sumo.agents.learner import Learner
from idas_sumo.agents.rollout import batch_from_episodes
from idas_sumo.env.layout import ACCEL_SCALE_MPS2, SPEED_SCALE_MPS
from idas_sumo.training.checkpoint import load_checkpoint
from idas_sumo.training.config import load_train_config
from idas_sumo.training.curriculum import plan_stages


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("checkpoint", type=Path)
    parser.add_argument("--episodes", type=int, default=32)
    parser.add_argument("--seed", type=int, default=11)
    parser.add_argument(
        "--horizon", choices=("episode", "agent"), default="episode", help="the return Q is compared with"
    )
    args = parser.parse_args()
    data, _ = collect(args.checkpoint, args.episodes, args.seed)
    batch = batch_from_episodes(data, central=True)
    learner = Learner(plan_stages(load_train_config(RECIPE))[0].learner, seed=0)
    learner.load_state_dict(load_checkpoint(args.checkpoint).learner, load_optimisers=False)
    assert batch.state is not None and batch.others_actions is not None and batch.slot is not None
    with torch.no_grad():
        q = learner.central(batch.state, batch.others_actions, batch.slot.long())
        probs = learner.actor.distribution(batch.obs, batch.mask.bool()).probs
    allowed = batch.mask.bool()
    a2_all = q - (q * probs).sum(1, keepdim=True)
    speed = batch.obs[:, 0].numpy() * SPEED_SCALE_MPS
    accel = batch.obs[:, 1].numpy() * ACCEL_SCALE_MPS2
    timeouts = np.mean([e.stats.timed_out for e in data])
    print(f"{args.checkpoint}: {len(data)} episodes, timed out {timeouts:.0%}, {len(speed)} agent-steps")
    for name, rows in (("< 2 m/s", speed < 2.0), (">= 2 m/s", speed >= 2.0)):
        r = torch.from_numpy(rows)
        if not r.any():
            continue
        a2 = torch.where(allowed[r], a2_all[r], torch.nan)
        print(
            f"  {name}: {int(r.sum())} rows; accel mean {accel[rows].mean():+.2f} m/s², < 0 in {np.mean(accel[rows] < 0):.0%}"
        )
        print("    policy π(a)       " + " ".join(f"{x:6.3f}" for x in probs[r].mean(0).tolist()))
        print("    allowed share     " + " ".join(f"{x:6.3f}" for x in allowed[r].float().mean(0).tolist()))
        print("    Q(s,a') - Σπ Q    " + " ".join(f"{x:+6.2f}" for x in torch.nanmean(a2, 0).tolist()))
        print(
            "    taken share       "
            + " ".join(f"{x:6.3f}" for x in np.bincount(batch.action.numpy()[rows], minlength=7) / rows.sum())
        )
    confounding(batch, q, a2_all, learner.config.gamma, args.horizon)


def team_returns(batch, gamma: float, horizon: str) -> np.ndarray:
    """Each row's discounted joint return to the episode's end (own next row, else the episode's next step), or
    with ``horizon`` 'agent' to its agent's last row."""
    own, team = batch.next_row.numpy(), batch.team_next_row.numpy()
    link = np.where(own >= 0, own, team) if horizon == "episode" else own
    joint = batch.joint_reward.numpy().astype(np.float64)
    g = np.zeros(len(link))
    for i in range(len(link) - 1, -1, -1):
        g[i] = joint[i] + (gamma * g[link[i]] if link[i] >= 0 else 0.0)
    return g


def confounding(batch, q: torch.Tensor, a2_all: torch.Tensor, gamma: float, horizon: str) -> None:
    """Does A2 say what an action does, or where the policy takes it? Per action taken: the mean A2 handed to
    the actor, against the mean return of the rows that took it less the mean return of all rows."""
    g = team_returns(batch, gamma, horizon)
    act = batch.action.numpy()
    q_taken = q.gather(1, batch.action.long().unsqueeze(1)).squeeze(1).numpy()
    a2_taken = a2_all.gather(1, batch.action.long().unsqueeze(1)).squeeze(1).numpy()
    r2 = 1.0 - np.var(g - q_taken) / np.var(g)
    print(
        f"  Q(s, a) against the measured joint return ({horizon} horizon): R² {r2:.2f}, corr {np.corrcoef(q_taken, g)[0, 1]:.2f}"
    )
    print(
        "    per action taken:  mean A2       "
        + " ".join(f"{a2_taken[act == a].mean():+6.2f}" if (act == a).any() else "   nan" for a in range(7))
    )
    print(
        "                       E[G|a] - E[G] "
        + " ".join(
            f"{g[act == a].mean() - g.mean():+6.2f}" if (act == a).any() else "   nan" for a in range(7)
        )
    )


if __name__ == "__main__":
    main()
