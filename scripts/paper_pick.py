"""The declared pick of the paper's recipe (idas_sumo/scenarios/train_paper.toml, scripts/paper_recipe.sh).

    python scripts/paper_pick.py runs/paper [--seeds 0 1 2] [--suffix _paper]

Per method, among every validation of its seeds (40 scenarios of validation seed 123): the first by validation
success, then joint return; within a run the earliest of equals (the run's own ``<stage>_best.pt``), across
runs the lower seed. idas_paper: the curriculum runs' intelligent stage; idas_v_paper: their robot stage;
idas_direct_paper: the direct runs. Beside each pick, every seed's best and its last validation (the end of the
budget the run has reached). Prints the table and writes OUT_ROOT/picks.csv; reads only validation.csv.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import pandas as pd

from idas_sumo.errors import InputError
from idas_sumo.io_utils import read_csv_columns, write_csv_atomic

METHODS: dict[str, tuple[str, str]] = {
    "idas": ("curriculum", "intelligent"),
    "idas_v": ("curriculum", "robot"),
    "idas_direct": ("direct", "direct"),
}
"""Method -> (run kind, stage): the runs are OUT_ROOT/<kind>_seed<S>, the stage names its validation rows.
The method's name takes the recipe's suffix: ``_paper`` for the paper's recipe, none for ours."""
COLUMNS = ("stage", "episode", "global_episode", "joint_return", "perfect_rate", "success_rate")


def seed_rows(root: Path, method: str, seeds: list[int], suffix: str = "_paper") -> pd.DataFrame:
    """One row per seed that has validated this method's stage: its best (by the rule) and its last validation."""
    kind, stage = METHODS[method]
    rows = []
    for seed in seeds:
        path = root / f"{kind}_seed{seed}" / "validation.csv"
        if not path.exists():
            continue
        table = read_csv_columns(path, COLUMNS, "idas-sumo train")
        table = table[table["stage"] == stage]
        if table.empty:
            continue
        # Stable sort: the earliest of equal validations first, as the run's <stage>_best.pt.
        best = table.sort_values(["success_rate", "joint_return"], ascending=False, kind="stable").iloc[0]
        last = table.iloc[-1]
        rows.append(
            {
                "method": method + suffix,
                "seed": seed,
                "run": str(path.parent),
                "checkpoint": str(path.parent / f"{stage}_best.pt"),
                "validations": len(table),
                "best_episode": int(best["episode"]),
                "best_success": float(best["success_rate"]),
                "best_perfect": float(best["perfect_rate"]),
                "best_joint_return": float(best["joint_return"]),
                "last_episode": int(last["episode"]),
                "last_success": float(last["success_rate"]),
                "last_perfect": float(last["perfect_rate"]),
                "last_joint_return": float(last["joint_return"]),
            }
        )
    return pd.DataFrame(rows)


def picks(root: Path, seeds: list[int], suffix: str = "_paper") -> pd.DataFrame:
    """Every seed's row per method, the pick marked (``picked``): success, then return, then the lower seed."""
    frames = []
    for method in METHODS:
        rows = seed_rows(root, method, seeds, suffix)
        if rows.empty:
            continue
        order = rows.sort_values(
            ["best_success", "best_joint_return", "seed"], ascending=[False, False, True], kind="stable"
        )
        rows["picked"] = rows.index == order.index[0]
        frames.append(rows)
    if not frames:
        raise InputError(f"{root}: no validation.csv of a recipe's runs (<kind>_seed<S>/validation.csv)")
    return pd.concat(frames, ignore_index=True)


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("root", type=Path, help="the runs' directory (scripts/paper_recipe.sh's OUT_ROOT)")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument(
        "--suffix", default="_paper", help="the methods' name suffix: _paper (the paper's recipe), '' (ours)"
    )
    args = parser.parse_args()
    try:
        table = picks(args.root, args.seeds, args.suffix)
    except InputError as err:
        print(f"paper_pick: {err}", file=sys.stderr)
        raise SystemExit(2) from None
    write_csv_atomic(table, args.root / "picks.csv")
    with pd.option_context("display.width", 200, "display.max_columns", 20):
        print(table.drop(columns=["run"]).to_string(index=False))
    for row in table[table["picked"]].itertuples():
        print(f"{row.method}: seed {row.seed}, episode {row.best_episode} -> {row.checkpoint}")


if __name__ == "__main__":
    main()
