"""Collect a fixed set of stage-2 episodes with a checkpoint's policy and save the learner's batch (issue 36).

The same collection as ``experiments/stage2_collapse/probe_signal.py`` (the shipped stage-2 recipe's traffic,
``collect_episodes`` → ``batch_from_episodes``), saved with each row's episode index so that critics can be fitted
offline on some episodes and scored on others (``fit_critic.py``).

    python experiments/stage2_critic/collect.py POLICY OUT.pt [--episodes 96] [--seed 11]
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np
import torch

from idas_sumo.agents.rollout import batch_from_episodes

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "stage2_collapse"))
from probe_signal import collect


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("policy", type=Path)
    parser.add_argument("out", type=Path)
    parser.add_argument("--episodes", type=int, default=96)
    parser.add_argument("--seed", type=int, default=11)
    args = parser.parse_args()
    data, gamma = collect(args.policy, args.episodes, args.seed)
    batch = batch_from_episodes(data, central=True)
    episode = np.concatenate([np.full(len(e), i) for i, e in enumerate(data)])
    fields = {f.name: getattr(batch, f.name) for f in dataclasses.fields(batch)}
    timed_out = float(np.mean([e.stats.timed_out for e in data]))
    torch.save({"batch": fields, "episode": torch.from_numpy(episode), "gamma": gamma}, args.out)
    print(
        f"{args.policy}: {len(data)} episodes, {len(episode)} rows, timed out {timed_out:.0%} -> {args.out}"
    )


if __name__ == "__main__":
    main()
