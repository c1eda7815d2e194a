"""Side-by-side tables of instrumented runs (markdown): ``python compare.py LABEL=RUN_DIR ... [--block 1000]``.

Validation (40 scenarios, seed 123, greedy) at the episodes every run validated, and per block of training
episodes the outcomes (``RUN_DIR/metrics.csv``) and the learner diagnostics (``RUN_DIR_diagnostics.csv``)."""

from __future__ import annotations

import argparse
from pathlib import Path

import pandas as pd


def blocks(run: Path, block: int) -> pd.DataFrame:
    m = pd.read_csv(run / "metrics.csv")
    m["block"] = m.episode // block * block
    g = m.groupby("block")
    out = pd.DataFrame(
        {
            "episodes": g.size(),
            "success %": 100 * g.success.mean(),
            "perfect %": 100 * g.perfect.mean(),
            "collision %": 100 * m.assign(c=m.collisions > 0).groupby("block").c.mean(),
            "timeout %": 100 * g.timed_out.mean(),
        }
    )
    d = pd.read_csv(run.with_name(run.name + "_diagnostics.csv"))
    d["block"] = (d["update"] * 16) // block * block
    dg = d.groupby("block")
    out["entropy"] = dg.entropy.mean()
    out["speed m/s"] = dg.speed_mean.mean()
    out["at rest %"] = 100 * dg.standstill.mean()
    out["keep %"] = 100 * dg.share_a2.mean()
    out["+0.2 %"] = 100 * dg.share_a4.mean()
    out["sd A2 / sd A1"] = dg.a2_std.mean() / dg.a1_std.mean()
    return out


def markdown(df: pd.DataFrame) -> str:
    """A pipe table (pandas' to_markdown needs tabulate, which the venv lacks)."""
    cols = [str(df.index.name or "")] + [str(c) for c in df.columns]
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for idx, row in df.iterrows():
        lines.append("| " + " | ".join([str(idx)] + [str(v) for v in row.tolist()]) + " |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", help="LABEL=RUN_DIR")
    parser.add_argument("--block", type=int, default=1000)
    args = parser.parse_args()
    runs = {label: Path(path) for label, path in (r.split("=", 1) for r in args.runs)}
    vals = []
    for label, run in runs.items():
        v = pd.read_csv(run / "validation.csv")
        v["run"] = label
        vals.append(v)
    val = pd.concat(vals)
    val["cell"] = (
        (100 * val.success_rate).round(1).astype(str)
        + " / "
        + (100 * val.perfect_rate).round(1).astype(str)
        + " / "
        + val.joint_return.round(1).astype(str)
    )
    print("Validation, success % / perfect % / joint return:\n")
    print(markdown(val.pivot(index="episode", columns="run", values="cell")[list(runs)].fillna("–")))
    for label, run in runs.items():
        print(f"\nTraining, {label}, per {args.block} episodes:\n")
        print(markdown(blocks(run, args.block).round(2)))


if __name__ == "__main__":
    main()
