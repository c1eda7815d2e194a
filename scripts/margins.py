"""IDAS's margins over the rules on perfect success, per evaluation seed and pooled, paired by scenario.

    python scripts/margins.py results/paper results/paper-2024 ... --out results/margin/margins.csv \
        [--methods idas idm fsm_idm warm_start]

Each directory is an ``idas-sumo evaluate`` output of the paper protocol (one seed each). Prints and writes one row
per seed and one for all of them: success and perfect success per method, and the first method's margin over each
other one on perfect success (IDAS − IDM, IDAS − FSM+IDM by default) with its standard error
(``idas_sumo.evaluation.metrics.paired_margin``). ``any_method_perfect_pct``: the scenarios that at least one
of the evaluated methods (every method in the directories, not only ``--methods``) finished perfectly, a lower
bound on what the best ego policy could reach there; ``methods_evaluated`` counts those methods.
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
"""The default --methods: the first is compared with each of the others."""
COLUMNS = ("method", "seed", "scenario", "success", "perfect")


def margin_rows(episodes: pd.DataFrame, methods: tuple[str, ...] = METHODS) -> list[dict[str, object]]:
    """One row per seed, then one for every seed together."""
    groups = [(str(seed), rows) for seed, rows in episodes.groupby("seed", sort=False)]
    rows = []
    for label, group in [*groups, ("all", episodes)]:
        row: dict[str, object] = {
            "seed": label,
            "scenarios": len(group[["seed", "scenario"]].drop_duplicates()),
        }
        for method in methods:
            mine = group[group["method"] == method]
            row[f"{method}_success_pct"] = round(100.0 * float(mine["success"].mean()), 2)
            row[f"{method}_perfect_pct"] = round(100.0 * float(mine["perfect"].mean()), 2)
        per_scenario = group.pivot_table(index=["seed", "scenario"], columns="method", values="perfect")
        row["methods_evaluated"] = per_scenario.shape[1]
        row["any_method_perfect_pct"] = round(100.0 * float(per_scenario.max(axis=1).mean()), 2)
        for rule in methods[1:]:
            margin = paired_margin(group, methods[0], rule)
            row[f"{methods[0]}_minus_{rule}_pts"] = margin.margin_pts
            row[f"{methods[0]}_minus_{rule}_se_pts"] = margin.standard_error_pts
        rows.append(row)
    return rows


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("dirs", type=Path, nargs="+", help="evaluate output directories, one seed each")
    parser.add_argument("--out", type=Path, required=True, help="the CSV to write")
    parser.add_argument(
        "--methods",
        nargs="+",
        default=list(METHODS),
        help="the method compared, then those it is compared with",
    )
    args = parser.parse_args()
    methods = tuple(args.methods)
    try:
        frames = [read_csv_columns(d / "episodes.csv", COLUMNS, "idas-sumo evaluate") for d in args.dirs]
        episodes = pd.concat(frames, ignore_index=True)
        missing = [m for m in methods if m not in set(episodes["method"])]
        if missing:
            raise InputError(f"no episodes of {', '.join(missing)} in {', '.join(map(str, args.dirs))}")
        if len(methods) < 2:
            raise InputError("--methods: the method compared and at least one other")
        table = pd.DataFrame(margin_rows(episodes, methods))
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
