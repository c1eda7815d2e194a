"""Train sb3-contrib's MaskablePPO on the single-ego Gymnasium env, then evaluate it briefly.

    pip install "idas-sumo[sb3]"      # or: pip install sb3-contrib
    python examples/sb3_maskable_ppo.py --timesteps 512

MaskablePPO finds the env's ``action_masks()`` method through gymnasium's wrappers and SB3's vector env,
so the env needs no ``ActionMasker`` wrapper. A few hundred steps only show that the pieces fit; a useful
ego policy takes tens of thousands of steps.
"""

from __future__ import annotations

import argparse

import gymnasium
import numpy as np
from sb3_contrib import MaskablePPO
from sb3_contrib.common.maskable.evaluation import evaluate_policy
from sb3_contrib.common.maskable.utils import get_action_masks
from stable_baselines3.common.logger import Logger
from stable_baselines3.common.monitor import Monitor

import idas_sumo  # noqa: F401  (registers idas_sumo/Merge-v0)
from idas_sumo.env.engine import EnvConfig


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--timesteps", type=int, default=512, help="training steps (default: 512)")
    parser.add_argument("--episodes", type=int, default=2, help="evaluation episodes (default: 2)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the env and the policy (default: 0)")
    args = parser.parse_args()

    # 30 s episodes keep the demo short; the paper's horizon is the default EnvConfig().
    env = Monitor(gymnasium.make("idas_sumo/Merge-v0", config=EnvConfig(max_episode_s=30.0)))
    model = MaskablePPO("MlpPolicy", env, n_steps=128, batch_size=64, n_epochs=2, seed=args.seed, verbose=0)
    model.set_logger(Logger(folder=None, output_formats=[]))  # no empty SB3-<date> folder in the temp dir
    model.learn(total_timesteps=args.timesteps)
    print(f"trained {model.num_timesteps} steps")

    # One step by hand: the mask comes from the env, the policy never picks a masked action.
    obs, info = env.reset(seed=args.seed)
    masks = get_action_masks(env)
    assert np.array_equal(masks, info["action_mask"].astype(bool))
    action, _ = model.predict(obs, action_masks=masks, deterministic=True)
    print(f"allowed actions {np.flatnonzero(masks).tolist()}, policy picks {int(action)}")

    mean, std = evaluate_policy(model, env, n_eval_episodes=args.episodes, deterministic=True)
    print(f"evaluation over {args.episodes} episodes: return {mean:.2f} ± {std:.2f}")
    env.close()


if __name__ == "__main__":
    main()
