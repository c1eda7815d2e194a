"""Block means of an instrumented run: ``python summarise.py RUN_DIR [EPISODES_PER_BLOCK]``.

Reads ``RUN_DIR/metrics.csv`` (outcomes per episode), ``RUN_DIR_diagnostics.csv`` (per update, written by
``instrumented_train.py``) and ``RUN_DIR/validation.csv``."""

from __future__ import annotations

import sys
from pathlib import Path

import pandas as pd

run = Path(sys.argv[1])
block = int(sys.argv[2]) if len(sys.argv) > 2 else 500
pd.set_option("display.width", 250)
m = pd.read_csv(run / "metrics.csv")
m["block"] = m.episode // block * block
outcome = m.groupby("block")[
    ["success", "perfect", "timed_out", "collisions", "impede", "flow", "finish"]
].mean()
outcome["with_collision"] = m.assign(c=m.collisions > 0).groupby("block").c.mean()
print(outcome.round(3).to_string())
diag_path = run.with_name(run.name + "_diagnostics.csv")
if diag_path.exists():
    d = pd.read_csv(diag_path)
    d["block"] = (d["update"] * 16) // block * block
    cols = [
        "entropy",
        "kl",
        "v_mean",
        "q_mean",
        "q_target_mean",
        "a1_std",
        "a2_std",
        "speed_mean",
        "standstill",
    ]
    cols += [f"share_a{a}" for a in range(7)] + ["forced_brake", "brake_chosen_free"]
    print(d.groupby("block")[cols].mean().round(3).to_string())
    print("A2 (raw) per action taken")
    print(d.groupby("block")[[f"a2_{a}" for a in range(7)]].mean().round(2).to_string())
    print("A1 (raw) per action taken")
    print(d.groupby("block")[[f"a1_{a}" for a in range(7)]].mean().round(2).to_string())
v = run / "validation.csv"
if v.exists():
    val = pd.read_csv(v)
    print(
        val[
            [
                c
                for c in val.columns
                if c
                in (
                    "episode",
                    "global_episode",
                    "success_rate",
                    "perfect_rate",
                    "joint_return",
                    "mean_end_time_s",
                )
            ]
        ].to_string()
    )
