"""``idas-sumo netgen``: the two-road merge network, written with netconvert."""

from __future__ import annotations

import argparse
import sys
from typing import TYPE_CHECKING

from idas_sumo.cli.common import out_path
from idas_sumo.errors import InputError
from idas_sumo.resources import DEFAULT_NET_NAME
from idas_sumo.sim.netgen import PRIORITIES, NetParams

if TYPE_CHECKING:
    from idas_sumo.cli.common import Subparsers

NETGEN_FLAGS: dict[str, tuple[str, str]] = {
    "main_length_m": ("--main-length", "main road length to the merge point, m"),
    "merge_length_m": ("--merge-length", "merge road length to the merge point, m"),
    "out_length_m": ("--out-length", "outgoing road length, m"),
    "main_speed_mps": ("--main-speed", "main road speed limit, m/s"),
    "merge_speed_mps": ("--merge-speed", "merge road speed limit, m/s"),
    "out_speed_mps": ("--out-speed", "outgoing road speed limit, m/s"),
    "angle_deg": ("--angle", "angle between the two roads, degrees"),
}
"""``netgen``'s flags: NetParams field -> (flag, help); the defaults are NetParams's."""


def add_parser(sub: Subparsers) -> None:
    net = sub.add_parser("netgen", help="generate the two-road merge network with netconvert")
    net.add_argument(
        "--out", type=out_path, default=DEFAULT_NET_NAME, help="output .net.xml (default: %(default)s)"
    )
    net.add_argument(
        "--force",
        action="store_true",
        help="replace an --out (or its .nod.xml/.edg.xml) that idas-sumo did not write",
    )
    defaults = NetParams()
    for field, (flag, what) in NETGEN_FLAGS.items():
        net.add_argument(
            flag,
            dest=field,
            metavar=flag.removeprefix("--").replace("-", "_").upper(),
            type=float,
            default=getattr(defaults, field),
            help=f"{what} (default: %(default)s)",
        )
    net.add_argument(
        "--priority",
        choices=PRIORITIES,
        default=defaults.priority,
        help="right of way: the main road's, or equal (a zipper junction) (default: %(default)s)",
    )


def run(args: argparse.Namespace) -> int:
    from idas_sumo.env.engine import DEFAULT_MAX_EPISODE_S
    from idas_sumo.env.net_needs import check_road_lengths, road_needs
    from idas_sumo.env.scenario import TrafficConfig
    from idas_sumo.sim.netgen import describe, generate_net, read_merge_net

    params = NetParams(**{field: getattr(args, field) for field in NETGEN_FLAGS}, priority=args.priority)
    path = generate_net(args.out, params, force=args.force)
    net = read_merge_net(path)
    print(describe(net))
    try:  # a net for other scenarios is fine to write, but say now what train/evaluate will say
        check_road_lengths(net, road_needs(TrafficConfig().start_range_m, DEFAULT_MAX_EPISODE_S))
    except InputError as err:
        print(
            f"idas-sumo: warning: with the default scenarios, train and evaluate refuse it: {err}",
            file=sys.stderr,
        )
    return 0
