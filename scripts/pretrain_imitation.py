"""The warm start of the shipped IDAS (ours, not the paper's): an actor that imitates a masked rule baseline.

    python scripts/pretrain_imitation.py --teacher fsm_idm_smooth --out runs/imitation_smooth.pt
    # then: idas-sumo train --config scenarios/train_smooth.toml  (its init_from is runs/imitation_smooth.pt)

The demonstrations alternate between the config's intelligent-world traffic and the paper suite's
generator (train_smooth.toml's traffic and learner are those of experiments/recipes/train_shipped.toml, the
default before it moved). docs/results.md ("What each method is") says how the shipped IDAS used it.
"""

from __future__ import annotations

import idas_sumo  # noqa: F401  (first: its OMP_WAIT_POLICY must be set before torch loads)

# isort: split
import argparse
import dataclasses
import time
from pathlib import Path

import numpy as np
import torch

from idas_sumo.agents.learner import Learner
from idas_sumo.baselines.policies import BASELINES
from idas_sumo.env.engine import EnvConfig, MergeEngine
from idas_sumo.env.scenario import TrafficConfig
from idas_sumo.resources import DEFAULT_NET_NAME, resolve_user_path
from idas_sumo.training.checkpoint import TrainingCheckpoint, save_checkpoint
from idas_sumo.training.config import load_train_config
from idas_sumo.training.imitation import collect_demonstrations, imitate


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--net", type=resolve_user_path, default=DEFAULT_NET_NAME)
    parser.add_argument("--config", type=resolve_user_path, default="scenarios/train_smooth.toml")
    parser.add_argument("--teacher", choices=tuple(BASELINES), default="idm")
    parser.add_argument("--episodes", type=int, default=200)
    parser.add_argument("--epochs", type=int, default=15)
    parser.add_argument("--lr", type=float, default=1e-3, help="actor and V learning rate while imitating")
    parser.add_argument("--seed", type=int, default=11)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()

    config = load_train_config(args.config)
    env_config = EnvConfig(max_episode_s=config.env.max_episode_s, safety_mask=config.env.safety_mask)
    engine = MergeEngine(args.net, copies=config.copies, seed=args.seed, config=env_config)
    rng = np.random.default_rng(args.seed)
    started = time.perf_counter()
    # The intelligent world's traffic and the paper suite's; a config in the first generator's traffic
    # (n_vehicles = 0, as train_shipped.toml) takes that generator's suite traffic, as the shipped imitation did.
    first = config.intelligent_traffic.n_vehicles == 0
    suite = (
        TrafficConfig(n_vehicles=0, min_vehicles_per_road=2, max_vehicles_per_road=8)
        if first
        else TrafficConfig()
    )
    demos = collect_demonstrations(
        engine, args.teacher, [config.intelligent_traffic, suite], args.episodes, rng
    )
    engine.close()
    print(
        f"{sum(len(e) for e in demos)} agent-steps from {args.episodes} episodes in {time.perf_counter() - started:.0f} s"
    )
    learner = Learner(dataclasses.replace(config.learner, lr_actor=args.lr, lr_value=args.lr), seed=args.seed)
    for row in imitate(learner, demos, args.epochs, torch.Generator().manual_seed(args.seed)):
        print(
            f"epoch {row.epoch}: cross-entropy {row.cross_entropy:.3f}, agreement {row.agreement:.3f}, V loss {row.value_loss:.2f}"
        )
    save_checkpoint(
        args.out,
        TrainingCheckpoint(
            learner=learner.state_dict(),
            config=config,
            stage=f"imitation-{args.teacher}",
            stage_index=0,
            episode=0,
            global_episode=0,
            numpy_rng=dict(rng.bit_generator.state),
            torch_rng=torch.Generator().manual_seed(args.seed).get_state(),
        ),
    )
    print(f"wrote {args.out} (use it as init_from)")


if __name__ == "__main__":
    main()
