"""``idas-sumo train`` with per-update diagnostics of the learner (issue 36, the stage-2 collapse).

Wraps ``Learner.update`` (every round updates in this process on its whole batch,
``RolloutWorkers.train_round_here``) and, for every update, writes one row to ``<out>/diagnostics.csv``: the batch's
action histogram, how often the mask leaves the hard brake alone, the ego speed distribution, the mean A1 and
A2 (raw, before any standardisation) per action, V and Q and their targets, the policy's entropy and the KL
between the policies before and after the step (on the batch's observations). Everything else is the ordinary
``train`` command (its ``metrics.csv`` keeps the outcomes per episode). Run with ``--workers 1`` so that
collection and update share this process:

    python experiments/stage2_collapse/instrumented_train.py --config experiments/recipes/train_smooth_stage2_full.toml \
        --stage intelligent --episodes 6000 --workers 1 --out /tmp/s2/base
"""

from __future__ import annotations

import csv
import sys
from pathlib import Path

import numpy as np
import torch

from idas_sumo.agents import learner as learner_module  # (idas_sumo before torch: see its import warning)
from idas_sumo.cli import main as cli_main
from idas_sumo.env.actions import HARD_BRAKE, N_ACTIONS
from idas_sumo.env.layout import SPEED_SCALE_MPS
from idas_sumo.training.workers import RolloutWorkers

KL_ROWS = 4096  # rows of the batch the KL between consecutive policies is measured on


def _out_dir(argv: list[str]) -> Path:
    return Path(argv[argv.index("--out") + 1])


def _per_action(values: torch.Tensor, actions: np.ndarray) -> list[float]:
    v = values.detach().cpu().numpy().astype(np.float64)
    return [float(v[actions == a].mean()) if (actions == a).any() else float("nan") for a in range(N_ACTIONS)]


def install(path: Path) -> None:
    original = learner_module.Learner.update
    state = {"n": 0, "writer": None, "file": None}

    def update(self: learner_module.Learner, batch: learner_module.Batch) -> dict[str, float]:
        n = batch.action.numel()
        if n == 0:
            return original(self, batch)
        rows = torch.randperm(n, generator=torch.Generator().manual_seed(state["n"]))[:KL_ROWS]
        obs, mask = batch.obs[rows], batch.mask[rows].bool()
        with torch.no_grad():
            before = self.actor.distribution(obs, mask)
            probs_before = before.probs.clone()
        stats = original(self, batch)
        with torch.no_grad():
            after = self.actor.distribution(obs, mask)
            kl = torch.distributions.kl_divergence(before, after).mean().item()
        record = self.last_update
        actions = batch.action.numpy()
        speed = batch.obs[:, 0].numpy() * SPEED_SCALE_MPS
        row: dict[str, float | int] = {"update": state["n"], "rows": n, **stats, "kl": kl}
        hist = np.bincount(actions, minlength=N_ACTIONS) / n
        row |= {f"share_a{a}": float(hist[a]) for a in range(N_ACTIONS)}
        row |= {f"p_a{a}": float(probs_before[:, a].mean()) for a in range(N_ACTIONS)}
        row["forced_brake"] = float((batch.mask.numpy().sum(1) == 1).mean())
        row["brake_chosen_free"] = float(((actions == HARD_BRAKE) & (batch.mask.numpy().sum(1) > 1)).mean())
        row |= {
            "speed_mean": float(speed.mean()),
            "speed_p10": float(np.percentile(speed, 10)),
            "standstill": float((speed < 0.5).mean()),
        }
        if record is not None:
            row |= {f"a1_{a}": x for a, x in enumerate(_per_action(record.value.advantage, actions))}
            row["v_target_mean"] = float(record.value.target.mean())
            if record.central is not None:
                row |= {f"a2_{a}": x for a, x in enumerate(_per_action(record.central.advantage, actions))}
                row["q_target_mean"] = float(record.central.target.mean())
                row["a2_std"] = float(record.central.advantage.std())
                row["a1_std"] = float(record.value.advantage.std())
        if state["writer"] is None:
            path.parent.mkdir(parents=True, exist_ok=True)
            state["file"] = path.open("w", newline="", encoding="utf-8")
            state["writer"] = csv.DictWriter(state["file"], fieldnames=list(row), extrasaction="ignore")
            state["writer"].writeheader()
        state["writer"].writerow(row)
        state["file"].flush()
        state["n"] += 1
        return stats

    learner_module.Learner.update = update  # type: ignore[method-assign]
    # Training rounds compute their gradients by groups (where they were collected); this script needs each
    # update's whole batch, so its rounds update here on all of it.
    RolloutWorkers.train_round = RolloutWorkers.train_round_here  # type: ignore[method-assign]


if __name__ == "__main__":
    argv = sys.argv[1:]
    if "--force" in argv:
        argv.remove("--force")
    install(_out_dir(argv).with_name(_out_dir(argv).name + "_diagnostics.csv"))
    sys.exit(cli_main(["train", *argv]))
