"""Methods an evaluation can run, behind one interface: given the simulation and some agents, pick
their actions. Baselines read the traffic snapshot; learned policies read observations."""

from __future__ import annotations

import difflib
from pathlib import Path

import numpy as np
import numpy.typing as npt

from idas_sumo.baselines.policies import BASELINES, baseline_policy
from idas_sumo.env.core import MergeSimulation, PolicyFn
from idas_sumo.errors import InputError
from idas_sumo.resources import POLICY_DIR

LEARNED_METHODS: dict[str, str] = {"idas": "idas.pt", "idas_v": "idas_v.pt", "idas_direct": "idas_direct.pt"}
METHODS: tuple[str, ...] = (*LEARNED_METHODS, *BASELINES)
METHOD_LABELS: dict[str, str] = {
    "idas": "IDAS",
    "idas_v": "IDAS-V",
    "idas_direct": "IDAS-direct",
    "idm": "IDM",
    "fsm_idm": "FSM+IDM",
}


def check_method(name: str, flag: str = "--baseline", also: tuple[str, ...] = ()) -> str:
    """``name`` if it is a method (or one of ``also``, e.g. "all"); else an InputError with a hint."""
    choices = (*METHODS, *also)
    if name not in choices:
        # Lower case first, so that "IDAS" is pointed to "idas" (difflib compares case-sensitively).
        close = difflib.get_close_matches(name.lower(), choices, n=1, cutoff=0.4)
        hint = f' (did you mean "{close[0]}"?)' if close else ""
        raise InputError(f"{flag}: unknown method {name!r}{hint}; choose from {', '.join(choices)}")
    return name


def learned_policy(path: Path, seed: int = 0) -> PolicyFn:
    """A shipped or trained actor, acting greedily (the most probable allowed action)."""
    from idas_sumo.agents.checkpoint_file import load_actor  # lazy: torch only for learned methods

    actor = load_actor(path)
    import torch

    generator = torch.Generator().manual_seed(seed)

    def policy(
        sim: MergeSimulation, agents: list[str], obs: npt.NDArray[np.float32], masks: npt.NDArray[np.int8]
    ) -> npt.NDArray[np.int64]:
        return actor.act(obs, masks, generator, deterministic=True)

    return policy


def resolve_policy(name: str, policy_path: Path | None = None, seed: int = 0) -> PolicyFn:
    """The policy for a method name; learned methods load ``policy_path`` or the shipped file."""
    check_method(name)
    if name in BASELINES:
        return baseline_policy(name)
    path = policy_path or POLICY_DIR / LEARNED_METHODS[name]
    if not path.exists():
        raise InputError(f"{path}: policy file not found (train it with `idas-sumo train` or pass --policy)")
    return learned_policy(path, seed)
