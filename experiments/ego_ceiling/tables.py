"""The tables of experiments/ego_ceiling/README.md from ``search.py``'s ``samples.csv`` files.

    python experiments/ego_ceiling/tables.py --reference results/headline-2030 results/ego_ceiling/seed2030
    python experiments/ego_ceiling/tables.py --reference results/equal-terms/episodes.csv \
        results/ego_ceiling/seed2031 results/ego_ceiling/seed2032 results/ego_ceiling/seed2033

``--reference``: as ``search.py``'s, to tell the searched scenarios (no reference method perfect) from the controls.

Per searched scenario: the runs, the perfect runs of each sampler, the other cars' hard brakes per run (fewest and
most: the same number in every run means no ego the search tried changed them), how many of them came before the
ego's first decision, the ego's own hard brakes and the runs with a collision. Then per seed: the scenarios the
reference methods left imperfect, how many the search reached, and those whose other cars braked alike in every
run, or before the ego could act.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parent))
from search import _reference


def per_scenario(samples: pd.DataFrame) -> pd.DataFrame:
    groups = samples.groupby("scenario", sort=False)
    table = groups.agg(
        runs=("perfect", "size"),
        others_brakes_min=("others_brakes", "min"),
        others_brakes_max=("others_brakes", "max"),
        before_ego_min=("others_brakes_before_ego", "min"),
        ego_brake_runs=("ego_brakes", lambda b: int((b > 0).sum())),
        collision_runs=("collisions", lambda c: int((c > 0).sum())),
    )
    perfect = samples.pivot_table(index="scenario", columns="method", values="perfect", aggfunc="sum")
    return table.join(perfect.add_suffix("_perfect"))


def summary(seed_dir: Path, table: pd.DataFrame, controls: set[str]) -> dict[str, object]:
    searched = table[~table.index.isin(controls)]
    perfect_cols = [c for c in searched.columns if c.endswith("_perfect")]
    reached = searched[perfect_cols].sum(axis=1) > 0
    alike = (searched.others_brakes_min == searched.others_brakes_max) & (searched.others_brakes_min > 0)
    return {
        "seed": seed_dir.name,
        "searched": len(searched),
        "reached": int(reached.sum()),
        **{f"reached_by_{c[: -len('_perfect')]}": int((searched[c] > 0).sum()) for c in perfect_cols},
        "others_brake_alike": int(alike.sum()),
        "others_brake_before_ego": int((searched.before_ego_min > 0).sum()),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--reference", type=Path, action="append", required=True)
    parser.add_argument("seed_dirs", type=Path, nargs="+")
    args = parser.parse_args(argv)
    rows = []
    for seed_dir in args.seed_dirs:
        samples = pd.read_csv(seed_dir / "samples.csv")
        reference = _reference(args.reference, int(samples["seed"].iloc[0]))
        best = reference.groupby("scenario")["perfect"].max()
        controls = set(best.index[best == 1])
        table = per_scenario(samples)
        print(f"## {seed_dir.name}\n")
        with pd.option_context("display.width", 250, "display.max_columns", 20):
            print(table.to_string())
        print()
        rows.append(summary(seed_dir, table, controls))
    with pd.option_context("display.width", 250, "display.max_columns", 20):
        print(pd.DataFrame(rows).to_string(index=False))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
