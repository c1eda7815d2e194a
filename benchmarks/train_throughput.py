"""Training throughput: episodes/s and agent-steps/s per stage and worker count, and what the
paper's budgets would take at that pace.

    python benchmarks/train_throughput.py [--episodes 16] [--workers 1 2] [--net sumo_nets/tjunction.net.xml]
    python benchmarks/train_throughput.py --compare-serial [--episodes 1000] [--repeats 2] [--workers 2]

Each measurement is a real ``idas-sumo train`` process (collection + learner updates + metrics)
with the default config, full 60 s episodes, and an untrained policy (which tends to dawdle until the
timeout, so episodes are long: a pessimistic pace for later training).

``--compare-serial``: the intelligent world from the shipped ``idas.pt`` (``--workers``, first value),
each run twice in turn, ``--repeats`` times (serial, overlapped, serial, overlapped, ...): *serial* is
what ``idas-sumo train`` does (the critics step before the update returns), *overlapped* the same run with
``IDAS_SUMO_OVERLAP_UPDATE=1`` (a round's critics step in a thread while the workers collect the next
round). The two give the same weights and metrics bit for bit (tests/test_overlap.py); only the time
differs. Prints each run and the ratio of the summed paces.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

from report import print_table
from rich.table import Table

from idas_sumo.resources import DEFAULT_NET_NAME, DEFAULT_TRAIN_CONFIG, POLICY_DIR, resolve_user_path
from idas_sumo.training.config import TrainConfig
from idas_sumo.training.loop import OVERLAP_UPDATE_ENV


def measure(
    net: Path, stage: str, workers: int, episodes: int, init_from: str = "", overlap: bool = False
) -> tuple[float, float]:
    """(episodes/s, agent-steps/s) of one ``idas-sumo train`` run with the default config, timed by the run's
    own clock (``wall_time_s`` of its last metrics row: worker start-up included, interpreter start-up not).

    The run is a real ``idas-sumo`` process, as a user starts it, not ``run_training`` in this one: this
    script imports torch before idas_sumo, and torch's OpenMP threads then spin instead of sleeping
    (``idas_sumo/__init__.py``), which made the learner up to 10x slower here beside any other job.
    ``init_from``: the checkpoint to start from (empty: random weights). ``overlap``: the learner's critics step
    beside the next collection (``OVERLAP_UPDATE_ENV``), not before the update returns as ``idas-sumo train``
    does by default.
    """
    default = DEFAULT_TRAIN_CONFIG.read_text(encoding="utf-8")
    config = default.replace('init_from = ""', f"init_from = {json.dumps(init_from)}").replace(
        "checkpoint_every = 1000", f"checkpoint_every = {10**9}"
    )
    with tempfile.TemporaryDirectory() as tmp:
        toml = Path(tmp) / "config.toml"
        toml.write_text(config, encoding="utf-8")
        run = Path(tmp) / "run"
        env = {k: v for k, v in os.environ.items() if k != OVERLAP_UPDATE_ENV}
        if overlap:
            env[OVERLAP_UPDATE_ENV] = "1"
        subprocess.run(
            [
                *(sys.executable, "-m", "idas_sumo.cli", "train", "--net", str(net), "--config", str(toml)),
                *("--stage", stage, "--episodes", str(episodes), "--workers", str(workers)),
                *("--no-progress", "--out", str(run)),
            ],
            check=True,
            capture_output=True,
            env=env,
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
    parser.add_argument(
        "--compare-serial",
        action="store_true",
        help="serial against overlapped learner updates, intelligent world, from the shipped idas.pt",
    )
    parser.add_argument("--repeats", type=int, default=2, help="with --compare-serial: pairs of runs")
    args = parser.parse_args()
    if args.compare_serial:
        compare_serial(args.net, args.workers[0], args.episodes, args.repeats)
        return

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


def compare_serial(net: Path, workers: int, episodes: int, repeats: int) -> None:
    """Serial and overlapped updates, alternated in one run (the machine's load drifts: pairs see the same)."""
    init = str(POLICY_DIR / "idas.pt")
    table = Table(
        title=f"learner update serial vs overlapped: intelligent world from idas.pt, {workers} workers, "
        f"{episodes} episodes per run"
    )
    for col in ("run", "update", "episodes/s", "agent-steps/s"):
        table.add_column(col, justify="right")
    paces: dict[bool, list[float]] = {True: [], False: []}
    for r in range(repeats):
        for serial in (True, False):
            eps, steps = measure(net, "intelligent", workers, episodes, init, overlap=not serial)
            paces[serial].append(eps)
            table.add_row(str(r + 1), "serial" if serial else "overlapped", f"{eps:.2f}", f"{steps:.0f}")
    ratio = sum(paces[False]) / sum(paces[True])
    table.add_row("all", "overlapped / serial", f"{ratio:.3f}", "")
    print_table(table)


if __name__ == "__main__":
    main()
