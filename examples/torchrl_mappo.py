"""MAPPO with TorchRL on the batched multi-agent merge: every car of K worlds an agent, masks respected.

    pip install 'idas-sumo[torchrl]'
    python examples/torchrl_mappo.py --frames 20000 --worlds 8

The env is ``MergeTorchRLEnv`` (idas_sumo/env/torchrl_env.py): K worlds in one SUMO, S fixed agent slots
each (group ``"agents"``, shape (K, S)); a slot without a car on the road is inactive (zero observation,
only action 0 allowed). The rest follows TorchRL's multi-agent PPO tutorial: a shared-parameter actor
(``MultiAgentMLP``, decentralised) whose logits are masked by ``MaskedCategorical`` with the env's
``action_mask``, a centralised critic over every slot of a world (MAPPO), GAE per slot (a slot's
``done`` cuts its returns where its car ended), and ``ClipPPOLoss`` with ``loss_mask_key`` = the slots'
``active`` flag, so inactive slots are left out of every loss term (objective, critic, entropy). Every
collected action is checked against its mask (asserted).

A few hundred steps only show that the pieces fit; a useful policy takes far more.
"""

from __future__ import annotations

import argparse
import time

# isort: off
import idas_sumo  # noqa: F401  (before torch, so torch's idle threads sleep)

# isort: on
import torch
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.collectors import Collector
from torchrl.data import LazyTensorStorage, ReplayBuffer, SamplerWithoutReplacement
from torchrl.modules import MaskedCategorical, MultiAgentMLP, ProbabilisticActor
from torchrl.objectives import ClipPPOLoss, ValueEstimators

from idas_sumo.env.actions import N_ACTIONS
from idas_sumo.env.engine import EnvConfig
from idas_sumo.env.layout import OBS_DIM
from idas_sumo.env.scenario import TrafficConfig
from idas_sumo.env.torchrl_env import GROUP, MergeTorchRLEnv


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=20_000, help="world-steps in all (default: 20000)")
    parser.add_argument("--frames-per-batch", type=int, default=512, help="world-steps per rollout")
    parser.add_argument("--worlds", type=int, default=8, help="worlds in the one SUMO (default: 8)")
    parser.add_argument("--cars", type=int, default=8, help="cars per scenario, = agent slots (default: 8)")
    parser.add_argument("--episode-s", type=float, default=30.0, help="episode timeout, s (default: 30)")
    parser.add_argument("--lr", type=float, default=3e-4)
    parser.add_argument("--epochs", type=int, default=2, help="passes over each rollout (default: 2)")
    parser.add_argument("--minibatch", type=int, default=64, help="world-steps per minibatch")
    parser.add_argument("--seed", type=int, default=0)
    return parser.parse_args(argv)


def make_modules(n_slots: int, n_actions: int) -> tuple[ProbabilisticActor, TensorDictModule]:
    """The masked shared actor and the centralised critic (one value per slot from all slots' inputs)."""
    actor_net = MultiAgentMLP(
        n_agent_inputs=OBS_DIM,
        n_agent_outputs=n_actions,
        n_agents=n_slots,
        centralised=False,
        share_params=True,
        depth=2,
        num_cells=64,
        activation_class=nn.Tanh,
    )
    actor = ProbabilisticActor(
        TensorDictModule(actor_net, in_keys=[(GROUP, "observation")], out_keys=[(GROUP, "logits")]),
        in_keys={"logits": (GROUP, "logits"), "mask": (GROUP, "action_mask")},
        out_keys=[(GROUP, "action")],
        distribution_class=MaskedCategorical,
        return_log_prob=True,
        log_prob_key=(GROUP, "action_log_prob"),
    )
    critic_net = MultiAgentMLP(
        n_agent_inputs=OBS_DIM,
        n_agent_outputs=1,
        n_agents=n_slots,
        centralised=True,
        share_params=True,
        depth=2,
        num_cells=64,
        activation_class=nn.Tanh,
    )
    critic = TensorDictModule(critic_net, in_keys=[(GROUP, "observation")], out_keys=[(GROUP, "state_value")])
    return actor, critic


def masked_actions(data: object) -> int:
    """How many collected actions their slot's mask forbids."""
    action = data.get((GROUP, "action"))  # type: ignore[attr-defined]
    mask = data.get((GROUP, "action_mask"))  # type: ignore[attr-defined]
    return int((~mask.gather(-1, action.unsqueeze(-1))).sum())


def main(argv: list[str] | None = None) -> dict[str, float]:
    args = parse_args(argv)
    torch.manual_seed(args.seed)
    traffic = TrafficConfig(n_vehicles=args.cars, max_vehicles_per_road=args.cars)
    env = MergeTorchRLEnv(
        args.worlds, traffic=traffic, config=EnvConfig(max_episode_s=args.episode_s), seed=args.seed
    )
    _, n_slots = env.marl.shape
    actor, critic = make_modules(n_slots, N_ACTIONS)
    loss = ClipPPOLoss(actor, critic, clip_epsilon=0.2, entropy_coeff=0.01, normalize_advantage=False)
    loss.set_keys(
        reward=(GROUP, "reward"),
        action=(GROUP, "action"),
        sample_log_prob=(GROUP, "action_log_prob"),
        value=(GROUP, "state_value"),
        done=(GROUP, "done"),
        terminated=(GROUP, "terminated"),
    )
    loss.loss_mask_key = (GROUP, "active")  # an inactive slot decides nothing
    loss.make_value_estimator(ValueEstimators.GAE, gamma=0.99, lmbda=0.95)
    optimizer = torch.optim.Adam(loss.parameters(), args.lr)
    collector = Collector(
        env,
        actor,
        frames_per_batch=args.frames_per_batch,
        total_frames=args.frames,
        device="cpu",
        auto_register_policy_transforms=False,
    )
    buffer = ReplayBuffer(
        storage=LazyTensorStorage(args.frames_per_batch),
        sampler=SamplerWithoutReplacement(),
        batch_size=args.minibatch,
    )
    stats = {"frames": 0.0, "agent_steps": 0.0, "masked_actions": 0.0, "env_s": 0.0}
    start = time.perf_counter()
    for data in collector:
        stats["masked_actions"] += masked_actions(data)
        assert stats["masked_actions"] == 0, f"{stats['masked_actions']:.0f} masked actions taken"
        stats["frames"] += data.numel()
        stats["agent_steps"] += float(data.get((GROUP, "active")).sum())
        with torch.no_grad():
            loss.value_estimator(
                data, params=loss.critic_network_params, target_params=loss.target_critic_network_params
            )
        buffer.extend(data.reshape(-1))
        for _ in range(args.epochs):
            for _ in range(len(buffer) // args.minibatch):
                parts = loss(buffer.sample())
                total = parts["loss_objective"] + parts["loss_critic"] + parts["loss_entropy"]
                optimizer.zero_grad()
                total.backward()
                nn.utils.clip_grad_norm_(loss.parameters(), 1.0)
                optimizer.step()
    wall = time.perf_counter() - start
    collector.shutdown()
    env.close()
    stats["wall_s"] = wall
    print(
        f"{int(stats['frames'])} world-steps, {int(stats['agent_steps'])} agent-steps in {wall:.1f} s: "
        f"{stats['frames'] / wall:.0f} world-steps/s, {stats['agent_steps'] / wall:.0f} agent-steps/s "
        f"(training included); masked actions taken: {int(stats['masked_actions'])}"
    )
    return stats


if __name__ == "__main__":
    main()
