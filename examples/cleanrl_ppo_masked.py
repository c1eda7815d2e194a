"""PPO with action masks on make_vec, in one file (CleanRL style): K ego worlds in one SUMO.

    python examples/cleanrl_ppo_masked.py --total-steps 20000 --num-envs 16

Each world is the single-ego ``MergeEnv``; ``gymnasium.make_vec`` runs K of them as slots of one SUMO
simulation (idas_sumo/env/vector_env.py). Two things differ from CleanRL's ppo.py:

- masks: the policy's logits are masked with ``envs.action_masks()`` (the same as ``info["action_mask"]``),
  so a masked action is never sampled (asserted at every step);
- rows that are no decision are left out of the loss: idle rows (``info["idle"]``: the world waits for the
  next wave of episodes) and the row of an episode's last observation (the next step is the reset step,
  Gymnasium's next-step autoreset, and ignores the action).

A few hundred steps only show that the pieces fit; a useful ego policy takes tens of thousands.
"""

from __future__ import annotations

import argparse
import time

# isort: off
import idas_sumo  # noqa: F401  (registers idas_sumo/Merge-v0; before torch, so torch's idle threads sleep)

# isort: on
import gymnasium
import numpy as np
import torch
from torch import nn

from idas_sumo.env.engine import EnvConfig


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--total-steps", type=int, default=20_000, help="vector steps x worlds (default: 20000)"
    )
    parser.add_argument("--num-envs", type=int, default=8, help="worlds in the one SUMO (default: 8)")
    parser.add_argument("--num-steps", type=int, default=64, help="vector steps per rollout (default: 64)")
    parser.add_argument("--episode-s", type=float, default=30.0, help="episode timeout, s (default: 30)")
    parser.add_argument("--lr", type=float, default=3e-4, help="Adam learning rate (default: 3e-4)")
    parser.add_argument("--gamma", type=float, default=0.99)
    parser.add_argument("--gae-lambda", type=float, default=0.95)
    parser.add_argument("--epochs", type=int, default=2, help="passes over each rollout (default: 2)")
    parser.add_argument("--minibatches", type=int, default=4)
    parser.add_argument("--clip", type=float, default=0.2)
    parser.add_argument("--ent-coef", type=float, default=0.01)
    parser.add_argument("--vf-coef", type=float, default=0.5)
    parser.add_argument("--seed", type=int, default=0)
    return parser.parse_args(argv)


class Agent(nn.Module):
    def __init__(self, obs_dim: int, n_actions: int) -> None:
        super().__init__()
        self.critic = nn.Sequential(
            nn.Linear(obs_dim, 64), nn.Tanh(), nn.Linear(64, 64), nn.Tanh(), nn.Linear(64, 1)
        )
        self.actor = nn.Sequential(
            nn.Linear(obs_dim, 64), nn.Tanh(), nn.Linear(64, 64), nn.Tanh(), nn.Linear(64, n_actions)
        )

    def value(self, obs: torch.Tensor) -> torch.Tensor:
        return self.critic(obs).squeeze(-1)

    def act(
        self, obs: torch.Tensor, mask: torch.Tensor, action: torch.Tensor | None = None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """(action, its log-prob, entropy, value); masked actions get probability 0."""
        logits = self.actor(obs).masked_fill(~mask, -1e8)
        dist = torch.distributions.Categorical(logits=logits)
        if action is None:
            action = dist.sample()
        return action, dist.log_prob(action), dist.entropy(), self.value(obs)


def gae(
    rewards: torch.Tensor,
    values: torch.Tensor,
    decides: torch.Tensor,
    next_value: torch.Tensor,
    next_decides: torch.Tensor,
    args: argparse.Namespace,
) -> torch.Tensor:
    """GAE over each world's decisions: a decision's next row is its next decision, or its episode's end
    (no bootstrap there); rows that decide nothing get 0."""
    t_len = len(rewards)
    advantages = torch.zeros_like(rewards)
    last_gae = torch.zeros(rewards.shape[1])
    for t in reversed(range(t_len)):
        later, later_value = (decides[t + 1], values[t + 1]) if t + 1 < t_len else (next_decides, next_value)
        delta = rewards[t] + args.gamma * later_value * later - values[t]
        last_gae = torch.where(decides[t], delta + args.gamma * args.gae_lambda * later * last_gae, 0.0)
        advantages[t] = last_gae
    return advantages


def update(
    agent: Agent,
    optimizer: torch.optim.Optimizer,
    batch: list[torch.Tensor],
    logprobs: torch.Tensor,
    advantages: torch.Tensor,
    targets: torch.Tensor,
    rows: torch.Tensor,
    args: argparse.Namespace,
) -> None:
    """PPO's clipped update on the decision ``rows`` (flat indices) of the rollout; ``batch``: their
    observations, masks and actions."""
    b_obs, b_mask, b_act = batch
    b_logp, b_target = logprobs.reshape(-1)[rows], targets.reshape(-1)[rows]
    b_adv = advantages.reshape(-1)[rows]
    b_adv = (b_adv - b_adv.mean()) / (b_adv.std() + 1e-8)
    for _ in range(args.epochs):
        for mb in torch.randperm(len(rows)).chunk(args.minibatches):
            _, logp, entropy, value = agent.act(b_obs[mb], b_mask[mb], b_act[mb])
            ratio = (logp - b_logp[mb]).exp()
            adv = b_adv[mb]
            pg_loss = torch.max(-adv * ratio, -adv * ratio.clamp(1 - args.clip, 1 + args.clip)).mean()
            v_loss = 0.5 * ((value - b_target[mb]) ** 2).mean()
            loss = pg_loss + args.vf_coef * v_loss - args.ent_coef * entropy.mean()
            optimizer.zero_grad()
            loss.backward()
            nn.utils.clip_grad_norm_(agent.parameters(), 0.5)
            optimizer.step()


def main(argv: list[str] | None = None) -> dict[str, float]:
    args = parse_args(argv)
    torch.manual_seed(args.seed)
    envs = gymnasium.make_vec(
        "idas_sumo/Merge-v0",
        num_envs=args.num_envs,
        vectorization_mode="vector_entry_point",
        config=EnvConfig(max_episode_s=args.episode_s),
    )
    k, t_len = args.num_envs, args.num_steps
    obs_dim, n_actions = envs.single_observation_space.shape[0], int(envs.single_action_space.n)
    agent = Agent(obs_dim, n_actions)
    optimizer = torch.optim.Adam(agent.parameters(), lr=args.lr, eps=1e-5)

    # Rollout storage: row t is what the agent saw and did before vector step t.
    obs_buf = torch.zeros((t_len, k, obs_dim))
    mask_buf = torch.zeros((t_len, k, n_actions), dtype=torch.bool)
    actions = torch.zeros((t_len, k), dtype=torch.long)
    logprobs, values, rewards = torch.zeros((t_len, k)), torch.zeros((t_len, k)), torch.zeros((t_len, k))
    decides = torch.zeros((t_len, k), dtype=torch.bool)
    """The world's ego acts on that row (not idle, not an episode's last observation)."""

    next_obs, info = envs.reset(seed=args.seed)
    next_decides = torch.as_tensor(~info["idle"])
    steps, decisions, episodes, returns, masked_taken = 0, 0, 0, [], 0
    episode_return = np.zeros(k)
    start = time.perf_counter()
    while steps < args.total_steps:
        for t in range(t_len):
            mask = torch.as_tensor(envs.action_masks())
            obs_buf[t], mask_buf[t], decides[t] = torch.as_tensor(next_obs), mask, next_decides
            with torch.no_grad():
                action, logprobs[t], _, values[t] = agent.act(obs_buf[t], mask)
            masked_taken += int((~mask.gather(1, action[:, None])).sum())
            actions[t] = action
            next_obs, reward, terminated, truncated, info = envs.step(action.numpy())
            rewards[t] = torch.as_tensor(reward, dtype=torch.float32)
            ended = terminated | truncated
            next_decides = torch.as_tensor(~info["idle"] & ~ended)
            episode_return += reward
            for w in np.flatnonzero(ended):
                returns.append(float(episode_return[w]))
                episode_return[w] = 0.0
            episodes += int(ended.sum())
            decisions += int(decides[t].sum())
            steps += k
        with torch.no_grad():
            next_value = agent.value(torch.as_tensor(next_obs))
        advantages = gae(rewards, values, decides, next_value, next_decides, args)
        targets = advantages + values
        rows = torch.nonzero(decides.reshape(-1)).squeeze(1)
        if len(rows) < 2:
            continue
        flat = (obs_buf.reshape(-1, obs_dim), mask_buf.reshape(-1, n_actions), actions.reshape(-1))
        update(agent, optimizer, [x[rows] for x in flat], logprobs, advantages, targets, rows, args)
    seconds = time.perf_counter() - start
    envs.close()
    assert masked_taken == 0, f"{masked_taken} masked actions taken"
    mean_return = float(np.mean(returns)) if returns else float("nan")
    print(
        f"{steps} world-steps ({decisions} decisions) in {seconds:.1f} s ({steps / seconds:,.0f} world-steps/s "
        f"with the updates), {episodes} episodes, "
        f"mean return {mean_return:.2f}, masked actions taken: {masked_taken}"
    )
    return {"steps": steps, "decisions": decisions, "episodes": episodes, "masked_taken": masked_taken}


if __name__ == "__main__":
    main()
