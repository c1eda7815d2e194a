"""IDAS's margins over the rules on perfect success, per evaluation seed and pooled, paired by scenario.

    python scripts/margins.py results/paper results/paper-2024 ... --out results/margin/margins.csv

Each directory is an ``idas-sumo evaluate`` output of the paper protocol (one seed each). Prints and writes one row
per seed and one for all of them: success and perfect success per method, and IDAS − IDM and IDAS − FSM+IDM on
perfect success with their standard errors (``idas_sumo.evaluation.metrics.paired_margin``).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import pandas as pd

from idas_sumo.errors import InputError
from idas_sumo.evaluation.metrics import paired_margin
from idas_sumo.io_utils import ensure_writable_dir, read_csv_columns, write_csv_atomic

METHODS = ("idas", "idm", "fsm_idm")
COLUMNS = ("method", "seed", "scenario", "success", "perfect")


def margin_rows(episodes: pd.DataFrame) -> list[dict[str, object]]:
    """One row per seed, then one for every seed together."""
    groups = [(str(seed), rows) for seed, rows in episodes.groupby("seed", sort=False)]
    rows = []
    for label, group in [*groups, ("all", episodes)]:
        row: dict[str, object] = {
            "seed": label,
            "scenarios": len(group[["seed", "scenario"]].drop_duplicates()),
        }
        for method in METHODS:
            mine = group[group["method"] == method]
            row[f"{method}_success_pct"] = round(100.0 * float(mine["success"].mean()), 2)
            row[f"{method}_perfect_pct"] = round(100.0 * float(mine["perfect"].mean()), 2)
        for rule in METHODS[1:]:
            margin = paired_margin(group, "idas", rule)
            row[f"idas_minus_{rule}_pts"] = margin.margin_pts
            row[f"idas_minus_{rule}_se_pts"] = margin.standard_error_pts
        rows.append(row)
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("dirs", type=Path, nargs="+", help="evaluate output directories, one seed each")
    parser.add_argument("--out", type=Path, required=True, help="the CSV to write")
    args = parser.parse_args()
    try:
        frames = [read_csv_columns(d / "episodes.csv", COLUMNS, "idas-sumo evaluate") for d in args.dirs]
        episodes = pd.concat(frames, ignore_index=True)
        missing = [m for m in METHODS if m not in set(episodes["method"])]
        if missing:
            raise InputError(f"no episodes of {', '.join(missing)} in {', '.join(map(str, args.dirs))}")
        table = pd.DataFrame(margin_rows(episodes))
        ensure_writable_dir(args.out.parent)
    except (InputError, ValueError) as err:
        print(f"margins: {err}", file=sys.stderr)
        return 2
    write_csv_atomic(table, args.out)
    print(table.to_string(index=False))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
