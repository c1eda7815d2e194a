"""Does the centralised critic Q know what an agent's action leads to? Q's counterfactual against a measured one.

    python scripts/counterfactual_probe.py --config scenarios/train_shipped_stage2_safety.toml \
        runs/idas_s2_safe_seed0/intelligent_best.pt [more checkpoints]

COMA's advantage rests on Q(s, a') for actions the agent did not take. The simulator can show what they lead to:
for each checkpoint, sample ``--scenarios`` intelligent-world episodes of the config's traffic (scenarios of
``--seed``, never an evaluation seed; every car on the checkpoint's policy, sampling as in training), pick
``--points`` decisions per episode where the agent could choose both a hard brake and Δa = 0 (half of them, where
there are any, in the 10 steps before a collision of that agent), and replay the episode once per action
(hard brake, Δa = −0.2, 0, +0.2, where allowed) and per continuation seed: every episode of a scenario is the
same up to the decision (the same action draws), the decision is replaced (``RolloutTask.override``), and the
draws after it come from the continuation seed, the same for every action (common random numbers). The measured
value of an action is the discounted joint return along the agent's own steps from there (Q's target: γ of the
config, a car cut off by the time limit not bootstrapped), averaged over the continuations.

With ``--hold N`` each replayed action is kept for the agent's next N decisions (a masked one replaced by the
closest allowed, as always): what a sustained brake or slow-down leads to, which COMA's one-step counterfactual
never asks (Q's column is still its one-step view). Printed per checkpoint and action a ≠ Δa = 0: the mean of Q(s, a) − Q(s, Δa = 0) and of its measured
counterpart, their correlation over the decisions (Pearson and Spearman), how often they agree in sign, and the
standard error of the measured differences (the continuations' noise); before a collision and elsewhere.
docs/results.md ("Declared diagnostic: Q's counterfactual against a measured one") quotes its output.
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
from idas_sumo.agents.returns import lambda_targets
from idas_sumo.agents.rollout import ActionOverride, EpisodeData, RolloutTask, collect_episodes
from idas_sumo.env.actions import DELTA_ACCEL_MPS2, HARD_BRAKE
from idas_sumo.env.engine import MergeEngine
from idas_sumo.env.scenario import generate_scenario
from idas_sumo.resources import DEFAULT_NET_NAME, resolve_user_path
from idas_sumo.training.checkpoint import load_checkpoint
from idas_sumo.training.config import TrainConfig, load_train_config

KEEP_ACCEL = DELTA_ACCEL_MPS2.index(0.0)
ACTIONS = {
    "hard brake": HARD_BRAKE,
    "Δa=-0.2": DELTA_ACCEL_MPS2.index(-0.2),
    "Δa=0": KEEP_ACCEL,
    "Δa=+0.2": DELTA_ACCEL_MPS2.index(0.2),
}
BEFORE_COLLISION_STEPS = 10  # 2 s at 5 Hz
ACTION_SEED_BASE = 1000
CONTINUATION_SEED_BASE = 5000


@dataclasses.dataclass(frozen=True)
class _Point:
    """One decision replayed: scenario, agent, its decision index, its row in the reference episode."""

    scenario: int
    agent_id: str
    decision: int
    row: int
    before_collision: bool


def _correlations(x: npt.NDArray[np.float64], y: npt.NDArray[np.float64]) -> tuple[float, float]:
    """Pearson's and Spearman's (Pearson's of the ranks; the values are continuous) correlation."""
    if np.std(x) == 0 or np.std(y) == 0:
        return float("nan"), float("nan")
    rank = lambda v: np.argsort(np.argsort(v)).astype(np.float64)  # noqa: E731
    return float(np.corrcoef(x, y)[0, 1]), float(np.corrcoef(rank(x), rank(y))[0, 1])


def _returns(
    episode: EpisodeData, gamma: float, collision_price: float
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.bool_]]:
    """Per row: the discounted joint return along the agent's own steps, and whether the agent collides within
    ``BEFORE_COLLISION_STEPS`` of its own steps (its last reward at most ``collision_price``)."""
    n = len(episode)
    joint = torch.from_numpy(episode.joint_reward.astype(np.float64))
    next_row = torch.from_numpy(episode.next_row)
    # λ = 1 on one-step targets without a bootstrap: Σ_k γ^k r_(t+k) along the agent's rows.
    ret = lambda_targets(joint, torch.zeros(n, dtype=torch.float64), next_row, gamma, 1.0).numpy()
    # The same recursion with γ = 1 on ones counts the steps to the agent's end.
    to_end = lambda_targets(
        torch.ones(n, dtype=torch.float64), torch.zeros(n, dtype=torch.float64), next_row, 1.0, 1.0
    )
    last = (episode.next_row < 0) & (episode.done > 0) & (episode.reward <= collision_price + 1e-6)
    collides = np.isin(episode.slot, episode.slot[last])
    return ret, collides & (to_end.numpy() <= BEFORE_COLLISION_STEPS)


def _pick_points(
    episodes: list[EpisodeData],
    scenarios: list[list[str]],
    points: int,
    returns: list[tuple[npt.NDArray[np.float64], npt.NDArray[np.bool_]]],
    rng: np.random.Generator,
) -> list[_Point]:
    """``points`` decisions per episode with a real choice between a hard brake and Δa = 0; half before a
    collision where there are such."""
    out: list[_Point] = []
    for i, e in enumerate(episodes):
        mask = e.mask.astype(np.bool_)
        choice = mask[:, HARD_BRAKE] & mask[:, KEEP_ACCEL]
        before = returns[i][1]
        chosen: list[int] = []
        near = np.flatnonzero(choice & before)
        if len(near):
            chosen += rng.choice(near, size=min(points // 2, len(near)), replace=False).tolist()
        rest = np.setdiff1d(np.flatnonzero(choice), chosen)
        chosen += rng.choice(rest, size=min(points - len(chosen), len(rest)), replace=False).tolist()
        for row in chosen:
            slot = int(e.slot[row])
            decision = int(np.sum(e.slot[:row] == slot))
            out.append(_Point(i, scenarios[i][slot], decision, int(row), bool(before[row])))
    return out


def probe(
    config: TrainConfig,
    net: Path,
    checkpoint: Path,
    n_scenarios: int,
    points: int,
    continuations: int,
    seed: int,
    hold: int,
) -> None:
    learner_config = dataclasses.replace(config.learner, use_central_critic=True)
    learner = Learner(learner_config)
    learner.load_state_dict(load_checkpoint(checkpoint).learner, load_optimisers=False)
    gamma = learner_config.gamma
    collision_price = -5.0 * config.reward.collide_scale  # r_collide ≤ this; a finish reward is ≥ 5
    engine = MergeEngine(net, copies=16, config=config.env_config())
    rng = np.random.default_rng(seed)
    try:
        scenarios = [
            generate_scenario(rng, config.intelligent_traffic, engine.speed_limits_mps)
            for _ in range(n_scenarios)
        ]
        reference = collect_episodes(
            engine, learner, [RolloutTask(s, ACTION_SEED_BASE + i) for i, s in enumerate(scenarios)]
        )
        ids = [[v.id for v in s.vehicles] for s in scenarios]
        returns = [_returns(e, gamma, collision_price) for e in reference]
        chosen = _pick_points(reference, ids, points, returns, rng)
        tasks: list[RolloutTask] = []
        keys: list[tuple[int, int, int]] = []  # (point, action, continuation)
        for p, point in enumerate(chosen):
            allowed = reference[point.scenario].mask[point.row].astype(np.bool_)
            for a in ACTIONS.values():
                if not allowed[a]:
                    continue
                for c in range(continuations):
                    override = ActionOverride(
                        point.agent_id, point.decision, a, CONTINUATION_SEED_BASE + c, hold=hold
                    )
                    tasks.append(
                        RolloutTask(
                            scenarios[point.scenario], ACTION_SEED_BASE + point.scenario, override=override
                        )
                    )
                    keys.append((p, a, c))
        replays = collect_episodes(engine, learner, tasks)
    finally:
        engine.close()
    measured = np.full((len(chosen), max(ACTIONS.values()) + 1, continuations), np.nan)
    for (p, a, c), episode in zip(keys, replays, strict=True):
        row = chosen[p].row
        assert episode.action[row] == a, "the override reached its decision"
        past = reference[chosen[p].scenario].obs[: row + 1]
        assert np.array_equal(episode.obs[: row + 1], past), "a replay is its reference up to the decision"
        ret, _ = _returns(episode, gamma, collision_price)
        measured[p, a, c] = ret[row]
    rows = [reference[pt.scenario] for pt in chosen]
    state = torch.from_numpy(np.stack([e.state[pt.row] for e, pt in zip(rows, chosen, strict=True)]))
    others = torch.from_numpy(
        np.stack([e.others_actions[pt.row] for e, pt in zip(rows, chosen, strict=True)])
    )
    slot = torch.tensor([int(e.slot[pt.row]) for e, pt in zip(rows, chosen, strict=True)])
    with torch.no_grad():
        q = learner.central(state, others, slot).numpy().astype(np.float64)
    before = np.array([pt.before_collision for pt in chosen])
    print(
        f"{checkpoint}: {n_scenarios} scenarios, {len(chosen)} decisions ({before.sum()} before a collision), "
        f"{len(replays)} replays, each action held for {hold} decision(s)"
    )
    print("  action vs Δa=0          where          n  Q diff  measured  se  pearson  spearman  same sign %")
    for name, a in ACTIONS.items():
        if a == KEEP_ACCEL:
            continue
        diff = measured[:, a, :] - measured[:, KEEP_ACCEL, :]  # common random numbers: paired by continuation
        have = ~np.isnan(diff).any(axis=1)
        for where, sel in (("before collision", have & before), ("elsewhere", have & ~before), ("all", have)):
            if sel.sum() < 3:
                continue
            m = diff[sel].mean(axis=1)
            se = float(np.sqrt(np.mean(diff[sel].var(axis=1, ddof=1) / continuations)))
            qd = q[sel, a] - q[sel, KEEP_ACCEL]
            r, rho = _correlations(qd, m)
            print(
                f"  {name:10s}  {where:18s} {sel.sum():5d}  {qd.mean():6.2f}  {m.mean():8.2f}  {se:5.2f}"
                f"  {r:7.2f}  {rho:8.2f}  {100 * np.mean(np.sign(qd) == np.sign(m)):11.0f}"
            )


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("checkpoints", nargs="+", type=Path)
    parser.add_argument("--config", required=True, type=resolve_user_path, help="the runs' training config")
    parser.add_argument("--net", type=resolve_user_path, default=DEFAULT_NET_NAME)
    parser.add_argument("--scenarios", type=int, default=32)
    parser.add_argument("--points", type=int, default=4, help="decisions replayed per scenario")
    parser.add_argument("--continuations", type=int, default=4, help="continuation seeds per action")
    parser.add_argument("--seed", type=int, default=77, help="scenario seed (not an evaluation seed)")
    parser.add_argument(
        "--hold", type=int, default=1, help="decisions each replayed action is held for (1: COMA's one step)"
    )
    args = parser.parse_args()
    config = load_train_config(args.config)
    for checkpoint in args.checkpoints:
        probe(
            config,
            args.net,
            checkpoint,
            args.scenarios,
            args.points,
            args.continuations,
            args.seed,
            args.hold,
        )


if __name__ == "__main__":
    main()
