"""make_vec's vector env against raw libsumo, and the single-world Gymnasium env, in one run.

    python benchmarks/vec_env.py [--repeats 3] [--steps 1500] [--quick] [--cpu] [--old TREE]

Rows, at N = 8 vehicles per world (K = 16 worlds in one SUMO) and N = 32 (K = 4):

* **raw libsumo**: steps/s of one N-vehicle simulation doing the least any controller needs per step
  (``simulationStep``, the id list, four getters and one ``setSpeed`` per vehicle; ``env_throughput.run_raw``).
* **make_vec**: world-steps/s of ``gymnasium.make_vec("idas_sumo/Merge-v0", num_envs=K,
  vectorization_mode="vector_entry_point")``: one ``step()`` of all K worlds counts K world-steps, and only
  worlds whose ego decides count (idle rows are not world-steps). Two worlds: *robots* (``others=None``: one
  ego, N - 1 SUMO-driven cars) and *all agents* (``others=`` a policy that keeps its acceleration: N agents,
  as in the raw row and the speed table's engine rows).
* **MergeEnv**: the single-world env's ``step()`` (one SUMO per world), the same two worlds.
* **MergeParallelEnv**: the PettingZoo env's ``step()``, one world, every car an agent
  (``env_throughput.run_env``: random allowed actions, drawn untimed).
* **engine alone**: the speed table's engine row (``speed_table.run_engine``: observe, every agent's
  observation, masks and step, no Gymnasium API), for what the vector env adds on top of it.

Every world runs ``env_throughput.make_scenario(N)`` (N/2 cars per road, equally spaced at 2.5 m/s, clear of
the merge for the episode) with the last car on the main road as the ego, which keeps its acceleration (action
2, or the first allowed one); episodes time out after ``EPISODE_STEPS``. Resets are not timed on any side (a
make_vec step that only starts the next wave is one). Ratio = measured / raw at the same N; the issue's target
is >= 0.5 for make_vec. Median of ``--repeats`` interleaved repeats.

``--cpu`` times with this process's CPU time instead of the wall clock: libsumo runs in the process, so both
count the same work, and on a machine shared with other jobs the CPU time swings far less. ``--old TREE`` adds
the rows an older checkout can run (the engine and the single-world envs), each in a child process that imports
``idas_sumo`` from TREE, interleaved with the others, and then times every row of this checkout in a fresh
child process too: e.g. ``git worktree add /tmp/base b744397`` and ``--old /tmp/base``.
"""

from __future__ import annotations

import os
import sys

if os.environ.get(_TREE_VAR := "IDAS_SUMO_BENCH_TREE"):  # a child timing an older checkout's code
    sys.path.insert(0, os.environ[_TREE_VAR])

import idas_sumo  # noqa: F401  (first: its OMP_WAIT_POLICY must be set before torch loads)

# isort: split
import argparse
import json
import statistics
import subprocess
import time
import types
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium
import numpy as np
import numpy.typing as npt
from rich.console import Console
from rich.table import Table

sys.path.insert(0, str(Path(__file__).resolve().parent))
from env_throughput import make_scenario, run_env, run_raw
from report import print_table

from idas_sumo.env.engine import AgentBatch, EnvConfig  # (names an older checkout has too)
from idas_sumo.env.gym_env import MergeEnv
from idas_sumo.env.scenario import Scenario
from idas_sumo.resources import DEFAULT_NET
from idas_sumo.sim.netgen import read_merge_net

IntArray = npt.NDArray[np.int64]
ROOT = Path(__file__).resolve().parents[1]
"""This checkout (what ``--old`` runs its own rows from)."""

CASES = ((8, 16), (32, 4))
"""(N vehicles per world, K worlds in the one SUMO)."""
EPISODE_STEPS = 100
KEEP = 2
"""The action that keeps the acceleration (Δa = 0)."""
EGO = "main0"
"""The last car on the main road: it stays clear of the merge for the episode."""


class KeepAcceleration:
    """``others=``: every other car keeps its acceleration (the engine's closest allowed action if masked)."""

    def act(self, batch: AgentBatch, rows: IntArray) -> IntArray:
        return np.full(len(rows), KEEP, dtype=np.int64)


@dataclass
class Timed:
    world_steps: int = 0
    seconds: float = 0.0

    @property
    def per_s(self) -> float:
        return self.world_steps / self.seconds if self.seconds > 0 else float("nan")


def _keep(masks: np.ndarray) -> np.ndarray:
    """Action KEEP where allowed, else each row's first allowed action."""
    return np.where(masks[:, KEEP], KEEP, np.argmax(masks, axis=1))


def _config() -> EnvConfig:
    return EnvConfig(max_episode_s=0.2 * (EPISODE_STEPS + 1))


def run_vec(scenario: Scenario, k: int, steps: int, others: Any) -> Timed:
    """make_vec with K worlds; ``steps`` world-steps timed (steps that only start a wave are not)."""
    envs = gymnasium.make_vec(
        "idas_sumo/Merge-v0",
        num_envs=k,
        vectorization_mode="vector_entry_point",
        scenario=scenario,
        ego=EGO,
        others=others,
        config=_config(),
    )
    timed = Timed()
    perf = time.perf_counter
    try:
        _, info = envs.reset(seed=0)
        decides = ~info["idle"]
        while timed.world_steps < steps:
            actions = _keep(envs.action_masks())
            t0 = perf()
            _, _, terminated, truncated, info = envs.step(actions)
            if decides.any():  # a step of the egos (else it only started the next wave: a reset)
                timed.seconds += perf() - t0
                timed.world_steps += int(decides.sum())
            decides = ~info["idle"] & ~(terminated | truncated)
    finally:
        envs.close()
    return timed


def run_single(scenario: Scenario, steps: int, others: Any) -> Timed:
    """MergeEnv.step (resets not timed)."""
    env = MergeEnv(scenario=scenario, ego=EGO, others=others, config=_config())
    timed = Timed()
    perf = time.perf_counter
    try:
        while timed.world_steps < steps:
            _, info = env.reset(seed=0)
            done = False
            while not done and timed.world_steps < steps:
                action = int(_keep(info["action_mask"][None].astype(bool))[0])
                t0 = perf()
                _, _, terminated, truncated, info = env.step(action)
                timed.seconds += perf() - t0
                timed.world_steps += 1
                done = terminated or truncated
    finally:
        env.close()
    return timed


def _runs(scenario: Scenario, n: int, k: int, steps: int) -> dict[str, Any]:
    """Each row's measurement (steps/s) at N = n, K = k."""
    from speed_table import run_engine

    net = read_merge_net(DEFAULT_NET)
    return {
        "raw": lambda: run_raw(net, scenario, steps, EPISODE_STEPS).steps_per_s,
        "engine": lambda: run_engine(net, scenario, k, steps, seed=0).steps_per_s,
        "vec robots": lambda: run_vec(scenario, k, steps, None).per_s,
        "vec all": lambda: run_vec(scenario, k, steps, KeepAcceleration()).per_s,
        "single robots": lambda: run_single(scenario, steps // 4, None).per_s,
        "single all": lambda: run_single(scenario, steps // 4, KeepAcceleration()).per_s,
        "parallel": lambda: run_env(net, scenario, steps // 4, EPISODE_STEPS, seed=0).steps_per_s,
    }


OLD_ROWS = ("engine", "single robots", "single all", "parallel")
"""The rows an older checkout runs (it may have no vector env)."""


def _in_child(tree: Path, row: str, n: int, k: int, steps: int, cpu: bool) -> float:
    """One row timed on the code of ``tree`` in a fresh child process (its numba kernels warmed up first)."""
    args = [sys.executable, __file__, "--child", json.dumps([row, n, k, steps])] + (["--cpu"] if cpu else [])
    env = {**os.environ, _TREE_VAR: str(tree)}
    done = subprocess.run(args, env=env, capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise SystemExit(f"{row!r} at N = {n} on {tree} failed:\n{done.stderr[-2000:]}")
    return float(done.stdout.strip().splitlines()[-1])


def child(spec: str) -> int:
    """``--child``: time one row (steps/s on the last line), after a short warm-up run of it."""
    row, n, k, steps = json.loads(spec)
    # speed_table's training rows import what an older checkout may lack; the engine row needs none of it.
    sys.modules.setdefault("train_throughput", types.SimpleNamespace(measure=None))  # type: ignore[arg-type]
    scenario = make_scenario(n, read_merge_net(DEFAULT_NET), EPISODE_STEPS)
    _runs(scenario, n, k, 40)[row]()
    print(_runs(scenario, n, k, steps)[row]())
    return 0


def measure(repeats: int, steps: int, old: Path | None, cpu: bool) -> dict[tuple[str, int], list[float]]:
    """Steps/s per (row, N), each repeat interleaving every row. With ``old`` every row runs in a fresh
    child process, this checkout's and the older one's alike (``old ...``), so that neither side inherits
    the other's process."""
    net = read_merge_net(DEFAULT_NET)
    rates: dict[tuple[str, int], list[float]] = {}
    for _ in range(repeats):
        for n, k in CASES:
            scenario = make_scenario(n, net, EPISODE_STEPS)
            for name, run in _runs(scenario, n, k, steps).items():
                if old is None:
                    rates.setdefault((name, n), []).append(run())
                    continue
                rates.setdefault((name, n), []).append(_in_child(ROOT, name, n, k, steps, cpu))
                if name in OLD_ROWS:
                    rates.setdefault((f"old {name}", n), []).append(_in_child(old, name, n, k, steps, cpu))
    return rates


ROWS = (
    ("raw", "raw libsumo (step, 4 getters, setSpeed per car)"),
    ("engine", "episode engine alone, K worlds, all agents (speed table)"),
    ("vec robots", "make_vec, K worlds in one SUMO, robots (1 ego/world)"),
    ("vec all", "make_vec, K worlds in one SUMO, all cars agents"),
    ("single robots", "MergeEnv (one SUMO per world), robots"),
    ("single all", "MergeEnv (one SUMO per world), all cars agents"),
    ("parallel", "MergeParallelEnv (PettingZoo, one world), all agents"),
)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--steps", type=int, default=1500, help="timed world-steps per run (default: 1500)")
    parser.add_argument("--quick", action="store_true", help="1 repeat of 200 steps: a smoke run")
    parser.add_argument("--cpu", action="store_true", help="time with this process's CPU time (see above)")
    parser.add_argument(
        "--old", type=Path, default=None, help="also time an older checkout's code (see above)"
    )
    parser.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.cpu:  # every timer of the benchmark functions reads time.perf_counter when it runs
        time.perf_counter = time.process_time
    if args.child is not None:
        return child(args.child)
    repeats, steps = (1, 200) if args.quick else (args.repeats, args.steps)
    # The numba kernels compile (or load from the cache) before anything is timed.
    run_vec(make_scenario(8, read_merge_net(DEFAULT_NET), EPISODE_STEPS), 2, 20, None)
    rates = measure(repeats, steps, args.old, args.cpu)
    clock = "CPU time" if args.cpu else "wall clock"
    table = Table(
        title=f"make_vec against raw libsumo ({clock}, median of {repeats}, {steps} world-steps per run)"
    )
    table.add_column("what")
    for n, k in CASES:
        table.add_column(f"N = {n} (K = {k}) steps/s", justify="right")
        table.add_column("ratio", justify="right")
    rows = list(ROWS)
    if args.old is not None:
        rows += [(f"old {key}", f"{label}, old code") for key, label in ROWS if key in OLD_ROWS]
    for key, label in rows:
        cells = [label]
        for n, _ in CASES:
            rate = statistics.median(rates[(key, n)])
            raw = statistics.median(rates[("raw", n)])
            cells += [f"{rate:,.0f}", f"{rate / raw:.2f}"]
        table.add_row(*cells)
    print_table(table, Console(width=150))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
