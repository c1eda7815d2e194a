"""Train sb3-contrib's MaskablePPO on K ego worlds in one SUMO (make_vec), then evaluate it briefly.

    pip install "idas-sumo[sb3]"      # or: pip install sb3-contrib
    python examples/sb3_maskable_ppo.py --timesteps 512 --num-envs 4

``gymnasium.make_vec("idas_sumo/Merge-v0", num_envs=K, vectorization_mode="vector_entry_point")`` runs K
single-ego worlds as slots of one SUMO simulation (idas_sumo/env/vector_env.py). SB3 takes its own
``VecEnv``, not Gymnasium's, so ``MaskableVecEnv`` below adapts it: SB3 resets a world in the step that
ends its episode; here the world's next episode starts with the next wave, so until then the world's rows
are idle ones (zero observation, reward 0, only action 0 allowed: no policy gradient, and MaskablePPO
never picks a masked action). MaskablePPO reads the (K, 7) masks through ``env_method("action_masks")``.
``--num-envs 1`` is the plain single-ego env. A few hundred steps only show that the pieces fit; a useful
ego policy takes tens of thousands of steps.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Sequence
from typing import Any

# isort: off
import idas_sumo  # noqa: F401  (registers idas_sumo/Merge-v0; before torch, so torch's idle threads sleep)

# isort: on
import gymnasium
import numpy as np
from sb3_contrib import MaskablePPO
from sb3_contrib.common.maskable.evaluation import evaluate_policy
from sb3_contrib.common.maskable.utils import get_action_masks
from stable_baselines3.common.logger import Logger
from stable_baselines3.common.vec_env import VecEnv, VecMonitor

from idas_sumo.env.engine import EnvConfig
from idas_sumo.env.vector_env import MergeVectorEnv


class MaskableVecEnv(VecEnv):
    """SB3's ``VecEnv`` over make_vec's ``MergeVectorEnv``, with ``action_masks`` for MaskablePPO."""

    def __init__(self, envs: MergeVectorEnv) -> None:
        self.envs = envs
        super().__init__(envs.num_envs, envs.single_observation_space, envs.single_action_space)
        self._actions = np.zeros(envs.num_envs, dtype=np.int64)

    def reset(self) -> np.ndarray:
        seed = self._seeds[0]  # SB3's seed(s) gives s, s + 1, ...: the vector env's own convention
        obs, _ = self.envs.reset(seed=seed)
        self._reset_seeds()
        return obs

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = np.asarray(actions, dtype=np.int64).reshape(self.num_envs)

    def step_wait(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[dict[str, Any]]]:
        obs, rewards, terminated, truncated, _ = self.envs.step(self._actions)
        dones = terminated | truncated
        infos: list[dict[str, Any]] = [{} for _ in range(self.num_envs)]
        for k in np.flatnonzero(dones).tolist():
            infos[k] = {"terminal_observation": obs[k].copy(), "TimeLimit.truncated": bool(truncated[k])}
            obs[k] = 0.0  # SB3 wants the next episode's first observation: the world is idle until then
        return obs, rewards.astype(np.float32), dones, infos

    def env_method(
        self, method_name: str, *args: Any, indices: int | Sequence[int] | None = None, **kwargs: Any
    ) -> list[Any]:
        if method_name != "action_masks":
            raise AttributeError(f"MaskableVecEnv has no per-world method {method_name!r}")
        masks = self.envs.action_masks()
        return [masks[k] for k in self._get_indices(indices)]

    def get_attr(self, attr_name: str, indices: int | Sequence[int] | None = None) -> list[Any]:
        value = getattr(self.envs, attr_name)  # an AttributeError says has_attr() is False
        return [value for _ in self._get_indices(indices)]

    def set_attr(self, attr_name: str, value: Any, indices: int | Sequence[int] | None = None) -> None:
        raise AttributeError("the worlds of one SUMO share their attributes: set them on the vector env")

    def env_is_wrapped(self, wrapper_class: type, indices: int | Sequence[int] | None = None) -> list[bool]:
        return [False for _ in self._get_indices(indices)]

    def close(self) -> None:
        self.envs.close()


def main(argv: list[str] | None = None) -> dict[str, float]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--timesteps", type=int, default=512, help="training world-steps (default: 512)")
    parser.add_argument("--num-envs", type=int, default=4, help="worlds in the one SUMO (default: 4)")
    parser.add_argument("--episodes", type=int, default=2, help="evaluation episodes (default: 2)")
    parser.add_argument("--episode-s", type=float, default=30.0, help="episode timeout, s (default: 30)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the env and the policy (default: 0)")
    args = parser.parse_args(argv)

    # Short episodes keep the demo short; the paper's horizon is the default EnvConfig().
    envs = gymnasium.make_vec(
        "idas_sumo/Merge-v0",
        num_envs=args.num_envs,
        vectorization_mode="vector_entry_point",
        config=EnvConfig(max_episode_s=args.episode_s),
    )
    assert isinstance(envs, MergeVectorEnv)
    env = VecMonitor(MaskableVecEnv(envs))
    env.seed(args.seed)
    n_steps = max(128 // args.num_envs, 8)
    model = MaskablePPO(
        "MlpPolicy", env, n_steps=n_steps, batch_size=64, n_epochs=2, seed=args.seed, device="cpu", verbose=0
    )
    model.set_logger(Logger(folder=None, output_formats=[]))  # no empty SB3-<date> folder in the temp dir
    start = time.perf_counter()
    model.learn(total_timesteps=args.timesteps)
    seconds = time.perf_counter() - start
    print(
        f"trained {model.num_timesteps} world-steps on {args.num_envs} worlds in {seconds:.1f} s "
        f"({model.num_timesteps / seconds:,.0f} world-steps/s with the updates)"
    )

    # One step by hand: the masks come from the env, the policy never picks a masked action.
    obs = env.reset()
    masks = get_action_masks(env)
    assert masks.shape == (args.num_envs, 7)
    actions, _ = model.predict(obs, action_masks=masks, deterministic=True)
    assert masks[np.arange(args.num_envs), actions].all()
    k = int(
        np.argmax(masks.sum(axis=1))
    )  # a world whose ego is on the road (an idle one allows action 0 only)
    print(
        f"allowed actions of world {k}: {np.flatnonzero(masks[k]).tolist()}, policy picks {int(actions[k])}"
    )

    mean, std = evaluate_policy(model, env, n_eval_episodes=args.episodes, deterministic=True)
    print(f"evaluation over {args.episodes} episodes: return {mean:.2f} ± {std:.2f}")
    env.close()
    return {"timesteps": model.num_timesteps, "mean_return": float(mean)}


if __name__ == "__main__":
    main()
