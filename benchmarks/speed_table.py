"""The speed story in one run and one table: SUMO alone, the environment, training, evaluation.

    python benchmarks/speed_table.py [--quick]

Rows, all measured in this one run (the machine is shared: compare rows of one run, not runs):

* **env step vs raw libsumo** at N = 8, 32, 128 and 512 vehicles (N/2 per road, every vehicle an agent,
  random allowed actions; N ≥ 128 on a generated net with 4 km roads so the queues fit). *raw*: the least
  any controller needs per step (``simulationStep``, the id list, four getters and one ``setSpeed`` per
  vehicle, ``env_throughput.run_raw``). *env*: one ``MergeParallelEnv.step`` (observations, masks and
  rewards of every agent, ``env_throughput.run_env``). *engine ×K*: the episode engine that training and
  evaluation use, running K copies of the N-vehicle world side by side in one SUMO (K·N ≈ 128 vehicles),
  timed over observe + observations + masks + step + rewards; its steps/s counts N-vehicle world-steps
  (K per SUMO step) so it compares with raw at the same N. Ratio = engine (or env) / raw.
* **training**: ``idas-sumo train`` (a real process, ``train_throughput.measure``) with the default config and
  ``--workers 2`` in the robot and the intelligent world, from random weights (200 episodes that run to the 60 s
  timeout: the slow case) and from the shipped ``idas.pt`` (2,000 episodes as long as a trained policy makes
  them), with the projected wall time of the paper's curriculum (20,000 robot + 50,000 intelligent episodes) at
  the trained pace.
* **paper evaluation**: ``idas-sumo evaluate --baseline all --suite paper --scenarios 100 --workers 2``.

``--quick`` shrinks every measurement (a smoke run of the script; its numbers are not worth quoting).
"""

from __future__ import annotations

import idas_sumo  # noqa: F401  (first: its OMP_WAIT_POLICY must be set before torch loads)

# isort: split
import argparse
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from rich.console import Console
from rich.table import Table

sys.path.insert(0, str(Path(__file__).resolve().parent))
from env_throughput import make_scenario, run_env, run_raw
from report import print_table
from train_throughput import measure as train_pace

from idas_sumo.env.engine import AgentBatch, MergeEngine
from idas_sumo.env.scenario import Scenario
from idas_sumo.resources import DEFAULT_NET, resolve_user_path
from idas_sumo.sim.netgen import MergeNet, NetParams, generate_net, read_merge_net

SIZES = (8, 32, 128, 512)
LONG_ROAD_M = 4000.0
VEHICLES_PER_SUMO_STEP = 128
"""The engine's copies are chosen so K·N is about this many vehicles per SUMO step."""
EPISODE_STEPS = 100
"""Steps before a reset (not timed); the cars stay clear of the merge point."""
SHIPPED_POLICY = "policies/idas.pt"
PAPER_ROBOT_EPISODES = 20_000
PAPER_INTELLIGENT_EPISODES = 50_000


@dataclass
class Timed:
    steps: int = 0
    seconds: float = 0.0
    vehicles: int = 0

    @property
    def steps_per_s(self) -> float:
        return self.steps / self.seconds if self.seconds > 0 else float("nan")


def run_engine(net: MergeNet, scenario: Scenario, copies: int, steps: int, seed: int) -> Timed:
    """K copies of the scenario on one engine; one timed step = observe, observations, masks, step."""
    rng = np.random.default_rng(seed)
    engine = MergeEngine(net, copies=copies, seed=seed)
    timed = Timed()
    perf = time.perf_counter
    try:
        while timed.steps < steps:
            engine.reset([scenario] * copies)
            for _ in range(EPISODE_STEPS):
                t0 = perf()
                batch: AgentBatch = engine.observe()
                _ = batch.obs  # the observations every learning policy reads
                elapsed = perf() - t0
                if not len(batch):
                    break
                scores = np.where(batch.masks.astype(bool), rng.random(batch.masks.shape) + 1e-9, -1.0)
                actions = np.argmax(scores, axis=1)  # a random allowed action (the draw is not timed)
                t0 = perf()
                engine.step(actions)
                timed.seconds += elapsed + perf() - t0
                timed.vehicles += len(engine.snapshot)
                timed.steps += copies  # K world-steps of N vehicles per SUMO step
                if timed.steps >= steps:
                    break
    finally:
        engine.close()
    return timed


def median_pace(runs: Sequence[Any]) -> float:
    """The median steps/s of repeated measurements (anything with ``steps_per_s``)."""
    return float(statistics.median(r.steps_per_s for r in runs))


def paper_eval_seconds(scenarios: int) -> float:
    with tempfile.TemporaryDirectory() as tmp:
        start = time.perf_counter()
        subprocess.run(
            [
                *(sys.executable, "-m", "idas_sumo.cli", "evaluate", "--baseline", "all", "--suite", "paper"),
                *("--scenarios", str(scenarios), "--workers", "2", "--out", str(Path(tmp) / "eval")),
            ],
            check=True,
            capture_output=True,
        )
        return time.perf_counter() - start


def _engine_rows(table: Table, console: Console, steps: int, repeats: int) -> None:
    """Raw libsumo, the one-world env and the engine at each N, interleaved repeats."""
    with tempfile.TemporaryDirectory(prefix="idas_speed_") as tmp:
        short = read_merge_net(DEFAULT_NET)
        long_path = generate_net(
            Path(tmp) / "long.net.xml", NetParams(main_length_m=LONG_ROAD_M, merge_length_m=LONG_ROAD_M)
        )
        long = read_merge_net(long_path)
        for n in SIZES:
            net = short if n <= 32 else long
            scenario = make_scenario(n, net, EPISODE_STEPS)
            copies = max(1, VEHICLES_PER_SUMO_STEP // n)
            console.print(f"[dim]N = {n}: raw, env, engine x{copies}...[/dim]")
            if n == SIZES[0]:  # compile the engine's numba kernels (or load them from numba's cache) untimed
                run_engine(net, scenario, copies, copies, seed=0)
            # Interleaved repeats, the median of each: the host is shared and its load drifts.
            raws, envs, engs = [], [], []
            for _ in range(repeats):
                raws.append(run_raw(net, scenario, steps, EPISODE_STEPS))
                envs.append(run_env(net, scenario, max(steps // 8, 20), EPISODE_STEPS, seed=0))
                engs.append(run_engine(net, scenario, copies, steps, seed=0))
            raw, env, eng = (median_pace(runs) for runs in (raws, envs, engs))
            raw_us = 1e6 / raw / n
            for label, measured in (
                ("env step (1 world)", env),
                (f"engine step x{copies}", eng),
            ):
                table.add_row(
                    label,
                    str(n),
                    f"{raw:,.0f} steps/s",
                    f"{measured:,.0f} steps/s",
                    f"{measured / raw:.2f}",
                    f"{raw_us:.1f} | {1e6 / measured / n:.1f}",
                )


def _training_rows(
    table: Table, console: Console, train_episodes: dict[str, int], eval_scenarios: int
) -> None:
    """Training paces, the paper curriculum projected from them, and the paper evaluation's wall time."""
    net_path = resolve_user_path("sumo_nets/tjunction.net.xml")
    pace: dict[str, float] = {}
    for stage in ("robot", "intelligent"):
        for label, init in (
            ("random weights", ""),
            ("from shipped idas.pt", str(resolve_user_path(SHIPPED_POLICY))),
        ):
            console.print(f"[dim]training, {stage} world, {label}...[/dim]")
            eps, agent_steps = train_pace(net_path, stage, 2, train_episodes[label], init)
            pace[f"{stage}/{label}"] = eps
            table.add_row(
                f"train, {label}, 2 workers, {train_episodes[label]} episodes",
                stage,
                "",
                f"{eps:.2f} episodes/s",
                "",
                f"{agent_steps:,.0f} agent-steps/s",
            )
    hours = (
        PAPER_ROBOT_EPISODES / pace["robot/from shipped idas.pt"]
        + PAPER_INTELLIGENT_EPISODES / pace["intelligent/from shipped idas.pt"]
    ) / 3600
    table.add_row(
        "paper curriculum (20k + 50k), projected",
        "train_default",
        "",
        f"{hours:.1f} h",
        "",
        "at the trained pace",
    )
    console.print("[dim]paper evaluation...[/dim]")
    seconds = paper_eval_seconds(eval_scenarios)
    table.add_row(
        f"paper evaluation, 5 methods x {eval_scenarios}",
        "paper suite",
        "",
        f"{seconds:.0f} s wall",
        "",
        "--workers 2",
    )


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--quick", action="store_true", help="tiny measurements: checks the script runs")
    args = parser.parse_args()
    steps = 60 if args.quick else 3000
    repeats = 1 if args.quick else 3
    # The bar is measured over at least 2,000 episodes of a trained policy; random weights are a
    # shorter look at the slow case (episodes run to the timeout).
    train_episodes = {
        "random weights": 8 if args.quick else 200,
        "from shipped idas.pt": 8 if args.quick else 2000,
    }
    eval_scenarios = 4 if args.quick else 100

    console = Console(width=150)
    table = Table(title="idas-sumo speed, one run (2-core machine; ratios are within this run)")
    for col in ("what", "N / world", "raw", "measured", "ratio", "µs per vehicle-step raw | measured"):
        table.add_column(col, justify="right")
    _engine_rows(table, console, steps, repeats)
    _training_rows(table, console, train_episodes, eval_scenarios)
    print_table(table, console)


if __name__ == "__main__":
    main()
