"""Training throughput: episodes/s and agent-steps/s per stage and worker count, and what the
paper's budgets would take at that pace; or this code against an older checkout, interleaved.

    python benchmarks/train_throughput.py [--episodes 16] [--workers 1 2] [--net sumo_nets/tjunction.net.xml]
    python benchmarks/train_throughput.py --against /path/to/old/checkout [--episodes 320] [--random-episodes 64]
        [--workers 1 2] [--repeats 2]

Each measurement is a real ``idas-sumo train`` process (collection + learner updates + metrics)
with the default config, full 60 s episodes. Without ``--against``: an untrained policy (which tends to dawdle
until the timeout, so episodes are long: a pessimistic pace for later training), per stage.

With ``--against``: the intelligent world (stage 2, 8 learning agents), from the shipped ``idas.pt`` and from
random weights, each worker count, old code (the checkout, run with ``PYTHONPATH`` pointing at it, same
interpreter and packages) and this code, interleaved (old, new, new, old, ...) so both see the shared
machine's load alike. Both read the same config file and start from the same ``idas.pt``: the older checkout's
shipped one, which both codes read (a policy shipped later may carry config keys the older code refuses). Each cell prints the
episodes/s of every repeat (by the run's own clock, which starts after the command's imports) and the CPU
seconds per episode (the train process and its workers), the ratio is new over old of the medians; the last
column is the whole command's wall time (interpreter start and imports included).
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import re
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

from report import print_table
from rich.table import Table

from idas_sumo.config import MAX_EPISODES
from idas_sumo.resources import DEFAULT_NET_NAME, DEFAULT_TRAIN_CONFIG, POLICY_DIR, resolve_user_path
from idas_sumo.training.config import TrainConfig

HERE = Path(__file__).resolve().parents[1]


@dataclass(frozen=True)
class Pace:
    """One ``idas-sumo train`` run: by its own clock, and the CPU its processes used."""

    episodes_per_s: float
    agent_steps_per_s: float
    cpu_s_per_episode: float
    command_s: float = 0.0
    """The whole command, interpreter start and imports included (the run's own clock starts after them)."""


def _config_text(init_from: str) -> str:
    """The shipped default config with ``init_from``, no checkpoint within a measurement, and ``workers`` as
    a number any version reads (the flag sets it)."""
    default = DEFAULT_TRAIN_CONFIG.read_text(encoding="utf-8")
    default = re.sub(r"(?m)^workers = \d+", "workers = 1", default)
    # q_horizon is newer than the baselines: both sides run the old code's Q target ("agent"), which the old
    # code takes as given and the new one is told.
    default = re.sub(r"(?m)^q_horizon = .*\n", "", default)
    return default.replace('init_from = ""', f"init_from = {json.dumps(init_from)}").replace(
        "checkpoint_every = 1000",
        f"checkpoint_every = {MAX_EPISODES}",  # never within a measurement
    )


def run_train(
    net: Path, stage: str, workers: int, episodes: int, init_from: str = "", code: Path | None = None
) -> Pace:
    """One ``idas-sumo train`` run with the default config, timed by the run's own clock (``wall_time_s`` of its
    last metrics row: worker start-up included, interpreter start-up not). ``code``: a checkout whose
    ``idas_sumo`` runs instead of this one's.

    The run is a real ``idas-sumo`` process, as a user starts it, not ``run_training`` in this one: this
    script imports torch before idas_sumo, and torch's OpenMP threads then spin instead of sleeping
    (``idas_sumo/__init__.py``), which slowed the learner down beside any other job.
    ``init_from``: the checkpoint to start from (empty: random weights).
    """
    env = dict(os.environ)
    if code is not None:
        env["PYTHONPATH"] = os.pathsep.join([str(code), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    with tempfile.TemporaryDirectory() as tmp:
        toml = Path(tmp) / "config.toml"
        text = _config_text(init_from)
        if code is not None and Path(code).resolve() == HERE:  # the new side of --against
            text = text.replace("[learner]\n", '[learner]\nq_horizon = "agent"\n', 1)
        toml.write_text(text, encoding="utf-8")
        run = Path(tmp) / "run"
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        started = time.perf_counter()
        subprocess.run(
            [
                *(sys.executable, "-m", "idas_sumo.cli", "train", "--net", str(net), "--config", str(toml)),
                *("--stage", stage, "--episodes", str(episodes), "--workers", str(workers)),
                *("--no-progress", "--out", str(run)),
            ],
            check=True,
            capture_output=True,
            env=env,
            cwd=tmp,
        )
        command_s = time.perf_counter() - started
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        with (run / "metrics.csv").open(newline="") as f:
            rows = list(csv.DictReader(f))
    wall = float(rows[-1]["wall_time_s"])
    steps = sum(int(r["agent_steps"]) for r in rows)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return Pace(len(rows) / wall, steps / wall, cpu / len(rows), command_s)


def measure(net: Path, stage: str, workers: int, episodes: int, init_from: str = "") -> tuple[float, float]:
    """(episodes/s, agent-steps/s) of one ``idas-sumo train`` run of this code (``run_train``)."""
    pace = run_train(net, stage, workers, episodes, init_from)
    return pace.episodes_per_s, pace.agent_steps_per_s


def _per_stage(args: argparse.Namespace) -> None:
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


def _shipped_of(checkout: Path) -> Path:
    """The ``idas.pt`` shipped with ``checkout`` (both sides start from it), or this code's if it has none."""
    theirs = checkout / "idas_sumo" / "policies" / "idas.pt"
    return theirs if theirs.is_file() else POLICY_DIR / "idas.pt"


def _against(args: argparse.Namespace) -> None:
    """Old (``--against``) and new, interleaved, intelligent world, shipped policy and random weights."""
    shipped = str(_shipped_of(args.against))
    starts = (("idas.pt", shipped, args.episodes), ("random weights", "", args.random_episodes))
    paces: dict[tuple[str, int, str], list[Pace]] = {}
    for code in (
        args.against,
        HERE,
    ):  # untimed: numba compiles (or loads its cache) on a checkout's first run
        run_train(args.net, "intelligent", max(args.workers), 16, shipped, code)
    for rep in range(args.repeats):
        for label, init, episodes in starts:
            for w in args.workers:
                order = ("old", "new") if rep % 2 == 0 else ("new", "old")
                for who in order:
                    code = args.against if who == "old" else HERE
                    pace = run_train(args.net, "intelligent", w, episodes, init, code)
                    paces.setdefault((label, w, who), []).append(pace)
                    print(
                        f"{label}, {w} worker(s), {who}: {pace.episodes_per_s:.2f} episodes/s, "
                        f"{pace.cpu_s_per_episode:.3f} CPU s/episode, the command {pace.command_s:.1f} s",
                        flush=True,
                    )
    table = Table(title=f"idas-sumo train, intelligent world: {args.against} (old) against this code (new)")
    for col in (
        "start",
        "episodes",
        "workers",
        "old episodes/s",
        "new episodes/s",
        "ratio",
        "CPU s/ep old | new",
        "command s old | new",
    ):
        table.add_column(col, justify="right")
    for label, _, episodes in starts:
        for w in args.workers:
            old, new = paces[(label, w, "old")], paces[(label, w, "new")]

            def eps(ps: list[Pace]) -> str:
                return ", ".join(f"{p.episodes_per_s:.2f}" for p in ps)

            ratio = statistics.median(p.episodes_per_s for p in new) / statistics.median(
                p.episodes_per_s for p in old
            )
            cpu = " | ".join(f"{statistics.median(p.cpu_s_per_episode for p in ps):.3f}" for ps in (old, new))
            command = " | ".join(f"{statistics.median(p.command_s for p in ps):.1f}" for ps in (old, new))
            table.add_row(label, str(episodes), str(w), eps(old), eps(new), f"{ratio:.2f}x", cpu, command)
    print_table(table)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--net", type=resolve_user_path, default=DEFAULT_NET_NAME)
    parser.add_argument("--episodes", type=int, default=16, help="episodes per measurement")
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    parser.add_argument(
        "--against",
        type=Path,
        help="a checkout of older code to compare with (e.g. a git worktree of b744397)",
    )
    parser.add_argument(
        "--random-episodes", type=int, default=64, help="with --against: episodes from random weights"
    )
    parser.add_argument("--repeats", type=int, default=2, help="with --against: interleaved pairs per cell")
    args = parser.parse_args()
    if args.against is None:
        _per_stage(args)
    else:
        _against(args)


if __name__ == "__main__":
    main()
