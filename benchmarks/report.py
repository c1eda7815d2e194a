"""How every benchmark ends: its table, then the load the shared machine was under (numbers of one run only
compare with each other)."""

from __future__ import annotations

import os

from rich.console import Console
from rich.table import Table


def print_table(table: Table, console: Console | None = None) -> None:
    out = console or Console()
    out.print(table)
    out.print(
        f"load average after (1 min): {os.getloadavg()[0]:.2f} on {os.cpu_count()} cores (others' jobs skew it)"
    )
