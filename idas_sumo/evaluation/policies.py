"""Methods an evaluation can run, behind the engine's ``Policy`` contract (env/engine.py): actions for
rows of an ``AgentBatch``. Baselines read the traffic snapshot; learned policies read observations."""

from __future__ import annotations

import difflib
from pathlib import Path

from idas_sumo.baselines.policies import BASELINES, RuleBasedPolicy
from idas_sumo.env.engine import Policy
from idas_sumo.errors import InputError
from idas_sumo.resources import POLICY_DIR

LEARNED_METHODS: dict[str, str] = {
    "idas": "idas.pt",
    "idas_v": "idas_v.pt",
    "idas_direct": "idas_direct.pt",
    # Ours, beside the paper's: IDAS trained on generated merges of many geometries (issue #17). Variant
    # policies live in experiments/policies and are evaluated by path (--policy; experiments/README.md).
    "idas_geometry": "idas_geometry.pt",
    # Ours (issue 36): the imitation of FSM+IDM-smooth that IDAS, IDAS-V and IDAS-direct start from, before any
    # RL episode, so that what RL adds to it is measured.
    "warm_start": "warm_start.pt",
    # The paper's recipe as printed, from random weights (issue 36; docs/paper-recipe.md), whatever it scores.
    "idas_paper": "idas_paper.pt",
    "idas_v_paper": "idas_v_paper.pt",
    "idas_direct_paper": "idas_direct_paper.pt",
}
PAPER_METHODS: tuple[str, ...] = ("idas", "idas_v", "idas_direct", "idm", "fsm_idm")
"""The paper's five methods: what ``--baseline all`` runs."""
PAPER_RECIPE_METHODS: tuple[str, ...] = ("idas_paper", "idas_v_paper", "idas_direct_paper")
"""The paper's methods trained by its recipe as printed (``idas_sumo/scenarios/train_paper.toml``)."""
METHODS: tuple[str, ...] = (*LEARNED_METHODS, *BASELINES)
METHOD_LABELS: dict[str, str] = {
    "idas": "IDAS",
    "idas_v": "IDAS-V",
    "idas_direct": "IDAS-direct",
    "idas_geometry": "IDAS-geometry",
    "warm_start": "warm start",
    "idas_paper": "IDAS (paper recipe)",
    "idas_v_paper": "IDAS-V (paper recipe)",
    "idas_direct_paper": "IDAS-direct (paper recipe)",
    "idm": "IDM",
    "fsm_idm": "FSM+IDM",
    "fsm_idm_smooth": "FSM+IDM-smooth",
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


def learned_policy(path: Path, seed: int = 0) -> Policy:
    """A shipped or trained actor, acting greedily (the most probable allowed action)."""
    import torch

    from idas_sumo.agents.checkpoint_file import load_actor  # lazy: torch only for learned methods
    from idas_sumo.agents.policy import ActorPolicy

    # One thread per evaluation process: a step's forward is a few dozen agents, and torch's waiting threads
    # compete with SUMO and the other workers for the cores (docs/performance.md).
    torch.set_num_threads(1)
    return ActorPolicy(load_actor(path), seed=seed, deterministic=True)


def resolve_policy(name: str, policy_path: Path | None = None, seed: int = 0) -> Policy:
    """The policy for a method name; learned methods load ``policy_path`` or the shipped file."""
    check_method(name)
    if name in BASELINES:
        return RuleBasedPolicy(name)
    path = policy_path or POLICY_DIR / LEARNED_METHODS[name]
    if not path.exists():
        raise InputError(f"{path}: policy file not found (train it with `idas-sumo train` or pass --policy)")
    return learned_policy(path, seed)
