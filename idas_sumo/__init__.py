"""idas-sumo: interaction-aware merging policies (IDAS, IROS 2019) trained and evaluated in SUMO."""

import os
import sys
import warnings

# Before anything loads torch's OpenMP runtime: idle OpenMP threads sleep instead of spinning, since spinning
# threads starve SUMO and the other workers on a small machine (docs/performance.md). A user's own setting wins.
# The runtime reads the policy once, when torch loads it: a script that imports torch first keeps spinning
# threads, so say so.
if "OMP_WAIT_POLICY" not in os.environ and "torch" in sys.modules:
    warnings.warn(
        "torch was imported before idas_sumo, so its idle OpenMP threads spin: beside other processes "
        "training can run several times slower; import idas_sumo first or set OMP_WAIT_POLICY=PASSIVE",
        RuntimeWarning,
        stacklevel=2,
    )
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from gymnasium.envs.registration import register, registry

__version__ = "0.1.0"

if "idas_sumo/Merge-v0" not in registry:
    # make_vec(..., vectorization_mode="vector_entry_point"): K worlds in one SUMO (env/vector_env.py).
    register(
        id="idas_sumo/Merge-v0",
        entry_point="idas_sumo.env.gym_env:MergeEnv",
        vector_entry_point="idas_sumo.env.vector_env:MergeVectorEnv",
        max_episode_steps=None,
    )
