"""Print a training run's sampled episodes per block of episodes, and its validations, as markdown tables.

    python scripts/training_blocks.py runs/idas_smooth_s2_anchor_seed0 runs/idas_smooth_s2_full_seed0 --block 5000

One pair of tables per run and stage: per block of ``--block`` episodes (by stage episode) the share of episodes in which every agent
succeeded, that were perfect, that held a collision and that timed out, and the mean policy entropy; then every
validation (success %, perfect %, joint return) with the run's best marked. What docs/results.md quotes for the
stage-2 runs.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import pandas as pd

from idas_sumo.training.metrics import METRICS_NAME
from idas_sumo.training.validation import VALIDATION_NAME


def block_table(metrics: pd.DataFrame, block: int) -> pd.DataFrame:
    """Per block of ``block`` stage episodes: success, perfect, collision and timeout shares (%), mean entropy."""
    first = (metrics["episode"] // block) * block
    grouped = metrics.assign(
        with_collision=metrics["collisions"] > 0,
        block=first.astype(str) + "–" + (first + block - 1).astype(str),
    ).groupby(first, sort=True)
    return pd.DataFrame(
        {
            "episodes": grouped["block"].first(),
            "success %": grouped["success"].mean() * 100,
            "perfect %": grouped["perfect"].mean() * 100,
            "collision %": grouped["with_collision"].mean() * 100,
            "timeout %": grouped["timed_out"].mean() * 100,
            "entropy": grouped["entropy"].mean(),
            "n": grouped["success"].size(),
        }
    ).reset_index(drop=True)


def markdown(table: pd.DataFrame) -> str:
    """``table`` as a markdown table, floats to two decimals (pandas' ``to_markdown`` needs tabulate)."""

    def cell(value: object) -> str:
        return f"{value:.2f}" if isinstance(value, float) else str(value)

    rows = [" | ".join(map(str, table.columns)), " | ".join("---" for _ in table.columns)]
    rows += [" | ".join(cell(v) for v in row) for row in table.itertuples(index=False)]
    return "\n".join(f"| {row} |" for row in rows)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "runs", nargs="+", type=Path, help="training run folders (metrics.csv, validation.csv)"
    )
    parser.add_argument("--block", type=int, default=5000, help="episodes per row (default 5000)")
    args = parser.parse_args(argv)
    if args.block < 1:
        print("training_blocks: --block must be at least 1", file=sys.stderr)
        return 2
    for run in args.runs:
        metrics_path = run / METRICS_NAME
        if not metrics_path.is_file():
            print(f"training_blocks: {metrics_path}: no such file", file=sys.stderr)
            return 2
        metrics = pd.read_csv(metrics_path)
        validation_path = run / VALIDATION_NAME
        validation = pd.read_csv(validation_path) if validation_path.is_file() else None
        # A curriculum run's stages count their episodes from 0 each: one pair of tables per stage.
        for stage in metrics["stage"].unique():
            print(f"\n## {run}: {stage}\n")
            print(markdown(block_table(metrics[metrics["stage"] == stage], args.block)))
            if validation is not None:
                v = validation[validation["stage"] == stage]
                v = v.assign(success=v["success_rate"] * 100, perfect=v["perfect_rate"] * 100)
                print()
                print(markdown(v[["episode", "success", "perfect", "joint_return", "best"]]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
