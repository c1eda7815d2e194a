"""How fast ``idas-sumo cosim`` runs: one simulated hour at 1,800 veh/h, every car automated, vs plain SUMO.

On the shipped T-junction, main 1,200 + merge 600 veh/h (SUMO's seed 0), one run each, one after the
other in this process:

* plain SUMO: the ``sumo`` binary on the run's own config at p = 0 (a subprocess; its start and net
  loading included), no idas-sumo in the loop;
* p = 0 through the co-simulation loop (libsumo; the loop reads every car each step and commands none);
* p = 1 with the IDM policy, and with the shipped IDAS (one batched forward pass per step for all
  automated cars, one torch thread), each car driven with the engine's observation and masks.

Each row: the run's wall seconds and real-time factor (simulated s / wall s), its CPU seconds (this
process's, or the sumo child's) and simulated s per CPU s, cars inserted, throughput past the merge and
collisions. A run is timed from SUMO's start to its close: not the statistics' reading, loading the
policy or the numba kernels' first load (an untimed 20 s warm-up run does that). One run each on a
shared machine: wall figures move with the load (printed first); the CPU figures are the steadier ones.

Run:  python benchmarks/cosim_speed.py [--duration-s 3600] [--seed 0]
"""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import tempfile
import time
from pathlib import Path

from idas_sumo.baselines.policies import RuleBasedPolicy
from idas_sumo.cosim.run import simulate
from idas_sumo.cosim.stats import EngineCounts, read_loops, read_statistics, run_row
from idas_sumo.env.contracts import Policy
from idas_sumo.evaluation.policies import resolve_policy
from idas_sumo.resources import DEFAULT_NET
from idas_sumo.sim.flows import FlowDemand, run_plain_sumo, write_run_files
from idas_sumo.sim.merge_detect import as_site

DEMAND = {"main": 1200.0, "merge": 600.0}


def _row(
    name: str, wall_s: float, cpu_s: float, duration_s: float, folder: Path, counts: EngineCounts | None
) -> str:
    stats = read_statistics(folder)
    if counts is not None:
        row = run_row(folder, counts, duration_s)
        through, collisions = row["throughput_veh_per_h"], row["collisions"]
    else:
        through = sum(read_loops(folder, duration_s, 1)) * 3600.0 / duration_s
        collisions = stats["collisions"]
    return (
        f"{name:24s} {wall_s:8.1f} {duration_s / wall_s:10.0f}x {cpu_s:7.1f} {duration_s / cpu_s:10.0f}x "
        f"{stats['inserted']:8d} "
        f"{through:10.0f} {collisions:10d}"
    )


def _children_cpu_s() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration-s", type=float, default=3600.0)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    site = as_site(DEFAULT_NET)
    duration = float(args.duration_s)
    print(f"load average {os.getloadavg()[0]:.2f}; {duration:g} s simulated, main 1200 + merge 600 veh/h")
    print(
        f"{'run':24s} {'wall s':>8s} {'real time':>11s} {'CPU s':>7s} {'per CPU s':>11s} {'inserted':>8s} "
        f"{'veh/h out':>10s} {'collisions':>10s}"
    )
    policies: list[tuple[str, float, Policy | None]] = [
        ("p=0, cosim loop", 0.0, None),
        ("p=1, IDM", 1.0, RuleBasedPolicy("idm")),
        ("p=1, IDAS", 1.0, resolve_policy("idas")),
    ]
    with tempfile.TemporaryDirectory(prefix="cosim_speed_") as tmp:
        # Untimed: the numba kernels of the snapshot, masks and policies load (or compile) on first use.
        simulate(site, FlowDemand(DEMAND, 1.0, 20.0, args.seed, 20.0), policies[1][2], Path(tmp) / "warm")
        plain = Path(tmp) / "plain"
        config = write_run_files(site, FlowDemand(DEMAND, 0.0, duration, args.seed, duration), plain)
        start, cpu = time.perf_counter(), _children_cpu_s()
        run_plain_sumo(config)
        wall, cpu = time.perf_counter() - start, _children_cpu_s() - cpu
        print(_row("plain SUMO (sumo binary)", wall, cpu, duration, plain, None))
        for name, p, policy in policies:
            folder = Path(tmp) / name.replace(" ", "").replace(",", "_").replace("=", "")
            start, cpu = time.perf_counter(), time.process_time()
            counts = simulate(site, FlowDemand(DEMAND, p, duration, args.seed, duration), policy, folder)
            wall, cpu = time.perf_counter() - start, time.process_time() - cpu
            print(_row(name, wall, cpu, duration, folder, counts))
            shutil.rmtree(folder, ignore_errors=True)


if __name__ == "__main__":
    main()
