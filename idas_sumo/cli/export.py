"""``idas-sumo export``: a scenario file, or one episode of an evaluation, as plain SUMO files that ``sumo``
and ``sumo-gui`` run without idas-sumo (sim/plain_sumo.py writes them)."""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from idas_sumo.cli.common import EVAL_SEED, JUNCTION_HELP, input_file, out_path, seed
from idas_sumo.errors import InputError
from idas_sumo.resources import DEFAULT_NET_NAME

if TYPE_CHECKING:
    from idas_sumo.cli.common import Subparsers
    from idas_sumo.env.scenario import Scenario
    from idas_sumo.sim.merge_detect import MergeSite


def add_parser(sub: Subparsers) -> None:
    ex = sub.add_parser(
        "export", help="write a scenario or an evaluated episode as .sumocfg + .rou.xml + net for plain SUMO"
    )
    ex.add_argument(
        "source",
        metavar="SCENARIO.toml|RESULTS_DIR",
        type=input_file,
        help="a scenario TOML (as evaluate --scenario reads it) or a directory written by `idas-sumo evaluate`",
    )
    ex.add_argument(
        "--scenario",
        metavar="K",
        help="which scenario of RESULTS_DIR: its name (paper-037) or index (37) (default: the only one)",
    )
    ex.add_argument("--out", type=out_path, required=True, help="output directory")
    ex.add_argument("--force", action="store_true", help="write into an existing, non-empty --out")
    ex.add_argument(
        "--net",
        type=input_file,
        help=f"a scenario file's merge network (default: {DEFAULT_NET_NAME}; a results directory "
        "brings the net it was evaluated on)",
    )
    ex.add_argument("--junction", metavar="ID", help=JUNCTION_HELP + "; scenario files only")
    ex.add_argument(
        "--seed",
        type=seed,
        help=f"SUMO's --seed in the .sumocfg (default: the evaluation's, or {EVAL_SEED}, evaluate's default)",
    )


@dataclass(frozen=True)
class _Source:
    scenario: Scenario
    site: MergeSite
    seed: int
    notes: list[str]
    """More lines for the route file's comment: where the scenario came from, each car."""


def run(args: argparse.Namespace) -> int:
    from idas_sumo.io_utils import output_directory
    from idas_sumo.sim.plain_sumo import plain_files, write_plain_sumo

    source = _read_source(args)  # every input checked before --out is touched
    names = plain_files(source.scenario.name, source.site.path)
    with output_directory(args.out, args.force, writes=names) as out:
        config, _, _ = write_plain_sumo(
            out, source.scenario.name, source.scenario, source.site, source.seed, source.notes
        )
    print(f"wrote {', '.join(names)} to {args.out}; run it: sumo -c {config} (or sumo-gui -c {config})")
    return 0


def _read_source(args: argparse.Namespace) -> _Source:
    path: Path = args.source
    if path.is_dir():
        return _from_results(args, path)
    if not path.exists():
        raise InputError(
            f"{path}: no such file or directory (expected a scenario TOML or a directory written by "
            "`idas-sumo evaluate`)"
        )
    if args.scenario is not None:
        raise InputError(f"--scenario picks an episode of a results directory; {path} is a scenario file")
    return _from_file(args, path)


def _from_file(args: argparse.Namespace, path: Path) -> _Source:
    """A scenario TOML, checked against the net as ``evaluate --scenario`` checks it."""
    from idas_sumo.env.scenario import Road, check_against_net, load_scenario, start_room_m
    from idas_sumo.resources import resolve_user_path
    from idas_sumo.sim.merge_detect import choose_merge

    net = args.net if args.net is not None else resolve_user_path(DEFAULT_NET_NAME)
    site = choose_merge(net, args.junction)
    limits: dict[Road, float] = {
        "main": site.main.road.speed_limit_mps,
        "merge": site.merge.road.speed_limit_mps,
    }
    scenario = load_scenario(path, limits)
    check_against_net(scenario, limits, start_room_m(site), str(path))
    notes = [
        f"Scenario file: {path}. Evaluated from the file, its first car ({scenario.vehicles[0].id}) runs",
        "the evaluated method and the other controlled cars the others' method.",
        *_vehicle_table(scenario),
    ]
    return _Source(scenario, site, EVAL_SEED if args.seed is None else args.seed, notes)


def _from_results(args: argparse.Namespace, path: Path) -> _Source:
    """The K-th (or named) scenario of an evaluation, from what it keeps for replay."""
    from idas_sumo.evaluation.replay import NET_NAME, REPLAY_DIR, load_replay_data, pick_case
    from idas_sumo.sim.merge_detect import choose_merge

    for flag, given in (("--net", args.net), ("--junction", args.junction)):
        if given is not None:
            raise InputError(
                f"{flag}: a results directory brings the merge it was evaluated on "
                f"({path / REPLAY_DIR / NET_NAME}); leave out {flag}"
            )
    data = load_replay_data(path)
    if args.scenario is None and len(data.cases) > 1:
        raise InputError(
            f"{path} holds {len(data.cases)} scenarios: choose one with --scenario NAME or an index "
            f"0-{len(data.cases) - 1}"
        )
    case = data.cases[0] if args.scenario is None else pick_case(data, args.scenario)
    site = choose_merge(data.net_path, data.env.junction)
    methods = ", ".join(data.methods)
    notes = [
        f"Episode {case.scenario.name} of the evaluation in {path}: {', '.join(case.method_vehicles)} ran",
        f"the evaluated method ({methods}), the other controlled cars {data.others.method}.",
        *_vehicle_table(case.scenario),
    ]
    return _Source(case.scenario, site, data.seed if args.seed is None else args.seed, notes)


def _vehicle_table(scenario: Scenario) -> list[str]:
    """Each car's start, its driver type (no SUMO attribute holds it) and who drives it in idas-sumo."""
    rows = [
        f"Road priorities (the policies' observation; SUMO's right of way is the net's): main "
        f"{scenario.main_prio}, merge {scenario.merge_prio}.",
        f"{'vehicle':<12} {'road':<6} {'start m':>8} {'speed m/s':>9} {'depart s':>8} {'b_type':>6}  in idas-sumo",
    ]
    for v in scenario.vehicles:
        who = "policy" if v.controlled else "SUMO"
        rows.append(
            f"{v.id:<12} {v.road:<6} {v.start_pos_m:>8.3f} {v.speed_mps:>9.3f} {v.depart_s:>8.2f} "
            f"{v.b_type:>6.3f}  {who}"
        )
    return rows
