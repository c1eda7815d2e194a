"""Which way each term pushes the actor, per block of training episodes (issue 36, stage 2's critic).

From an instrumented run's per-update diagnostics (``experiments/stage2_collapse/instrumented_train.py``): the mean
advantage of the rows that took +0.2 m/s² less that of the rows that kept their acceleration, for J1 (A1) and J2
(A2), each in units of its batch standard deviation (the shipped recipe standardises both before mixing). A term
that keeps one sign for thousands of episodes pushes the policy that way whatever the returns say.

    python experiments/stage2_critic/push.py LABEL=DIAGNOSTICS.csv[.gz] ... [--block 1000]
"""

from __future__ import annotations

import argparse

import pandas as pd

KEEP, PLUS, MINUS = 2, 4, 0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", help="LABEL=DIAGNOSTICS_CSV")
    parser.add_argument("--block", type=int, default=1000)
    args = parser.parse_args()
    cols = []
    for label, path in (r.split("=", 1) for r in args.runs):
        d = pd.read_csv(path)
        d["block"] = (d["update"] * 16) // args.block * args.block
        d["J1 +0.2-keep"] = (d[f"a1_{PLUS}"] - d[f"a1_{KEEP}"]) / d.a1_std
        d["J2 +0.2-keep"] = (d[f"a2_{PLUS}"] - d[f"a2_{KEEP}"]) / d.a2_std
        d["J2 -0.2-keep"] = (d[f"a2_{MINUS}"] - d[f"a2_{KEEP}"]) / d.a2_std
        g = d.groupby("block")[["J1 +0.2-keep", "J2 +0.2-keep", "J2 -0.2-keep"]].mean().round(3)
        g.columns = [f"{label}: {c}" for c in g.columns]
        cols.append(g)
    table = pd.concat(cols, axis=1)
    header = ["episodes", *table.columns]
    print("| " + " | ".join(header) + " |\n|" + "---|" * len(header))
    for idx, row in table.iterrows():
        print("| " + " | ".join([str(idx)] + ["–" if pd.isna(v) else f"{v:+.3f}" for v in row]) + " |")


if __name__ == "__main__":
    main()
