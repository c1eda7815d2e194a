"""``idas-sumo cosim``: SUMO's own traffic through a merge, a share of it automated, and its flow statistics."""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import TYPE_CHECKING

from idas_sumo.cli.common import JUNCTION_HELP, add_worker_flags, check_backend, input_file, out_path
from idas_sumo.env.actions import DEFAULT_SAFETY_MASK, SAFETY_MASKS
from idas_sumo.errors import InputError
from idas_sumo.resources import DEFAULT_NET_NAME

if TYPE_CHECKING:
    from idas_sumo.cli.common import Subparsers
    from idas_sumo.cosim.stats import Row

DEFAULT_BIN_S = 300.0
"""The statistics' time bin when --bin-s is not given (or the whole run, when that does not divide it)."""


def add_parser(sub: Subparsers) -> None:
    co = sub.add_parser(
        "cosim",
        help="co-simulate: SUMO inserts traffic flows, a share of the cars is automated; flow statistics",
        description=(
            "SUMO inserts the demand (vehicles per hour per incoming road) and drives the cars with its own "
            "models; each car is automated with probability --penetration and then driven by --policy with "
            "the engine's observation and masks. Runs the grid demand x penetration x seed and writes "
            "OUT/flows.csv (one row per run), OUT/bins.csv (one row per run and time bin) and OUT/flows.png "
            "(throughput, delay and hard brakes against demand, per penetration). Run again "
            "in the same OUT, it skips the runs flows.csv already holds."
        ),
    )
    co.add_argument(
        "--net", type=input_file, default=DEFAULT_NET_NAME, help="a net with a merge (default: %(default)s)"
    )
    co.add_argument("--junction", metavar="ID", help=JUNCTION_HELP)
    co.add_argument(
        "--demand",
        action="append",
        required=True,
        metavar="ROAD=VEH_PER_H[,ROAD=...]",
        help="vehicles per hour entering each road, named as `idas-sumo nets inspect` names them (main, "
        "merge, or an edge id of the road); repeat the flag for several demand levels",
    )
    co.add_argument(
        "--penetration",
        required=True,
        metavar="P[,P...]",
        help="share of automated cars, each in [0, 1] (0: plain SUMO)",
    )
    co.add_argument(
        "--policy",
        default="idas",
        metavar="METHOD",
        help="the automated cars' method: idas, idas_v, idas_direct, idas_geometry, warm_start, idm, fsm_idm, "
        "fsm_idm_smooth (default: %(default)s)",
    )
    co.add_argument(
        "--policy-file", type=input_file, metavar="PATH", help="a trained checkpoint for a learned --policy"
    )
    co.add_argument(
        "--safety-mask",
        choices=SAFETY_MASKS,
        default=DEFAULT_SAFETY_MASK,
        help="which car the automated cars' safety mask follows (default: %(default)s)",
    )
    co.add_argument(
        "--duration-s", type=float, default=3600.0, help="simulated seconds (default: %(default)s)"
    )
    co.add_argument(
        "--bin-s",
        type=float,
        help=f"the statistics' time bin, s (default: {DEFAULT_BIN_S:g}, or the whole run if that does not divide it)",
    )
    co.add_argument(
        "--warmup-s",
        type=float,
        default=0.0,
        help="leave this start out of the run statistics (whole bins; the road fills up from empty) "
        "(default: %(default)s)",
    )
    co.add_argument(
        "--seeds", default="0", help="SUMO seeds of the runs: 0-4, 0,3,7 or a mix (default: %(default)s)"
    )
    co.add_argument(
        "--out", type=out_path, default=Path("results/cosim"), help="folder (default: %(default)s)"
    )
    co.add_argument(
        "--force", action="store_true", help="start over in --out (its earlier cosim files are removed)"
    )
    _add_extra_flags(co)


def _add_extra_flags(co: argparse.ArgumentParser) -> None:
    """The demand's time profile, trajectories, and where the runs run."""
    co.add_argument(
        "--demand-profile",
        type=input_file,
        metavar="CSV",
        help="a time profile of every --demand: a CSV with the header time_s,multiplier, piecewise "
        "constant (each row's multiplier from its time to the next row's; the first row at 0)",
    )
    co.add_argument(
        "--trajectories",
        action="store_true",
        help="also record every car's position on the merge's roads each second, OUT/trajectories/"
        "RUN.csv, for the time-space diagram `idas-sumo plot OUT` draws (slower runs, larger files)",
    )
    add_worker_flags(
        co, "co-simulation workers", "processes sharing the runs", "default: %(default)s", workers_default=1
    )


def _bin_s(args: argparse.Namespace) -> float:
    if args.bin_s is not None:
        return float(args.bin_s)
    d = float(args.duration_s)
    return DEFAULT_BIN_S if math.isfinite(d) and d >= DEFAULT_BIN_S and d % DEFAULT_BIN_S == 0 else d


def _report(key: dict[str, str], row: Row | None) -> None:
    what = f"{key['demand']} p={key['penetration']} seed {key['seed']}"
    if row is None:
        print(f"{what}: done before, skipped")
        return
    print(
        f"{what}: throughput {row['throughput_veh_per_h']:.0f} veh/h, mean time loss "
        f"{row['mean_time_loss_s']:.1f} s, collisions {row['collisions']}, teleports {row['teleports']} "
        f"({row['real_time_factor']:.0f}x real time)"
    )


def run(args: argparse.Namespace) -> int:
    from functools import partial

    from idas_sumo.cosim.demand import (
        check_duration,
        check_profile_demand,
        parse_demands,
        parse_penetrations,
        parse_profile,
    )
    from idas_sumo.cosim.study import StudyPlan, run_study
    from idas_sumo.evaluation.policies import LEARNED_METHODS, check_method, resolve_policy
    from idas_sumo.sim.merge_detect import choose_merge
    from idas_sumo.training.sweep import parse_seeds

    check_backend(args)
    bin_s = _bin_s(args)
    check_duration(float(args.duration_s), bin_s, float(args.warmup_s))
    profile = parse_profile(args.demand_profile, float(args.duration_s)) if args.demand_profile else ()
    penetrations = parse_penetrations(args.penetration)
    seeds = parse_seeds(args.seeds)
    policy = check_method(args.policy, "--policy")
    site = choose_merge(args.net, args.junction)
    demands = parse_demands(list(args.demand), site)
    check_profile_demand(demands, profile, site)
    plan = StudyPlan(
        site=site,
        demands=demands,
        penetrations=penetrations,
        seeds=seeds,
        policy=policy,
        duration_s=float(args.duration_s),
        bin_s=bin_s,
        safety_mask=args.safety_mask,
        warmup_s=float(args.warmup_s),
        profile=profile,
        trajectories=args.trajectories,
    )
    policy_file = Path(args.policy_file) if args.policy_file is not None else None
    if policy_file is not None and policy not in LEARNED_METHODS:
        raise InputError(f"--policy-file: {policy} is a rule, not a learned policy; leave --policy-file out")
    flows, bins = run_study(
        plan,
        partial(resolve_policy, policy, policy_file),  # picklable: workers make it themselves
        args.out,
        force=args.force,
        on_run=_report,
        workers=args.workers,
        ray_address=args.ray_address,
    )
    print(f"wrote {flows}, {bins}, {flows.with_name('flows.png')}")
    return 0
