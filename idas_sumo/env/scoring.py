"""A step's rewards as named parts: one function (``score``) over a registry of reward terms.

A term is registered by name and computes its part for every agent of the step from a ``StepContext`` (as
sumo-rl resolves a reward function by name and HighwayEnv returns a dict of named parts). The paper's four
terms are registered here; ``RewardConfig.extra_terms`` names more, registered from outside the core. An
individual term's part enters its agent's reward; a shared term's part (the paper's r_flow) is one value per
copy, given to each of its agents in ``reward_parts`` and counted once, in the copy's joint reward only.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from idas_sumo.env.jit import kernel
from idas_sumo.env.kernels import _REASON_CODE
from idas_sumo.env.layout import VISIBILITY_M
from idas_sumo.env.rewards import (
    FLOW_PENALTY_PER_HARD_BRAKE,
    IMPEDE_PENALTY,
    REWARD_PART_NAMES,
    RewardConfig,
    collide_reward,
)
from idas_sumo.env.snapshot import NO_LEADER, TrafficSnapshot, nearest_ahead
from idas_sumo.errors import InputError

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]
BoolArray = npt.NDArray[np.bool_]


@dataclass(frozen=True)
class StepContext:
    """What a step knows when it is scored. Per agent: row i is agent i of the step's batch."""

    config: RewardConfig
    copies: int
    """K: the engine's slots (a shared part has one value per copy)."""
    copy: IntArray
    """Per agent: its copy."""
    b_type: FloatArray
    """Per agent: its driver type."""
    b_prio: FloatArray
    """Per agent: the priority of the road it came from (collisions happen on or past the junction, where
    the road is the outgoing one)."""
    egos: IntArray
    """Per agent: its row in ``before``."""
    end_code: IntArray
    """Per agent: its end reason's code (``kernels._REASON_CODE``; 0: it goes on)."""
    before: TrafficSnapshot
    """The snapshot the agents decided in (every copy)."""
    brakes: IntArray
    """The step's hard brakes, as rows of ``before``: the agents' (batch order), then SUMO's cars'."""
    zone_brakes: IntArray
    """Per copy: of those, the ones within the merging zone."""
    impeded_by: IntArray
    """Rows of ``before`` of whoever caused each hard brake (one per brake that has a car ahead in sight)."""

    def ended(self, reason: str) -> BoolArray:
        """Per agent: whether its episode ended for ``reason`` (one of END_REASONS)."""
        return np.asarray(self.end_code == _REASON_CODE[reason])


RewardFn = Callable[[StepContext], FloatArray]


@dataclass(frozen=True)
class RewardTerm:
    """A named reward part: ``fn`` gives (n agents,) values, or (K copies,) when ``shared``."""

    name: str
    fn: RewardFn
    shared: bool = False


_TERMS: dict[str, RewardTerm] = {}


def register_reward_term(name: str, fn: RewardFn, shared: bool = False) -> RewardTerm:
    """Make ``fn`` the reward term ``name`` (a second registration of a name is refused)."""
    if name in _TERMS:
        raise ValueError(f"reward term {name!r} is registered already")
    term = _TERMS[name] = RewardTerm(name, fn, shared)
    return term


def reward_term(name: str) -> RewardTerm:
    """The term registered as ``name``; InputError naming the registered ones if there is none."""
    term = _TERMS.get(name)
    if term is None:
        raise InputError(f"unknown reward term {name!r}; registered: {', '.join(_TERMS)}")
    return term


def check_terms(config: RewardConfig) -> None:
    """Refuse a config that names an unregistered term (InputError), before any episode runs."""
    for name in config.part_names:
        reward_term(name)


@dataclass(frozen=True)
class Scores:
    """A step's rewards: per agent its named parts and its reward, per copy the joint reward."""

    parts: FloatArray
    """(n, len(config.part_names))."""
    rewards: FloatArray
    """Per agent: the sum of its individual parts, in order."""
    joint: FloatArray
    """Per copy: the sum of its agents' rewards plus its shared parts."""


def score(ctx: StepContext) -> Scores:
    """Every term of ``ctx.config`` over every agent of the step."""
    names = ctx.config.part_names
    if names == REWARD_PART_NAMES and not ctx.end_code.any():
        if not (len(ctx.impeded_by) or ctx.zone_brakes.any()):
            return quiet_scores(len(ctx.copy), ctx.copies)
        return _nobody_ended(ctx)
    n = len(ctx.copy)
    parts = np.zeros((n, len(names)))
    shared: list[FloatArray] = []
    own: list[int] = []
    for j, name in enumerate(names):
        term = reward_term(name)
        if term.shared:
            per_copy = np.asarray(term.fn(ctx), dtype=np.float64)
            parts[:, j] = per_copy[ctx.copy]
            shared.append(per_copy)
        else:
            parts[:, j] = term.fn(ctx)
            own.append(j)
    rewards = parts[:, own[0]].copy() if own else np.zeros(n)
    for j in own[1:]:
        rewards = rewards + parts[:, j]
    joint: FloatArray = np.bincount(ctx.copy, weights=rewards, minlength=ctx.copies).astype(np.float64)
    for per_copy in shared:
        joint = joint + per_copy
    return Scores(parts, rewards, joint)


def quiet_scores(n: int, copies: int) -> Scores:
    """``score`` of the paper's four terms in a step where no agent ended, no hard brake had a car ahead
    and none was in the merging zone (most steps): what the terms give then, bit for bit (impede and flow
    are -5·0 and -1·0, i.e. -0.0; every sum 0.0), without calling them."""
    parts = np.empty((n, len(REWARD_PART_NAMES)))
    parts[:] = _QUIET_PARTS
    return Scores(parts, np.zeros(n), np.zeros(copies))


def _nobody_ended(ctx: StepContext) -> Scores:
    """``score`` of the paper's four terms in a step where no agent ended: finish and collide are 0.0
    everywhere, so only impede and flow are computed; an agent's reward (0.0 + 0.0) + impede is impede + 0.0,
    bit for bit."""
    parts = np.zeros((len(ctx.copy), len(REWARD_PART_NAMES)))
    impede, per_copy = _impede(ctx), _flow(ctx)
    parts[:, _IMPEDE_COLUMN] = impede
    parts[:, _FLOW_COLUMN] = per_copy[ctx.copy]
    rewards = impede + 0.0
    joint = np.bincount(ctx.copy, weights=rewards, minlength=ctx.copies).astype(np.float64) + per_copy
    return Scores(parts, rewards, joint)


def nobody_ended_scores(
    copy: IntArray, egos: IntArray, n_rows: int, copies: int, impeded_by: IntArray, zone_brakes: IntArray
) -> Scores:
    """``score`` of the paper's four terms in a step where no agent ended (``_nobody_ended``, and
    ``quiet_scores``' values when nothing was impeded and no brake was in the zone), in one compiled pass:
    the agents' rows ``egos`` of the ``n_rows``-row snapshot they decided in, their ``copy``, and the
    ``StepContext`` fields of the same names."""
    # (Filled, not returned: a compiled call's every returned array costs about 0.5 µs of boxing.)
    n = len(egos)
    parts, rewards, joint = np.zeros((n, len(REWARD_PART_NAMES))), np.empty(n), np.zeros(copies)
    _nobody_ended_kernel(
        copy,
        egos,
        n_rows,
        copies,
        impeded_by,
        zone_brakes,
        IMPEDE_PENALTY,
        FLOW_PENALTY_PER_HARD_BRAKE,
        _IMPEDE_COLUMN,
        _FLOW_COLUMN,
        parts,
        rewards,
        joint,
    )
    return Scores(parts, rewards, joint)


@kernel
def _nobody_ended_kernel(
    copy,
    egos,
    n_rows,
    copies,
    impeded_by,
    zone_brakes,
    impede_penalty,
    flow_penalty,
    impede_col,
    flow_col,
    parts,
    rewards,
    joint,
):
    """``_nobody_ended``'s arithmetic, in its order: impede = penalty · brakes caused (bincount), flow =
    penalty · zone brakes per copy, reward = impede + 0.0, joint = the copy's rewards summed in row order
    from 0.0 (bincount's weights), then + flow; into ``parts`` (zeros, (n, parts)), ``rewards`` (n) and
    ``joint`` (zeros, per copy)."""
    caused = np.zeros(n_rows, dtype=np.int64)
    for j in range(impeded_by.shape[0]):
        caused[impeded_by[j]] += 1
    per_copy = np.empty(copies)
    for k in range(copies):
        per_copy[k] = flow_penalty * zone_brakes[k]
    n = egos.shape[0]
    for i in range(n):
        impede = impede_penalty * caused[egos[i]]
        parts[i, impede_col] = impede
        parts[i, flow_col] = per_copy[copy[i]]
        rewards[i] = impede + 0.0
        joint[copy[i]] += rewards[i]
    for k in range(copies):
        joint[k] = joint[k] + per_copy[k]


def impeding_vehicles(before: TrafficSnapshot, brake_rows: IntArray) -> IntArray:
    """For each hard-braking vehicle, the nearest vehicle ahead of it on either lane (within sight, same
    copy): their rows in ``before`` (one per brake that has one). Our reading of "penalizes agents that
    cause other agents to hard brake" (L286)."""
    if len(brake_rows) == 0:
        return np.zeros(0, dtype=np.int64)
    ahead, _ = nearest_ahead(before, brake_rows, any_lane=True, level_counts=True, max_ahead_m=VISIBILITY_M)
    return np.asarray(ahead[ahead != NO_LEADER], dtype=np.int64)


# -- the paper's four terms (Section V-B) ----------------------------------------------------------


def _finish(ctx: StepContext) -> FloatArray:
    """r_finish = (15·b_type + 50)/4 for each agent that finished in this step."""
    part = np.zeros(len(ctx.copy))
    won = ctx.ended("finished")
    if won.any():  # (most steps nobody finishes)
        part[won] = ctx.config.finish(ctx.b_type[won])
    return part


def _collide(ctx: StepContext) -> FloatArray:
    """r_collide = -5·b_prio - 5 (or the config's other sign) for each agent that collided in this step."""
    part = np.zeros(len(ctx.copy))
    hit = ctx.ended("collided")
    if hit.any():
        part[hit] = collide_reward(ctx.b_prio[hit], ctx.config.collision_sign)
    return part


def _impede(ctx: StepContext) -> FloatArray:
    """r_impede = -5 per hard brake the agent caused (it was the nearest car ahead of the braking one)."""
    if not len(ctx.impeded_by):  # no hard brake had a car ahead: -5 * 0 everywhere (-0.0, as before)
        return np.full(len(ctx.egos), IMPEDE_PENALTY * 0.0)
    caused = np.bincount(ctx.impeded_by, minlength=len(ctx.before))
    return np.asarray(IMPEDE_PENALTY * caused[ctx.egos], dtype=np.float64)


def _flow(ctx: StepContext) -> FloatArray:
    """r_flow = -1 per hard brake within the merging zone, per copy: shared by its agents."""
    return np.asarray(FLOW_PENALTY_PER_HARD_BRAKE * ctx.zone_brakes, dtype=np.float64)


register_reward_term("finish", _finish)
register_reward_term("collide", _collide)
register_reward_term("impede", _impede)
register_reward_term("flow", _flow, shared=True)
assert tuple(_TERMS) == REWARD_PART_NAMES
_IMPEDE_COLUMN, _FLOW_COLUMN = REWARD_PART_NAMES.index("impede"), REWARD_PART_NAMES.index("flow")
_QUIET_PARTS = np.array([-0.0 if name in ("impede", "flow") else 0.0 for name in REWARD_PART_NAMES])
_QUIET_PARTS.flags.writeable = False
