"""Training throughput: episodes/s and agent-steps/s per stage and worker count, and what the
paper's budgets would take at that pace.

    python benchmarks/train_throughput.py [--episodes 16] [--workers 1 2] [--net sumo_nets/tjunction.net.xml]

Each measurement is a real ``run_training`` (collection + learner updates + metrics + checkpoints)
with the default config, full 60 s episodes, and an untrained policy (which tends to dawdle until the
timeout, so episodes are long: a pessimistic pace for later training).
"""

from __future__ import annotations

import argparse
import csv
import os
import tempfile
import time
from pathlib import Path

from rich.console import Console
from rich.table import Table

from idas_sumo.resources import DEFAULT_NET_NAME, resolve_user_path
from idas_sumo.training.config import TrainConfig
from idas_sumo.training.loop import run_training


def measure(net: Path, stage: str, workers: int, episodes: int, init_from: str = "") -> tuple[float, float]:
    """(episodes/s, agent-steps/s) of one short run, start-up of workers included; ``init_from``: the
    checkpoint to start from (empty: random weights)."""
    config = TrainConfig(stage=stage, checkpoint_every=10**9, init_from=init_from).with_overrides(
        episodes=episodes, workers=workers
    )  # type: ignore[arg-type]
    with tempfile.TemporaryDirectory() as tmp:
        start = time.perf_counter()
        run_training(net, config, Path(tmp) / "run", progress=False)
        wall = time.perf_counter() - start
        with (Path(tmp) / "run" / "metrics.csv").open(newline="") as f:
            steps = sum(int(r["agent_steps"]) for r in csv.DictReader(f))
    return episodes / wall, steps / wall


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--net", type=resolve_user_path, default=DEFAULT_NET_NAME)
    parser.add_argument("--episodes", type=int, default=16, help="episodes per measurement")
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    args = parser.parse_args()

    paper = TrainConfig()
    table = Table(title=f"training throughput ({args.episodes} episodes per run, default config)")
    for col in ("stage", "workers", "episodes/s", "agent-steps/s", "paper budget", "projected hours"):
        table.add_column(col, justify="right")
    pace: dict[tuple[str, int], float] = {}
    for stage, budget in (("robot", paper.robot_episodes), ("intelligent", paper.intelligent_episodes)):
        for w in args.workers:
            eps, steps = measure(args.net, stage, w, args.episodes)
            pace[(stage, w)] = eps
            table.add_row(
                stage, str(w), f"{eps:.2f}", f"{steps:.0f}", str(budget), f"{budget / eps / 3600:.1f}"
            )
    for w in args.workers:
        hours = (
            paper.robot_episodes / pace[("robot", w)] + paper.intelligent_episodes / pace[("intelligent", w)]
        ) / 3600
        table.add_row("curriculum (70k)", str(w), "", "", "70000", f"{hours:.1f}")
    console = Console()
    console.print(table)
    console.print(
        f"load average after (1 min): {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores (others' jobs skew it)"
    )


if __name__ == "__main__":
    main()
