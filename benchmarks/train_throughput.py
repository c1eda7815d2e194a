"""Training throughput: episodes/s and agent-steps/s per stage and worker count, and what the
paper's budgets would take at that pace.

    python benchmarks/train_throughput.py [--episodes 16] [--workers 1 2] [--net sumo_nets/tjunction.net.xml]

Each measurement is a real ``idas-sumo train`` process (collection + learner updates + metrics)
with the default config, full 60 s episodes, and an untrained policy (which tends to dawdle until the
timeout, so episodes are long: a pessimistic pace for later training).
"""

from __future__ import annotations

import argparse
import csv
import json
import subprocess
import sys
import tempfile
from pathlib import Path

from report import print_table
from rich.table import Table

from idas_sumo.config import MAX_EPISODES
from idas_sumo.resources import DEFAULT_NET_NAME, DEFAULT_TRAIN_CONFIG, resolve_user_path
from idas_sumo.training.config import TrainConfig


def measure(net: Path, stage: str, workers: int, episodes: int, init_from: str = "") -> tuple[float, float]:
    """(episodes/s, agent-steps/s) of one ``idas-sumo train`` run with the default config, timed by the run's
    own clock (``wall_time_s`` of its last metrics row: worker start-up included, interpreter start-up not).

    The run is a real ``idas-sumo`` process, as a user starts it, not ``run_training`` in this one: this
    script imports torch before idas_sumo, and torch's OpenMP threads then spin instead of sleeping
    (``idas_sumo/__init__.py``), which slowed the learner down beside any other job.
    ``init_from``: the checkpoint to start from (empty: random weights).
    """
    default = DEFAULT_TRAIN_CONFIG.read_text(encoding="utf-8")
    config = default.replace('init_from = ""', f"init_from = {json.dumps(init_from)}").replace(
        "checkpoint_every = 1000",
        f"checkpoint_every = {MAX_EPISODES}",  # never within a measurement
    )
    with tempfile.TemporaryDirectory() as tmp:
        toml = Path(tmp) / "config.toml"
        toml.write_text(config, encoding="utf-8")
        run = Path(tmp) / "run"
        subprocess.run(
            [
                *(sys.executable, "-m", "idas_sumo.cli", "train", "--net", str(net), "--config", str(toml)),
                *("--stage", stage, "--episodes", str(episodes), "--workers", str(workers)),
                *("--no-progress", "--out", str(run)),
            ],
            check=True,
            capture_output=True,
        )
        with (run / "metrics.csv").open(newline="") as f:
            rows = list(csv.DictReader(f))
    wall = float(rows[-1]["wall_time_s"])
    steps = sum(int(r["agent_steps"]) for r in rows)
    return len(rows) / wall, steps / wall


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
    print_table(table)


if __name__ == "__main__":
    main()
