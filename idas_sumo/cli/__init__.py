"""``idas-sumo``: netgen | nets | train | evaluate | sweep | cosim | plot | replay | export, one module each;
exit codes and signals in ``exits``, what the subcommands share in ``common``."""

from __future__ import annotations

import argparse
import logging
from collections.abc import Sequence
from types import ModuleType

from idas_sumo.cli import cosim, evaluate, export, netgen, nets, plot, replay, sweep, train
from idas_sumo.cli.common import Parser, VersionAction
from idas_sumo.cli.exits import (
    LateSignals,
    exit_code,
    forget_caught_interrupt,
    in_main_thread,
    sigterm_as_interrupt,
)

__all__ = ["build_parser", "main"]

DESCRIPTION = (
    "Train and evaluate IDAS merging policies in SUMO. "
    "Exit codes: 0 ok, 1 runtime failure, 2 bad input, 130 Ctrl-C, 143 SIGTERM."
)
COMMANDS: dict[str, ModuleType] = {
    "netgen": netgen,
    "nets": nets,
    "train": train,
    "evaluate": evaluate,
    "sweep": sweep,
    "cosim": cosim,
    "plot": plot,
    "replay": replay,
    "export": export,
}
"""Each subcommand's module, in ``--help``'s order: its ``add_parser(sub)`` and ``run(args)``."""


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(prog="idas-sumo", description=DESCRIPTION)
    parser.add_argument("-v", "--verbose", action="store_true", help="log progress details")
    parser.add_argument("--version", action=VersionAction, help="show the version and exit")
    sub = parser.add_subparsers(dest="command", required=True, parser_class=Parser)
    for module in COMMANDS.values():
        module.add_parser(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """The command line. ``argv`` None (the ``idas-sumo`` script, ``python -m idas_sumo.cli``): the
    process is ours, so signals that come after the command are handled too (``LateSignals``);
    with ``argv`` (a caller in Python) the caller's signal handlers are left alone."""
    late = LateSignals() if argv is None and in_main_thread() else None
    code = exit_code(lambda: _parse_and_run(argv), late)
    forget_caught_interrupt()
    return late.exit_code(code) if late is not None else code


def _parse_and_run(argv: Sequence[str] | None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING, format="%(levelname)s %(message)s"
    )
    with sigterm_as_interrupt():
        result: int = COMMANDS[args.command].run(args)
        return result
