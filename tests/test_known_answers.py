"""The learner solves small problems whose optimum is known (as Stable-Baselines3 checks each algorithm on
identity environments), through its real update path: actions drawn by ``Learner.act``, the agent-steps
recorded as ``EpisodeData`` and batched by ``batch_from_episodes`` exactly as a rollout's, one
``Learner.update`` per round, the paper's networks, masks and defaults (γ 0.9, one-step V with target V̂,
one-step SARSA Q, α 0.7).

Each task writes its few features into the observation's scalar slots (the grids stay empty) and uses the
action mask to offer a subset of the 7 actions, so the real encoder, heads and masking are what learn.
Only the learning rates and the target rate are raised (a few hundred updates, not tens of thousands);
everything else is ``LearnerConfig``'s default unless a test says otherwise.

- a one-step identity task (bandit per observation), J1 alone: the greedy action is the rewarded one;
- a two-agent social dilemma, one step: individual rewards favour "defect", the joint reward "cooperate".
  J1 alone (stage 1) must find defect, J2 alone and the paper's α = 0.7 mix must find cooperate: only the
  centralised critic's counterfactual advantage can carry the joint reward to the actor;
- a 4-step chain with a delayed terminal reward and an early exit worth 0.5: walking on pays 1 after four
  steps, worth 0.9³ = 0.729 > 0.5 at γ 0.9 and 0.5³ = 0.125 < 0.5 at γ 0.5; the learned choice at the start
  flips with γ, and V learns γ^(steps to go) through the one-step targets;
- a 3-step road where waiting pays nothing and the time limit cuts a waiting agent off (done 0, bootstrapped, as
  a rollout batches a timeout): the stall is not learned, the agent drives on.

Checked against broken learners (by hand, not kept): the policy gradient's sign flipped fails all seven; COMA's
advantage flipped fails J2 and the mix only; the configured γ ignored in the TD target fails the γ 0.5 chain.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
import pytest
import torch

from idas_sumo.agents.critic_input import OTHERS_ACTIONS_DIM, others_actions_onehot
from idas_sumo.agents.learner import Learner, LearnerConfig
from idas_sumo.agents.rollout import EpisodeData, EpisodeStats, batch_from_episodes
from idas_sumo.env.actions import N_ACTIONS
from idas_sumo.env.layout import N_SCALARS, OBS_DIM
from idas_sumo.env.state_layout import STATE_DIM, STATE_SLOTS

CONTEXT_CELLS = 40  # 20 m of road: wider than the conv's 30-cell kernel
ROAD_ROUNDS = 45
FAST = LearnerConfig(lr_actor=3e-3, lr_value=1e-2, lr_central=1e-2, target_tau=0.1)
"""Raised rates so a task is learned in a few hundred updates; the rest of the config is the default."""


@dataclass
class Step:
    """One agent-step as a rollout records it."""

    obs: npt.NDArray[np.float32]
    mask: npt.NDArray[np.int8]
    action: int
    reward: float
    slot: int = 0
    others: npt.NDArray[np.float32] | None = None
    joint_reward: float = 0.0


def observation(*features: float) -> npt.NDArray[np.float32]:
    """An observation with ``features`` in its first scalar slots and empty grids."""
    assert len(features) <= N_SCALARS
    obs = np.zeros(OBS_DIM, dtype=np.float32)
    obs[: len(features)] = features
    return obs


def seen_at(context: int) -> npt.NDArray[np.float32]:
    """An observation that shows ``context`` as the conv sees a car: occupancy in cells
    [CONTEXT_CELLS·k, CONTEXT_CELLS·(k + 1)) of the own lane, the rest of the road empty."""
    obs = observation()
    start = N_SCALARS + CONTEXT_CELLS * context  # the own lane's occupancy channel comes first (layout.py)
    obs[start : start + CONTEXT_CELLS] = 1.0
    return obs


def mask_of(allowed: Sequence[int]) -> npt.NDArray[np.int8]:
    mask = np.zeros(N_ACTIONS, dtype=np.int8)
    mask[list(allowed)] = 1
    return mask


def episode(agents: Sequence[Sequence[Step]], cut_off: npt.NDArray[np.float32] | None = None) -> EpisodeData:
    """One episode's ``EpisodeData``: each agent's steps in time order, rows time-major as a rollout writes
    them, each row linked to its agent's next one. An agent's last step ends its episode (done), unless
    ``cut_off`` is given: then the time limit cut a single agent off there (done 0) with o' = ``cut_off``."""
    rows: list[tuple[int, int, Step]] = sorted(
        ((t, n, step) for n, steps in enumerate(agents) for t, step in enumerate(steps)),
        key=lambda r: (r[0], r[1]),
    )
    index = {(n, t): i for i, (t, n, _) in enumerate(rows)}
    count = len(rows)
    next_row = np.array([index.get((n, t + 1), -1) for t, n, _ in rows], dtype=np.int64)
    last = next_row < 0
    col = np.array([s.action for _, _, s in rows], dtype=np.int64)
    state = np.zeros((count, STATE_DIM), np.float32)
    others = np.stack(
        [np.zeros(OTHERS_ACTIONS_DIM, np.float32) if s.others is None else s.others for *_, s in rows]
    )
    slot = np.array([s.slot for *_, s in rows], dtype=np.int64)

    def following(column: npt.NDArray) -> npt.NDArray:
        out = np.zeros_like(column)
        out[~last] = column[next_row[~last]]
        return out

    return EpisodeData(
        obs_bank=np.stack([s.obs for *_, s in rows] + ([] if cut_off is None else [cut_off])),
        obs_index=np.arange(count, dtype=np.int64),
        next_obs_index=np.where(last & (cut_off is not None), count, next_row),
        mask=np.stack([s.mask for *_, s in rows]),
        action=col,
        reward=np.array([s.reward for *_, s in rows], dtype=np.float32),
        done=(last & (cut_off is None)).astype(np.float32),
        state=state,
        others_actions=others,
        slot=slot,
        joint_reward=np.array([s.joint_reward for *_, s in rows], dtype=np.float32),
        next_state=following(state),
        next_others_actions=following(others),
        next_slot=following(slot),
        next_action=following(col),
        next_valid=(~last).astype(np.float32),
        next_row=next_row,
        stats=EpisodeStats(
            agents=len(agents),
            steps=max(len(s) for s in agents),
            agent_steps=count,
            sim_time_s=0.0,
            return_mean=0.0,
            reward_parts={},
            collisions=0,
            timed_out=cut_off is not None,
            success=cut_off is None,
            perfect=cut_off is None,
        ),
    )


def greedy(learner: Learner, obs: npt.NDArray[np.float32], allowed: Sequence[int]) -> int:
    return int(learner.act(obs[None], mask_of(allowed)[None], torch.Generator(), deterministic=True)[0])


def probability(learner: Learner, obs: npt.NDArray[np.float32], allowed: Sequence[int], action: int) -> float:
    with torch.no_grad():
        dist = learner.actor.distribution(
            torch.from_numpy(obs[None]), torch.from_numpy(mask_of(allowed)[None])
        )
    return float(dist.probs[0, action])


def value(learner: Learner, obs: npt.NDArray[np.float32]) -> float:
    with torch.no_grad():
        return float(learner.value(torch.from_numpy(obs[None]))[0])


def train(
    learner: Learner,
    play: Callable[[Learner, torch.Generator], list[EpisodeData]],
    rounds: int,
    seed: int = 0,
) -> None:
    """``rounds`` rounds of: play a batch of episodes with the current policy, one update on them."""
    generator = torch.Generator().manual_seed(seed)
    for _ in range(rounds):
        learner.update(
            batch_from_episodes(play(learner, generator), central=learner.config.use_central_critic)
        )


# --- (a) one-step bandit, J1 ----------------------------------------------------------------------------

BANDIT_ACTIONS = tuple(range(N_ACTIONS))
BANDIT_REWARDS = (0.2, 0.4, 1.0, 0.1, 0.6, 0.0, 0.3)
"""Action 2 is best; the actor starts on action 6 (its head's initial bias puts ~80 % there)."""
BANDIT_BEST = 2
BANDIT_OBS = seen_at(1)


def play_bandit(learner: Learner, generator: torch.Generator, episodes: int = 64) -> list[EpisodeData]:
    obs = np.repeat(BANDIT_OBS[None], episodes, axis=0)
    masks = np.repeat(mask_of(BANDIT_ACTIONS)[None], episodes, axis=0)
    actions = learner.act(obs, masks, generator).tolist()
    return [episode([[Step(BANDIT_OBS, masks[0], a, BANDIT_REWARDS[a])]]) for a in actions]


def test_bandit_is_solved_with_j1() -> None:
    learner = Learner(FAST, seed=0)
    assert probability(learner, BANDIT_OBS, BANDIT_ACTIONS, 6) > 0.7
    train(learner, play_bandit, rounds=25)
    assert greedy(learner, BANDIT_OBS, BANDIT_ACTIONS) == BANDIT_BEST
    best = probability(learner, BANDIT_OBS, BANDIT_ACTIONS, BANDIT_BEST)
    assert best > 0.9
    # V(o) is the expected reward of the policy it was trained on: near 1 once the policy settles.
    assert value(learner, BANDIT_OBS) == pytest.approx(BANDIT_REWARDS[BANDIT_BEST], abs=0.15)


# --- (b) two-agent social dilemma: J1, J2 (COMA) and the α mix -------------------------------------------

COOPERATE, DEFECT = 1, 2
DILEMMA_ACTIONS = (COOPERATE, DEFECT)
DEFECT_GAIN = 1.0  # what defecting pays the agent itself
GIFT = 10.0  # what cooperating pays the other agent: the joint reward gains GIFT - DEFECT_GAIN per cooperator
DILEMMA_OBS = observation(0.0, 0.0, 0.0, 1.0, 0.0)


def dilemma_rewards(a0: int, a1: int) -> tuple[float, float]:
    def own(me: int, other: int) -> float:
        return DEFECT_GAIN * (me == DEFECT) + GIFT * (other == COOPERATE)

    return own(a0, a1), own(a1, a0)


def play_dilemma(learner: Learner, generator: torch.Generator, episodes: int = 64) -> list[EpisodeData]:
    obs = np.repeat(DILEMMA_OBS[None], 2 * episodes, axis=0)
    masks = np.repeat(mask_of(DILEMMA_ACTIONS)[None], 2 * episodes, axis=0)
    actions = learner.act(obs, masks, generator).reshape(episodes, 2)
    out = []
    acting = np.zeros(STATE_SLOTS, dtype=bool)
    acting[:2] = True
    for a0, a1 in actions.tolist():
        r0, r1 = dilemma_rewards(a0, a1)
        joint = np.zeros(STATE_SLOTS, dtype=np.int64)
        joint[:2] = a0, a1
        others = others_actions_onehot(joint, acting)
        steps = [
            [Step(DILEMMA_OBS, masks[0], a, r, slot=n, others=others[n], joint_reward=r0 + r1)]
            for n, (a, r) in enumerate(((a0, r0), (a1, r1)))
        ]
        out.append(episode(steps))
    return out


@pytest.mark.parametrize(
    ("alpha", "central", "answer", "rounds", "advantage"),
    [
        (1.0, False, DEFECT, 45, "q"),
        (0.0, True, COOPERATE, 30, "q"),
        (0.7, True, COOPERATE, 55, "q"),
        (0.7, True, COOPERATE, 55, "return"),
    ],
    ids=["J1-stage1", "J2-coma", "paper-mix-0.7", "mix-0.7-return-advantage"],
)
def test_social_dilemma_answer_follows_the_objective(
    alpha: float, central: bool, answer: int, rounds: int, advantage: str
) -> None:
    """``advantage`` 'return' (ours, ``central_advantage``): J2 with Q's target for the action taken in place of
    Q(s, a) still carries the joint reward to the actor."""
    config = dataclasses.replace(FAST, alpha=alpha, use_central_critic=central, central_advantage=advantage)
    learner = Learner(config, seed=0)
    train(learner, play_dilemma, rounds=rounds)
    assert probability(learner, DILEMMA_OBS, DILEMMA_ACTIONS, answer) > 0.9


# --- (c) a chain with a delayed terminal reward ----------------------------------------------------------

WALK, EXIT = 1, 2
CHAIN_ACTIONS = (WALK, EXIT)
CHAIN_LENGTH = 4  # WALK at the last position pays FINISH and ends the episode
FINISH = 1.0
EXIT_REWARD = 0.3  # EXIT anywhere pays this and ends the episode


def chain_obs(position: int) -> npt.NDArray[np.float32]:
    return seen_at(position)


def play_chain(learner: Learner, generator: torch.Generator, episodes: int = 64) -> list[EpisodeData]:
    mask = mask_of(CHAIN_ACTIONS)
    walking = [[] for _ in range(episodes)]  # type: list[list[Step]]
    alive = list(range(episodes))
    for position in range(CHAIN_LENGTH):
        if not alive:
            break
        obs = np.repeat(chain_obs(position)[None], len(alive), axis=0)
        actions = learner.act(obs, np.repeat(mask[None], len(alive), axis=0), generator)
        still = []
        for e, a in zip(alive, actions.tolist(), strict=True):
            if a == EXIT:
                reward = EXIT_REWARD
            else:
                reward = FINISH if position == CHAIN_LENGTH - 1 else 0.0
                if position < CHAIN_LENGTH - 1:
                    still.append(e)
            walking[e].append(Step(obs[0], mask, a, reward))
        alive = still
    return [episode([steps]) for steps in walking]


@pytest.mark.parametrize(("gamma", "answer", "rounds"), [(0.9, WALK, 90), (0.5, EXIT, 40)])
def test_chain_with_delayed_reward_answer_follows_gamma(gamma: float, answer: int, rounds: int) -> None:
    # The actor slower than V (two timescales): V must carry the delayed reward back to the start before
    # the actor settles, or the exit's immediate 0.3 wins against a V(o') that has not learned yet.
    learner = Learner(dataclasses.replace(FAST, gamma=gamma, lr_actor=1e-3), seed=0)
    train(learner, play_chain, rounds=rounds)
    assert greedy(learner, chain_obs(0), CHAIN_ACTIONS) == answer
    assert probability(learner, chain_obs(0), CHAIN_ACTIONS, answer) > 0.8
    if answer == WALK:
        # The policy walks: V(position k) → γ^(steps after k) · FINISH, learned back from the end through
        # one-step targets on V̂ (the start, last to learn, is still on its way up).
        values = [value(learner, chain_obs(k)) for k in range(CHAIN_LENGTH)]
        assert values == sorted(values)
        for k in range(1, CHAIN_LENGTH):
            assert values[k] == pytest.approx(gamma ** (CHAIN_LENGTH - 1 - k) * FINISH, abs=0.1)


# --- (d) a stall the time limit cuts off ------------------------------------------------------------------

WAIT = 0
ROAD_ACTIONS = (WAIT, WALK)
ROAD_LENGTH = 3  # WALK at the last position pays FINISH and ends the episode
TIME_LIMIT_STEPS = (
    4  # an agent still on the road after this many steps is cut off: done 0, V(o') bootstrapped
)


def play_road(learner: Learner, generator: torch.Generator, episodes: int = 64) -> list[EpisodeData]:
    mask = mask_of(ROAD_ACTIONS)
    steps: list[list[Step]] = [[] for _ in range(episodes)]
    position = [0] * episodes
    driving = list(range(episodes))
    for _ in range(TIME_LIMIT_STEPS):
        if not driving:
            break
        obs = np.stack([seen_at(position[e]) for e in driving])
        actions = learner.act(obs, np.repeat(mask[None], len(driving), axis=0), generator)
        still = []
        for row, (e, a) in enumerate(zip(driving, actions.tolist(), strict=True)):
            finished = a == WALK and position[e] == ROAD_LENGTH - 1
            steps[e].append(Step(obs[row], mask, a, FINISH if finished else 0.0))
            if not finished:
                position[e] += a == WALK
                still.append(e)
        driving = still
    return [
        episode([steps[e]], cut_off=seen_at(position[e]) if e in driving else None) for e in range(episodes)
    ]


def test_waiting_until_the_time_limit_is_not_learned() -> None:
    """Waiting pays nothing and never ends an episode; the time limit cuts a waiting agent off (done 0, its o' in
    ``bootstrap_obs``, as a rollout batches a timeout). The answer is to drive on everywhere."""
    learner = Learner(dataclasses.replace(FAST, lr_actor=1e-3), seed=0)
    train(learner, play_road, rounds=ROAD_ROUNDS)
    for k in range(ROAD_LENGTH):
        assert probability(learner, seen_at(k), ROAD_ACTIONS, WALK) > 0.8
