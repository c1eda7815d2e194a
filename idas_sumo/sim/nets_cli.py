"""``idas-sumo nets``: the merges a SUMO network holds (``inspect``), and the sample nets (``sample``).

``idas_sumo/cli/nets.py`` registers the command (``add_nets_parser``) and calls ``run_nets``; everything else is here.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TypeVar

from idas_sumo.sim.sample_nets import SAMPLE_NETS

P = TypeVar("P", bound=argparse.ArgumentParser)


def add_nets_parser(sub: argparse._SubParsersAction[P]) -> None:
    """The ``nets`` command and its subcommands on ``sub`` (the main parser's subparsers)."""
    nets = sub.add_parser("nets", help="list the merges of a SUMO network; build the sample nets")
    actions = nets.add_subparsers(dest="nets_command", required=True, parser_class=type(nets))
    inspect = actions.add_parser(
        "inspect",
        help="list the merges detected in a .net.xml, one line each (exit 2 if there is none)",
        description=(
            "Merges are junctions where two roads' lanes become one, and on-ramps whose acceleration lane "
            "ends beside the highway. Each line: junction id, kind, then for the main road and the merging "
            "road their edges[the lane that merges], length to the merge point, speed limits and priority, "
            "then the road after the merge."
        ),
    )
    inspect.add_argument("net", type=Path, metavar="FILE", help="a SUMO .net.xml")
    inspect.add_argument(
        "--junction",
        metavar="ID",
        help="show only the merge at this junction, lane by lane (exit 2 if it is not one)",
    )
    sample = actions.add_parser("sample", help="build one of the sample nets with netconvert")
    sample.add_argument("name", choices=sorted(SAMPLE_NETS), help="which net")
    sample.add_argument("--out", type=Path, required=True, help="output .net.xml")
    sample.add_argument(
        "--force",
        action="store_true",
        help="replace an --out (or its plain XML) that idas-sumo did not write",
    )


def run_nets(args: argparse.Namespace) -> int:
    if args.nets_command == "sample":
        from idas_sumo.sim.sample_nets import build_sample_net

        print(f"wrote {build_sample_net(args.name, args.out, force=args.force)}")
        return 0
    from idas_sumo.sim.merge_detect import choose_merge, describe_site, detect_merges

    if args.junction is None:
        for site in detect_merges(args.net, none_is_error=True):
            print(describe_site(site))
        return 0
    site = choose_merge(args.net, args.junction)
    print(describe_site(site))
    for side in ("main", "merge"):
        for lane in site.route(side):
            where = "before" if lane.start_to_merge_m >= 0 else "past"
            print(
                f"  {side:5s} {lane.lane_id:24s} {lane.length_m:8.1f} m, starts {abs(lane.start_to_merge_m):7.1f} m "
                f"{where} the merge point, {lane.speed_limit_mps:g} m/s"
                + ("" if lane.internal else f", priority {lane.priority}")
            )
    return 0


__all__ = ["add_nets_parser", "run_nets"]
