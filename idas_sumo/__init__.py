"""idas-sumo: interaction-aware merging policies (IDAS, IROS 2019) trained and evaluated in SUMO."""

from gymnasium.envs.registration import register, registry

__version__ = "0.1.0"

if "idas_sumo/Merge-v0" not in registry:
    register(id="idas_sumo/Merge-v0", entry_point="idas_sumo.env.gym_env:MergeEnv", max_episode_steps=None)
