"""Throughput of the multi-agent environment against raw libsumo on the same scenario.

For N = 8, 16, 32 vehicles on the default net and N = 64 on a generated net with 1000 m roads, this
measures, interleaved and repeated (median of repeats, the machine may be noisy):

* raw: steps/s of the least work any controller needs per step — ``libsumo.simulationStep()``, the id
  list, four getters per vehicle (road, lane position, speed, acceleration) and one ``setSpeed`` per
  vehicle;
* env: steps/s of ``MergeParallelEnv.step`` with every vehicle an agent, random actions drawn among the
  allowed ones of each agent's action mask (the draw itself is not timed), observations and masks built
  every step as the env always does.

Both sides load the same scenario through the same SUMO options (``SumoBackend``): N/2 vehicles on each
road, equally spaced and at the same speed, short episodes so nobody reaches the merge point. Resets
(loading SUMO, the insertion step, the env's first observation) are not timed. The table also shows the
mean number of vehicles per step and the collisions on each side, so a reader can check both sides
really simulated the same traffic. Ratio = env steps/s / raw steps/s (target >= 0.5).

Run:  python benchmarks/env_throughput.py [--repeats 5] [--steps 300]
"""

from __future__ import annotations

import argparse
import cProfile
import io
import pstats
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from idas_sumo.env.parallel import MergeParallelEnv  # noqa: E402
from idas_sumo.env.scenario import ROADS, Scenario, VehicleSpec  # noqa: E402
from idas_sumo.resources import DEFAULT_NET  # noqa: E402
from idas_sumo.sim.backend import SumoBackend  # noqa: E402
from idas_sumo.sim.netgen import MergeNet, NetParams, generate_net, read_merge_net  # noqa: E402

TARGET_RATIO = 0.5
PITCH_M = 12.0
"""Front-to-front spacing on each road: a 7 m gap, more than IDM's desired gap at the start speed."""
SPEED_MPS = 2.5
"""Start speed of every vehicle (and the raw side's constant speed command)."""
FIRST_POS_M = 5.0
MERGE_MARGIN_M = 5.0


@dataclass(frozen=True)
class Case:
    n: int
    net_label: str
    net: MergeNet


@dataclass
class RunResult:
    steps: int
    seconds: float
    vehicles: int
    """Vehicles in the simulation, summed over the timed steps."""
    collisions: int

    @property
    def steps_per_s(self) -> float:
        return self.steps / self.seconds if self.seconds > 0 else float("nan")

    @property
    def mean_vehicles(self) -> float:
        return self.vehicles / self.steps if self.steps else float("nan")


def make_scenario(n: int, net: MergeNet, episode_steps: int) -> Scenario:
    """N/2 vehicles per road, equally spaced from the road start, all at SPEED_MPS, all controlled."""
    if n % 2:
        raise SystemExit(f"N must be even (half on each road), got {n}")
    per_road = n // 2
    front = FIRST_POS_M + (per_road - 1) * PITCH_M
    travel = SPEED_MPS * episode_steps * 0.2
    shortest = min(net.main.length_m, net.merge.length_m)
    if front + travel > shortest - MERGE_MARGIN_M:
        raise SystemExit(
            f"N={n}: the front car would reach the merge point within {episode_steps} steps on {net.path.name} "
            f"(front at {front:.0f} m + {travel:.0f} m of travel > {shortest:.0f} m road); "
            "use a smaller --episode-steps or N"
        )
    vehicles = [
        VehicleSpec(
            id=f"{road}{i}", road=road, start_pos_m=FIRST_POS_M + i * PITCH_M, speed_mps=SPEED_MPS, b_type=0.0
        )
        for road in ROADS
        for i in range(per_road)
    ]
    return Scenario(name=f"bench{n}", vehicles=tuple(vehicles))


def run_raw(net: MergeNet, scenario: Scenario, steps: int, episode_steps: int) -> RunResult:
    """Raw libsumo: simulationStep + 4 getters + setSpeed per vehicle (reset not timed)."""
    import libsumo

    vehicle = libsumo.vehicle
    simulation = libsumo.simulation
    step = libsumo.simulationStep
    perf = time.perf_counter
    backend = SumoBackend(net, seed=0)
    elapsed = 0.0
    done = vehicles = collisions = 0
    try:
        while done < steps:
            backend.reset(scenario)  # same SUMO options and route file as the env
            backend.step()  # insertion step (sets the controlled speed mode), like the env's reset
            for _ in range(min(episode_steps, steps - done)):
                t0 = perf()
                step()
                ids = vehicle.getIDList()
                states = []
                for vid in ids:
                    states.append(
                        (
                            vehicle.getRoadID(vid),
                            vehicle.getLanePosition(vid),
                            vehicle.getSpeed(vid),
                            vehicle.getAcceleration(vid),
                        )
                    )
                    vehicle.setSpeed(vid, SPEED_MPS)
                elapsed += perf() - t0
                vehicles += len(states)
                collisions += simulation.getCollidingVehiclesNumber()
                done += 1
    finally:
        backend.close()
    return RunResult(done, elapsed, vehicles, collisions)


def _random_actions(
    observations: dict[str, dict[str, np.ndarray]], agents: list[str], rng: np.random.Generator
) -> dict[str, int]:
    """A uniform draw among each agent's allowed actions."""
    masks = np.stack([observations[a]["action_mask"] for a in agents]).astype(bool)
    scores = np.where(masks, rng.random(masks.shape) + 1e-9, -1.0)
    return dict(zip(agents, np.argmax(scores, axis=1).tolist(), strict=True))


def run_env(
    net: MergeNet,
    scenario: Scenario,
    steps: int,
    episode_steps: int,
    seed: int,
    wrap: Callable[[Callable[[], None]], None] | None = None,
) -> RunResult:
    """MergeParallelEnv.step with every vehicle an agent (reset and action draws not timed)."""
    perf = time.perf_counter
    rng = np.random.default_rng(seed)
    env = MergeParallelEnv(net=net, scenario=scenario, seed=seed)
    result = RunResult(0, 0.0, 0, 0)

    def loop() -> None:
        while result.steps < steps:
            observations, _ = env.reset()
            for _ in range(min(episode_steps, steps - result.steps)):
                if not env.agents:  # the episode ended: reset (not timed)
                    break
                actions = _random_actions(observations, env.agents, rng)
                t0 = perf()
                observations, *_ = env.step(actions)
                result.seconds += perf() - t0
                outcome = env.last_outcome
                assert outcome is not None
                result.vehicles += len(env.sim.snapshot)
                result.collisions += len(outcome.collisions)
                result.steps += 1

    try:
        if wrap is None:
            loop()
        else:
            wrap(loop)
    finally:
        env.close()
    return result


def _median(values: list[float]) -> float:
    return statistics.median(values) if values else float("nan")


def print_table(rows: list[list[str]], headers: list[str], title: str) -> None:
    try:
        from rich.console import Console
        from rich.table import Table
    except ImportError:
        widths = [max(len(h), *(len(r[i]) for r in rows)) for i, h in enumerate(headers)]
        print(title)
        print("  ".join(h.rjust(w) for h, w in zip(headers, widths, strict=True)))
        for r in rows:
            print("  ".join(c.rjust(w) for c, w in zip(r, widths, strict=True)))
        return
    table = Table(title=title)
    for h in headers:
        table.add_column(h, justify="right")
    for r in rows:
        table.add_row(*r)
    Console(width=160).print(table)


def profile_env(case: Case, steps: int, episode_steps: int, top: int) -> None:
    """cProfile the env side of one case and print where the time goes."""
    profiler = cProfile.Profile()

    def wrap(loop: Callable[[], None]) -> None:
        profiler.runcall(loop)

    scenario = make_scenario(case.n, case.net, episode_steps)
    run_env(case.net, scenario, steps, episode_steps, seed=0, wrap=wrap)
    for sort in ("tottime", "cumulative"):
        out = io.StringIO()
        stats = pstats.Stats(profiler, stream=out)
        stats.strip_dirs().sort_stats(sort).print_stats(top)
        text = out.getvalue()
        body = text[text.find("   ncalls") :] if "   ncalls" in text else text
        print(
            f"\ncProfile of the env loop (N={case.n}, {case.net_label}, {steps} steps, resets included), by {sort}:"
        )
        print(body.rstrip())


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--repeats", type=int, default=5, help="measurements per side and case (median taken)"
    )
    parser.add_argument("--steps", type=int, default=300, help="timed steps per measurement")
    parser.add_argument(
        "--episode-steps",
        type=int,
        default=100,
        help="steps before a reset (not timed); keeps cars off the merge",
    )
    parser.add_argument("--sizes", type=int, nargs="+", default=[8, 16, 32], help="N on the default net")
    parser.add_argument("--long-sizes", type=int, nargs="*", default=[64], help="N on the 1000 m net")
    parser.add_argument("--long-road-m", type=float, default=1000.0, help="road length of the generated net")
    parser.add_argument(
        "--profile",
        choices=("auto", "always", "never"),
        default="auto",
        help="cProfile the env step afterwards (auto: when a ratio is below the target)",
    )
    parser.add_argument("--profile-n", type=int, default=32, help="which case to profile")
    parser.add_argument("--profile-top", type=int, default=20, help="profile rows to print")
    return parser


def _measure(
    cases: list[Case], scenarios: dict[int, Scenario], args: argparse.Namespace
) -> tuple[dict[int, list[RunResult]], dict[int, list[RunResult]]]:
    """Raw and env runs of every case, ``args.repeats`` times each, interleaved."""
    raw: dict[int, list[RunResult]] = {c.n: [] for c in cases}
    env: dict[int, list[RunResult]] = {c.n: [] for c in cases}
    # Warm-up (imports, first libsumo start, numpy caches): one short run of each side, not kept.
    run_raw(cases[0].net, scenarios[cases[0].n], 20, args.episode_steps)
    run_env(cases[0].net, scenarios[cases[0].n], 20, args.episode_steps, seed=0)
    for r in range(args.repeats):
        for c in cases:
            # Interleave, alternating which side goes first, so drifts in machine load hit both.
            sides = ("raw", "env") if r % 2 == 0 else ("env", "raw")
            for side in sides:
                if side == "raw":
                    raw[c.n].append(run_raw(c.net, scenarios[c.n], args.steps, args.episode_steps))
                else:
                    env[c.n].append(run_env(c.net, scenarios[c.n], args.steps, args.episode_steps, seed=r))
        print(f"repeat {r + 1}/{args.repeats} done", file=sys.stderr, flush=True)
    return raw, env


def _table_rows(
    cases: list[Case], raw: dict[int, list[RunResult]], env: dict[int, list[RunResult]]
) -> tuple[list[list[str]], bool]:
    """The table's rows, and whether any ratio is below the target."""
    rows = []
    below = False
    for c in cases:
        raw_sps = _median([x.steps_per_s for x in raw[c.n]])
        env_sps = _median([x.steps_per_s for x in env[c.n]])
        ratio = env_sps / raw_sps
        below |= ratio < TARGET_RATIO
        rows.append(
            [
                str(c.n),
                c.net_label,
                f"{raw_sps:,.0f}",
                f"{env_sps:,.0f}",
                f"{ratio:.2f}" + ("" if ratio >= TARGET_RATIO else " (<0.5)"),
                f"{1e6 / raw_sps:,.0f}",
                f"{1e6 / env_sps:,.0f}",
                f"{_median([x.mean_vehicles for x in raw[c.n]]):.1f}|"
                f"{_median([x.mean_vehicles for x in env[c.n]]):.1f}",
                f"{sum(x.collisions for x in raw[c.n])}|{sum(x.collisions for x in env[c.n])}",
            ]
        )
    return rows, below


def main(argv: list[str] | None = None) -> int:
    parser = _parser()
    args = parser.parse_args(argv)
    if args.repeats < 1 or args.steps < 1 or args.episode_steps < 1:
        parser.error("--repeats, --steps and --episode-steps must be >= 1")

    with tempfile.TemporaryDirectory(prefix="idas_bench_") as tmp:
        cases = [Case(n, "default", read_merge_net(DEFAULT_NET)) for n in args.sizes]
        if args.long_sizes:
            length = args.long_road_m
            path = generate_net(
                Path(tmp) / "long.net.xml", NetParams(main_length_m=length, merge_length_m=length)
            )
            long_net = read_merge_net(path)
            cases += [Case(n, f"{length:g} m", long_net) for n in args.long_sizes]
        scenarios = {c.n: make_scenario(c.n, c.net, args.episode_steps) for c in cases}
        raw, env = _measure(cases, scenarios, args)
        headers = [
            "N",
            "net",
            "raw steps/s",
            "env steps/s",
            "ratio",
            "raw µs/step",
            "env µs/step",
            "veh/step raw|env",
            "collisions raw|env",
        ]
        rows, below = _table_rows(cases, raw, env)
        print_table(
            rows,
            headers,
            f"env throughput vs raw libsumo (median of {args.repeats} repeats x {args.steps} steps, "
            f"resets every {args.episode_steps} steps not timed; target ratio >= {TARGET_RATIO})",
        )
        if args.profile == "always" or (args.profile == "auto" and below):
            chosen = [c for c in cases if c.n == args.profile_n] or cases[-1:]
            profile_env(chosen[0], args.steps, args.episode_steps, args.profile_top)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
