"""Rollout throughput of the Ray backend against the local worker processes, at the same worker count.

    python benchmarks/ray_backend.py [--workers 2] [--rounds 4] [--episodes 16] [--repeats 2]

Each measurement opens the rollout workers the training loop uses (``make_workers``: local processes,
or Ray actors on a Ray instance started here with ``--ray-address local``), runs one round to warm
them up (start-up is reported apart: it is paid once per run), then times ``--rounds`` rounds of
``--episodes`` robot-world episodes with an untrained actor, the weights sent out every round as in
training. Local and Ray alternate ``--repeats`` times (the machine's other jobs drift); the table
shows each backend's best, and the ratio Ray / local.
"""

from __future__ import annotations

import idas_sumo  # noqa: F401  (first: its OMP_WAIT_POLICY must be set before torch loads)

# isort: split
import argparse
import time
from pathlib import Path

import numpy as np
import torch
from report import print_table
from rich.table import Table

from idas_sumo.agents.learner import Learner
from idas_sumo.env.engine import EnvConfig
from idas_sumo.env.scenario import generate_scenario
from idas_sumo.resources import DEFAULT_NET_NAME, resolve_user_path
from idas_sumo.sim.merge_detect import choose_merge
from idas_sumo.sim.netgen import read_merge_net
from idas_sumo.training.config import TrainConfig
from idas_sumo.training.curriculum import plan_stages
from idas_sumo.training.workers import EpisodeTask, make_workers


def tasks_for(net: Path, rounds: int, episodes: int, seed: int = 0) -> list[list[EpisodeTask]]:
    """``rounds`` rounds of robot-world episodes, drawn as the training loop draws them."""
    merge = read_merge_net(net)
    limits = {"main": merge.main.speed_limit_mps, "merge": merge.merge.speed_limit_mps}
    plan = plan_stages(TrainConfig(stage="robot"))[0]
    rng, torch_rng = np.random.default_rng(seed), torch.Generator().manual_seed(seed)
    return [
        [
            EpisodeTask(
                scenario=generate_scenario(rng, plan.traffic, limits, name=f"bench-{r}-{i}"),  # type: ignore[arg-type]
                action_seed=int(torch.randint(0, 2**62, (1,), generator=torch_rng).item()),
            )
            for i in range(episodes)
        ]
        for r in range(rounds + 1)
    ]


def measure(
    net: Path, workers: int, rounds: list[list[EpisodeTask]], ray_address: str | None
) -> tuple[float, float]:
    """(start-up + first round seconds, episodes/s over the other rounds)."""
    config = TrainConfig()
    learner = Learner(plan_stages(config)[0].learner, seed=0)
    env_config = EnvConfig(max_episode_s=config.env.max_episode_s)
    start = time.perf_counter()
    with make_workers(
        choose_merge(net), env_config, 0, workers, config.copies, ray_address=ray_address
    ) as pool:
        pool.run(learner, rounds[0])
        warm = time.perf_counter()
        for tasks in rounds[1:]:
            pool.run(learner, tasks)
        done = time.perf_counter()
    episodes = sum(len(t) for t in rounds[1:])
    return warm - start, episodes / (done - warm)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--net", type=resolve_user_path, default=DEFAULT_NET_NAME)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--rounds", type=int, default=4, help="timed rounds per measurement")
    parser.add_argument("--episodes", type=int, default=16, help="episodes per round")
    parser.add_argument("--repeats", type=int, default=2, help="measurements per backend, alternating")
    args = parser.parse_args()

    rounds = tasks_for(args.net, args.rounds, args.episodes)
    best: dict[str, tuple[float, float]] = {}
    for _ in range(args.repeats):
        for name, address in (("local processes", None), ("Ray actors (local instance)", "local")):
            startup, pace = measure(args.net, args.workers, rounds, address)
            print(f"{name}: start-up + first round {startup:.1f} s, {pace:.2f} episodes/s")
            if name not in best or pace > best[name][1]:
                best[name] = (startup, pace)

    table = Table(
        title=f"rollout throughput, {args.workers} workers, {args.rounds} x {args.episodes} episodes"
    )
    for col in ("backend", "start-up + first round, s", "episodes/s (best)", "vs local"):
        table.add_column(col, justify="right")
    local = best["local processes"][1]
    for name, (startup, pace) in best.items():
        table.add_row(name, f"{startup:.1f}", f"{pace:.2f}", f"{pace / local:.1%}")
    print_table(table)


if __name__ == "__main__":
    main()
