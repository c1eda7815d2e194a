"""The project's exception types. The CLI maps them onto exit codes (docs/design-notes.md, "Command line and exit codes")."""

from __future__ import annotations


class IdasError(Exception):
    """Base class for every error idas-sumo raises on purpose."""

    exit_code = 1


class InputError(IdasError):
    """Bad user input: a file, flag or value we cannot use. Exit code 2."""

    exit_code = 2


class SimulationError(IdasError):
    """SUMO failed while running (carries SUMO's own message where it has one). Exit code 1."""

    exit_code = 1


class SumoRefusedInput(InputError, SimulationError):
    """SUMO would not load what it was given (a net our checks let through): exit 2, SUMO's own message."""

    exit_code = 2
