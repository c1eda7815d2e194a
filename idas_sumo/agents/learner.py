"""The IDAS learner: one shared actor, a decentralised critic V and a centralised COMA critic Q.

Stage 1 (Robot World) trains the actor and V with ∇J1 only (``use_central_critic=False``); stage 2
(Intelligent World) adds Q and uses ∇J = α∇J1 + (1-α)∇J2. Both critics have soft-updated target
networks. All networks exist in both stages so a stage-1 checkpoint loads into stage 2 as is.

Our reading of the paper's Q target (eq. for L(φ2)): it names a target policy π̂ for the next
joint action. We bootstrap SARSA-style from the actions the agents actually took at t+1, which
were drawn from the current policy (the on-policy limit of π̂); this needs no resampling of the
other agents' next actions and keeps the joint action consistent with the recorded state.
"""

from __future__ import annotations

import copy
import dataclasses
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Generic, Literal, TypeVar

import numpy as np
import numpy.typing as npt
import torch
from torch import nn
from torch.distributions import kl_divergence

from idas_sumo.agents.coma import ALPHA, coma_advantage, combined_policy_loss, subtract_action_means
from idas_sumo.agents.critic_input import STATE_LAYOUT_ID
from idas_sumo.agents.networks import Actor, CentralCritic, ObsWindows, ValueCritic
from idas_sumo.agents.returns import GAMMA, gae_advantages, lambda_targets, td_advantages, td_targets
from idas_sumo.env.actions import N_ACTIONS, N_DELTA_ACTIONS
from idas_sumo.env.layout import OBS_DIM, OBS_LAYOUT_ID
from idas_sumo.env.state_layout import STATE_SLOTS
from idas_sumo.errors import InputError

CentralHead = Literal["per_action", "state_value"]
CentralInput = Literal["scenario_slots", "ego_first"]
ComaActions = Literal["all", "delta_only"]
ComaActionMeans = Literal["keep", "subtract"]
CentralActionRows = Literal["all", "explored"]

__all__ = ["ActorStep", "Batch", "CriticStep", "Learner", "LearnerConfig", "PendingUpdate", "UpdateRecord"]

CHECKPOINT_FORMAT = 1


@dataclass(frozen=True)
class LearnerConfig:
    """Hyper-parameters of the learner; validated once on construction."""

    lr_actor: float = 1e-4
    """Adam learning rate of the actor."""
    lr_value: float = 1e-3
    """Adam learning rate of the decentralised critic V."""
    lr_central: float = 1e-3
    """Adam learning rate of the centralised critic Q."""
    gamma: float = GAMMA
    """Discount per 0.2 s decision step (paper: 0.9)."""
    alpha: float = ALPHA
    """Weight of ∇J1 in α∇J1 + (1-α)∇J2 (paper: 0.7); treated as 1 when the central critic is off."""
    use_central_critic: bool = False
    """False: stage 1, J1 only, Q is neither trained nor used. True: stage 2, J1 + J2."""
    target_tau: float = 0.01
    """Soft target update rate: target ← (1-τ) target + τ online, after every update (ours)."""
    entropy_coef: float = 0.0
    """Weight of the mean policy entropy subtracted from the actor loss (ours; the paper has none)."""
    max_grad_norm: float = 10.0
    """Global L2 norm each network's gradient is clipped to before its Adam step (ours)."""
    gae_lambda: float = 0.0
    """λ of generalised advantage estimation for A1 and the V target (ours). 0: the paper's one-step TD
    error and TD(0) target; > 0 needs ``Batch.next_row``."""
    q_lambda: float = 0.0
    """λ of the centralised critic's target (ours): 0 is the paper's one-step SARSA target; > 0 gives Q
    the λ-return of the joint reward along each agent's own steps (needs ``Batch.next_row``)."""
    normalize_advantages: bool = False
    """Standardise A1 and A2 over each batch before the policy gradient (ours; the paper does not)."""
    central_head: CentralHead = "per_action"
    """How Q gives its per-action values. 'per_action' (the default, COMA's critic head): one output per
    own action, each trained only on the rows where the agent took that action. 'state_value' (ours, a
    labelled variant): Q(s, a) = U(s) + D(s, a), U trained on every row's target whatever the action,
    D (starting near 0) on what is left, target - U(s). A per-action output the agents rarely take
    stays near its initial value while the targets move, so COMA's advantage of a rare action carries
    that lag; under 'state_value' it stays near U(s), an advantage near 0. Measured (docs/results.md): it
    removed that early bias but not stage 2's drift into collisions and stalls."""
    central_input: CentralInput = "scenario_slots"
    """The order of the vehicle slots Q reads. 'scenario_slots' (the default): the scenario's order, the agent's
    own slot one-hot. 'ego_first' (ours, a labelled variant; ``networks.ego_first_slots``): per row the
    agent's own slot first, then the others by how far their distance to the merge point is from its own.
    The input's size is the same, so a checkpoint loads under either; its Q only means something under the
    order it was trained with."""
    coma_actions: ComaActions = "all"
    """Which rows J2 (COMA's term) steps the actor on. 'all' (the default, the paper). 'delta_only' (ours, a
    labelled diagnostic): only the rows whose action was a Δa; a hard brake's or a release's row gets no COMA
    advantage (J1's only), and with ``normalize_advantages`` A2 is standardised over the Δa rows. It asks
    whether the stage-2 drift needs J2's view of the brake (docs/results.md)."""
    coma_action_means: ComaActionMeans = "keep"
    """What J2 does with each action's mean COMA advantage over a batch. 'keep' (the default, the paper).
    'subtract' (ours, a labelled variant; ``coma.subtract_action_means``): every row whose mask allowed a choice
    gets its advantage minus the mean over the batch's chosen rows that took the same action, so a Q whose
    value of an action is off by about the same amount everywhere (as measured for the hard brake,
    docs/results.md) steers where the policy takes it, not how often; J1 alone sets how often."""
    central_action_rows: CentralActionRows = "all"
    """Which rows train Q's action part D(s, a) under ``central_head = "state_value"``. 'all' (the default).
    'explored' (ours, a labelled variant): only the rows whose action was drawn uniformly from the allowed ones
    (``Batch.explored``, ``TrainConfig.critic_exploration``), where the action taken does not depend on the
    state: Q's differences between actions then cannot learn which situations an action is taken in, only what
    it leads to (docs/results.md, "Declared: a critic that learns actions from random ones")."""
    anchor_coef: float = 0.0
    """Weight of KL(π ‖ π₀) in the actor loss, π₀ the policy the stage started from (ours, a labelled variant;
    0: none, the paper). A trust region around the warm start: the paper's stage 2 drifts from IDAS-V into
    collisions and then a stall in every seed after ~2,500 episodes, both pushed by J2 (docs/results.md); with the
    anchor a push that the returns do not back costs the policy its distance from π₀. Set by ``anchor_to_start``."""
    device: str = "cpu"
    """Torch device the networks live on; sampling in ``act`` always draws on the CPU generator."""

    def __post_init__(self) -> None:
        for name in ("lr_actor", "lr_value", "lr_central", "max_grad_norm"):
            if not getattr(self, name) > 0.0:
                raise InputError(f"{name} must be positive, got {getattr(self, name)}")
        if not 0.0 < self.gamma <= 1.0:
            raise InputError(f"gamma must lie in (0, 1], got {self.gamma}")
        if not 0.0 <= self.alpha <= 1.0:
            raise InputError(f"alpha must lie in [0, 1], got {self.alpha}")
        if not 0.0 < self.target_tau <= 1.0:
            raise InputError(f"target_tau must lie in (0, 1], got {self.target_tau}")
        for name in ("gae_lambda", "q_lambda"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise InputError(f"{name} must lie in [0, 1], got {getattr(self, name)}")
        for name in ("entropy_coef", "anchor_coef"):
            if getattr(self, name) < 0.0:
                raise InputError(f"{name} must be non-negative, got {getattr(self, name)}")
        if self.central_action_rows == "explored" and self.central_head != "state_value":
            raise InputError('central_action_rows = "explored" needs central_head = "state_value"')

    @property
    def effective_alpha(self) -> float:
        """α actually used: 1 in stage 1, where J2 has no critic."""
        return self.alpha if self.use_central_critic else 1.0


@dataclass
class Batch:
    """B agent-steps. Central-critic fields may be None in stage 1.

    ``done`` is 1 when the agent's episode ended at this step by finishing or colliding (no
    bootstrap); a timeout is 0 (bootstrap). ``next_valid`` is 1 when the agent also acts at t+1,
    i.e. ``next_state``/``next_others_actions``/``next_slot``/``next_action`` are meaningful.

    With ``next_row`` most rows' o' is another row's o, so ``next_obs`` may be None and ``bootstrap_obs``
    hold o' for just the rows that have no next row but did not end (cut off by the timeout), in row
    order: a stage-2 round's full ``next_obs`` is some 30 MB copied to read a handful of rows.
    """

    obs: torch.Tensor  # (B, OBS_DIM) float32
    mask: torch.Tensor  # (B, N_ACTIONS) bool, the mask the action was drawn under
    action: torch.Tensor  # (B,) int64
    reward: torch.Tensor  # (B,) float32, individual reward
    next_obs: torch.Tensor | None  # (B, OBS_DIM) float32; None only with next_row and bootstrap_obs
    done: torch.Tensor  # (B,) float32
    state: torch.Tensor | None = None  # (B, STATE_DIM)
    others_actions: torch.Tensor | None = None  # (B, OTHERS_ACTIONS_DIM)
    slot: torch.Tensor | None = None  # (B,) int64
    joint_reward: torch.Tensor | None = None  # (B,) sum of all agents' rewards at t
    next_state: torch.Tensor | None = None
    next_others_actions: torch.Tensor | None = None
    next_slot: torch.Tensor | None = None
    next_action: torch.Tensor | None = None  # (B,) int64, any value where next_valid is 0
    next_valid: torch.Tensor | None = None  # (B,) float32
    next_row: torch.Tensor | None = None  # (B,) int64 row of the same agent's next step, -1: none
    bootstrap_obs: torch.Tensor | None = None  # (cut-off rows, OBS_DIM): o' where next_row is -1, done 0
    explored: torch.Tensor | None = None  # (B,) bool: the action was drawn uniformly, not by the policy

    def to(self, device: torch.device | str) -> Batch:
        moved: dict[str, Any] = {
            f.name: (None if (v := getattr(self, f.name)) is None else v.to(device))
            for f in dataclasses.fields(self)
        }
        return Batch(**moved)


@dataclass(frozen=True)
class CriticStep:
    """One critic's part of an update; tensors (B,), detached, from the critic before its step."""

    prediction: torch.Tensor
    """V(o), or Q(s, a) for the action taken."""
    target: torch.Tensor
    """What the prediction was regressed to."""
    advantage: torch.Tensor
    """A1 (TD error or GAE) or A2 (COMA), before any standardisation."""
    loss: float
    """0.5 · mean (target - prediction)²."""


@dataclass(frozen=True)
class ActorStep:
    """The actor's part of an update."""

    loss: float
    """-mean((α A1 + (1-α) A2) log π(a|o)) - entropy_coef · mean entropy + anchor_coef · mean KL(π ‖ π₀)."""
    entropy: float
    """Mean entropy of the masked policy before the step."""
    grad_norm: float
    """Global L2 norm of the actor's gradient before clipping."""


UPDATE_STAT_NAMES: tuple[str, ...] = (
    "actor_loss",
    "v_loss",
    "q_loss",
    "entropy",
    "adv_v_mean",
    "adv_q_mean",
    "v_mean",
    "q_mean",
    "actor_grad_norm",
)
"""The scalar metrics ``Learner.update`` returns, in metrics.csv's order."""


@dataclass(frozen=True)
class UpdateRecord:
    """What the last ``Learner.update`` regressed its critics to and stepped its actor with."""

    value: CriticStep
    central: CriticStep | None
    """None in stage 1, where Q is neither trained nor used."""
    actor: ActorStep

    def stats(self) -> dict[str, float]:
        """The scalar metrics ``update`` returns (one row of metrics.csv columns)."""
        central = self.central
        values = (
            self.actor.loss,
            self.value.loss,
            0.0 if central is None else central.loss,
            self.actor.entropy,
            float(self.value.advantage.mean().item()),
            0.0 if central is None else float(central.advantage.mean().item()),
            float(self.value.prediction.mean().item()),
            0.0 if central is None else float(central.prediction.mean().item()),
            self.actor.grad_norm,
        )
        return dict(zip(UPDATE_STAT_NAMES, values, strict=True))


@dataclass(frozen=True)
class _ValueForward:
    """V's forward pass on a batch: what the actor needs from it (A1) and what V's own step reuses."""

    obs: ObsWindows
    """The batch's observations, cut into the encoder's windows once for V, V̂ and the actor."""
    values: torch.Tensor
    """V(o) (B,), with gradient."""
    advantage: torch.Tensor
    """A1: the TD error (or GAE) with the online V on both ends."""
    next_index: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None
    """With ``next_row``: where each row's o' sits in [V(o), V(o') of the cut-off rows] (``_next_index``)."""


@dataclass(frozen=True)
class _CentralForward:
    """Q's forward pass on a batch: A2 for the actor, Q(s, ·) for Q's own step."""

    q_all: torch.Tensor
    """Q(s, ·) (B, N_ACTIONS), with gradient."""
    state_value: torch.Tensor | None
    """U(s) (B,), with gradient, under ``central_head = 'state_value'``; else None."""
    advantage: torch.Tensor
    """A2 (COMA) from this Q and the policy before the actor's step."""


_T = TypeVar("_T")


class _Background(Generic[_T]):
    """Work running in a thread of this process: ``wait`` for it, then take its ``result``.

    A thread, not the main one, so Ctrl-C (delivered to the main thread) never stops the work halfway:
    whoever catches the interrupt waits for it and finds the networks whole.
    """

    def __init__(self, work: Callable[[], _T]) -> None:
        self._work = work
        self._result: _T | None = None
        self._error: BaseException | None = None
        # An event, not Thread.join: a join interrupted by a signal (Ctrl-C, SIGTERM) can mark the thread
        # stopped while it still runs (CPython 3.11), and a second join then returns at once.
        self._finished = threading.Event()
        threading.Thread(target=self._run, name="critic step", daemon=True).start()

    def _run(self) -> None:
        try:
            self._result = self._work()
        except BaseException as err:  # handed to whoever takes the result
            self._error = err
        finally:
            self._finished.set()

    def wait(self) -> None:
        self._finished.wait()

    def result(self) -> _T:
        """What the work returned (re-raises what it raised); call after ``wait``."""
        assert self._finished.is_set(), "result() before wait()"
        if self._error is not None:
            raise self._error
        assert self._result is not None
        return self._result


class PendingUpdate:
    """An update of ``Learner.begin_update``: its actor has stepped; its critics may still be stepping in
    the background. ``stats`` waits for them and returns the update's metrics."""

    def __init__(
        self, done: dict[str, float] | None = None, critics: _Background[UpdateRecord] | None = None
    ) -> None:
        self._done, self._critics = done, critics

    @property
    def ready(self) -> bool:
        """Whether ``stats`` returns without waiting (the serial update: the critics stepped already)."""
        return self._done is not None

    def stats(self) -> dict[str, float]:
        """The scalar metrics (one row of metrics.csv columns), once the critics have stepped."""
        if self._done is None:
            assert self._critics is not None
            self._critics.wait()
            self._done = self._critics.result().stats()
        return self._done


@dataclass(frozen=True)
class _Policy:
    """The masked policy on a batch, with gradients: log π(a|o) (B,), entropy (B,), π (B, A)."""

    log_prob: torch.Tensor
    entropy: torch.Tensor
    probs: torch.Tensor
    anchor_kl: torch.Tensor | None = None
    """KL(π ‖ π₀) per row (B,), with gradients; None without an anchor."""


def _standardised(adv: torch.Tensor) -> torch.Tensor:
    """Zero mean, unit variance over the batch (a batch of one is only centred)."""
    centred = adv - adv.mean()
    return centred / (centred.std() + 1e-8) if adv.numel() > 1 else centred


def _soft_update(target: nn.Module, online: nn.Module, tau: float) -> None:
    with torch.no_grad():
        for t_param, o_param in zip(target.parameters(), online.parameters(), strict=True):
            t_param.lerp_(o_param, tau)


_Net = TypeVar("_Net", bound=nn.Module)


def _frozen_copy(net: _Net) -> _Net:
    target = copy.deepcopy(net)
    for p in target.parameters():
        p.requires_grad_(False)
    return target


def _require(value: torch.Tensor | None, name: str) -> torch.Tensor:
    if value is None:
        raise ValueError(f"Batch.{name} is required when the central critic is on")
    return value


def _gather_next(bank: torch.Tensor, where: torch.Tensor, ended: torch.Tensor) -> torch.Tensor:
    """Each row's value of o' from ``bank`` (``Learner._next_index``), 0 where the episode ended."""
    zero = torch.zeros((), dtype=bank.dtype, device=bank.device)
    return torch.where(ended, zero, bank[where])


def _cut_off_obs(b: Batch, cut_off: torch.Tensor) -> torch.Tensor:
    """o' of the rows ``cut_off`` (no next row, not done), from ``bootstrap_obs`` when the batch has it."""
    if b.bootstrap_obs is None:
        return _require(b.next_obs, "next_obs")[cut_off]
    if b.bootstrap_obs.shape[0] != cut_off.numel():
        raise ValueError(
            f"bootstrap_obs has {b.bootstrap_obs.shape[0]} rows for {cut_off.numel()} rows cut off by a timeout"
        )
    return b.bootstrap_obs


def _sample_grouped(
    probs: torch.Tensor, groups: Sequence[tuple[npt.NDArray[np.int64], torch.Generator]]
) -> torch.Tensor:
    """One draw per row of ``probs``, each group's rows with its own generator: exactly
    ``torch.multinomial(probs[rows], 1, generator=g)`` per group, draws and generator states alike.

    For one sample torch's CPU multinomial is argmax(p / q) with q ~ Exp(1) drawn into a tensor of
    ``probs[rows]``'s shape (the Gumbel-max trick; ``test_agents_networks.py`` checks the equality). Drawing
    each group's q and dividing and taking the argmax once for all rows does the same arithmetic with a
    tenth of the small tensor operations, which cost more than the arithmetic at rollout batch sizes. A
    masked action (probability exactly 0) gives 0 / q = 0 and an allowed one a positive ratio, so it never
    comes out.
    """
    draws = [torch.empty(len(rows), probs.shape[1]).exponential_(1, generator=g) for rows, g in groups]
    order = np.concatenate([np.asarray(rows, dtype=np.int64) for rows, _ in groups])
    if np.array_equal(order, np.arange(probs.shape[0])):  # the groups tile the rows in order
        q = torch.cat(draws)
    else:
        q = torch.ones_like(probs)
        q[torch.from_numpy(order)] = torch.cat(draws)
    return (probs / q).argmax(dim=1)


class _LazyAdam:
    """A learner's Adam optimiser for one of its networks, built on first use.

    Building the first optimiser of a process imports ``torch._dynamo`` (about 0.9 s here), which a learner
    that only acts, a rollout worker's or an evaluated policy's, never needs. Adam keeps no state until its
    first step, so building it later changes nothing; a test may put another optimiser in its place.
    """

    def __init__(self, network: str, lr: str) -> None:
        self.network, self.lr = network, lr
        self.attr = ""

    def __set_name__(self, owner: type, name: str) -> None:
        self.attr = f"_{name}"

    def __get__(self, learner: Any, owner: type | None = None) -> torch.optim.Optimizer:
        optimiser: torch.optim.Optimizer | None = learner.__dict__.get(self.attr)
        if optimiser is None:
            params = getattr(learner, self.network).parameters()
            optimiser = torch.optim.Adam(params, lr=getattr(learner.config, self.lr))
            learner.__dict__[self.attr] = optimiser
        return optimiser

    def __set__(self, learner: Any, optimiser: torch.optim.Optimizer) -> None:
        learner.__dict__[self.attr] = optimiser


class Learner:
    """Actor, V, Q, their targets and Adam optimisers; ``act`` for rollouts, ``update`` to learn.

    ``critics_in_background``: ``begin_update`` returns once the actor has stepped, and the critics'
    targets, backward passes, optimiser steps and target-network updates run in a thread meanwhile (the
    training loop collects the next round with the new actor then). The arithmetic and its order per
    tensor are those of the serial update, so the weights are bit for bit the same. The next update,
    ``state_dict``, ``load_state_dict`` and ``finish_critics`` wait for that step; nothing else may read
    the critics before one of them.
    """

    opt_actor = _LazyAdam("actor", "lr_actor")
    opt_value = _LazyAdam("value", "lr_value")
    opt_central = _LazyAdam("central", "lr_central")

    def __init__(self, config: LearnerConfig, seed: int = 0, critics_in_background: bool = False) -> None:
        self.config = config
        self.critics_in_background = critics_in_background
        self._critic_step: _Background[UpdateRecord] | None = None
        """The critics' step of the last update, while it runs in the background."""
        self.device = torch.device(config.device)
        # Seed only the initialisation, without touching the caller's global RNG; sampling in `act`
        # uses the caller's generator.
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            self.actor = Actor().to(self.device)
            self.value = ValueCritic().to(self.device)
            self.central = CentralCritic(
                state_value=config.central_head == "state_value",
                ego_first=config.central_input == "ego_first",
            ).to(self.device)
        self.value_target = _frozen_copy(self.value)
        self.central_target = _frozen_copy(self.central)
        self.last_update: UpdateRecord | None = None
        """What the last ``update`` regressed to and stepped with; None before the first."""
        self.anchor: Actor | None = None
        """π₀ of ``anchor_coef``: a frozen copy of the actor the stage started from; None without one."""

    def anchor_to_start(self) -> None:
        """Freeze a copy of the current actor as π₀, the policy ``anchor_coef`` keeps the actor near (call once,
        after the stage's starting weights are loaded)."""
        self.anchor = _frozen_copy(self.actor)

    def act(
        self,
        obs: npt.NDArray[np.float32],
        mask: npt.NDArray[np.int8],
        generator: torch.Generator,
        deterministic: bool = False,
    ) -> npt.NDArray[np.int64]:
        """Actions (B,) for B agents; never a masked one. ``generator`` must be a CPU generator."""
        return self.act_grouped(obs, mask, [(np.arange(obs.shape[0]), generator)], deterministic)

    def act_grouped(
        self,
        obs: npt.NDArray[np.float32],
        mask: npt.NDArray[np.int8],
        groups: Sequence[tuple[npt.NDArray[np.int64], torch.Generator]],
        deterministic: bool = False,
    ) -> npt.NDArray[np.int64]:
        """``act`` for agents of several episodes in one forward pass; each episode's rows (``groups``:
        rows, that episode's CPU generator) sample with their own generator, as they would alone."""
        if obs.ndim != 2 or obs.shape[1] != OBS_DIM or mask.shape != (obs.shape[0], N_ACTIONS):
            raise ValueError(
                f"expected obs (B, {OBS_DIM}) and mask (B, {N_ACTIONS}), got {obs.shape} and {mask.shape}"
            )
        allowed = torch.from_numpy(np.asarray(mask) != 0)
        if not bool(allowed.any(dim=1).all()):
            raise ValueError("every agent needs at least one allowed action (hard brake is never masked)")
        with torch.inference_mode():
            obs_t = torch.from_numpy(np.ascontiguousarray(obs, dtype=np.float32)).to(self.device)
            logits = self.actor.masked_logits(obs_t, allowed.to(self.device)).cpu()
            if deterministic:
                actions = logits.argmax(dim=1)
            else:
                actions = _sample_grouped(torch.softmax(logits, dim=1), groups)
        chosen = allowed.gather(1, actions.unsqueeze(1))
        assert bool(chosen.all()), "sampled a masked action"
        out: npt.NDArray[np.int64] = actions.numpy().astype(np.int64)
        return out

    def update(self, batch: Batch) -> dict[str, float]:
        """One gradient step on V, (Q), and the actor from B agent-steps; returns scalar metrics.

        Losses are means over the batch (the paper writes sums; a mean keeps the step size
        independent of B). Critics step before the actor, but both advantages are computed from the
        critics as they were before their step. What each part regressed to and handed on is kept in
        ``last_update``. With ``critics_in_background`` the same, waited for.
        """
        return self.begin_update(batch).stats()

    def begin_update(self, batch: Batch) -> PendingUpdate:
        """``update``, returning once the actor has stepped; with ``critics_in_background`` the critics
        step in a thread meanwhile (``PendingUpdate.stats`` waits for them), else they have stepped."""
        self.finish_critics()
        if batch.action.numel() == 0:
            # A round in which no learning car acted (each entered too late, or the episodes were cut
            # short): nothing to learn from, so no step; the metrics row says so with zero losses.
            return PendingUpdate(done=dict.fromkeys(UPDATE_STAT_NAMES, 0.0))
        b = self._checked(batch)
        if not self.critics_in_background:
            return PendingUpdate(done=self._serial_update(b).stats())
        self._critic_step = self._actor_first_update(b)
        return PendingUpdate(critics=self._critic_step)

    def finish_critics(self) -> None:
        """Wait for the critics' step of the last update when it runs in the background (else a no-op);
        re-raises what it raised."""
        pending = self._critic_step
        if pending is None:
            return
        pending.wait()  # a Ctrl-C here leaves it pending: the next call waits for it again
        self._critic_step = None
        pending.result()

    def _serial_update(self, b: Batch) -> UpdateRecord:
        """V steps, then Q, then the actor, each on its forward pass of the batch."""
        value_forward = self._value_forward(b)
        value_step = self._step_value_critic(b, value_forward)
        policy = self._policy(b, value_forward.obs)
        central_forward, central_step = None, None
        if self.config.use_central_critic:
            central_forward = self._central_forward(b, policy.probs.detach())
            central_step = self._step_central_critic(b, central_forward)
        actor_step = self._update_actor(
            b.action,
            b.mask,
            b.explored,
            policy,
            value_forward.advantage,
            None if central_forward is None else central_forward.advantage,
        )
        self._update_targets()
        self.last_update = UpdateRecord(value=value_step, central=central_step, actor=actor_step)
        return self.last_update

    def _actor_first_update(self, b: Batch) -> _Background[UpdateRecord]:
        """``_serial_update`` with the critics' half moved after the actor's step, into a thread: the actor
        needs only the critics' forward passes (the advantages), and nothing the actor does reads a
        critic. The same operations on the same tensors, so the same bits, in another order."""
        value_forward = self._value_forward(b)
        policy = self._policy(b, value_forward.obs)
        central_forward = (
            self._central_forward(b, policy.probs.detach()) if self.config.use_central_critic else None
        )
        actor_step = self._update_actor(
            b.action,
            b.mask,
            b.explored,
            policy,
            value_forward.advantage,
            None if central_forward is None else central_forward.advantage,
        )

        def critics() -> UpdateRecord:
            value_step = self._step_value_critic(b, value_forward)
            central_step = None if central_forward is None else self._step_central_critic(b, central_forward)
            self._update_targets()
            self.last_update = UpdateRecord(value=value_step, central=central_step, actor=actor_step)
            return self.last_update

        return _Background(critics)

    def _checked(self, batch: Batch) -> Batch:
        """The batch on this learner's device, refused when an action breaks its own mask."""
        b = batch.to(self.device)
        if not bool(b.mask.bool().gather(1, b.action.long().unsqueeze(1)).all()):
            raise ValueError("batch holds an action its own mask forbids")
        return b

    def _value_forward(self, b: Batch) -> _ValueForward:
        """V(o) and the advantage A1 handed to the actor, with the online V on both ends (paper eq. for
        ∇J1): the TD error, or GAE over it."""
        cfg = self.config
        reward, done = b.reward.float(), b.done.float()
        obs = ObsWindows(b.obs)
        values = self.value(obs)
        next_index = None if b.next_row is None else self._next_index(b)
        with torch.no_grad():
            if next_index is None:
                next_values = self.value(_require(b.next_obs, "next_obs"))
            else:
                # V(o') of most rows is another row's V(o), already computed: V runs again only on the
                # rows cut off by a timeout.
                where, ended, cut_off = next_index
                bank = torch.cat([values.detach(), self.value(_cut_off_obs(b, cut_off))])
                next_values = _gather_next(bank, where, ended)
            advantage = td_advantages(reward, values.detach(), next_values, done, cfg.gamma)
            if cfg.gae_lambda > 0.0:
                advantage = gae_advantages(
                    advantage, _require(b.next_row, "next_row"), cfg.gamma, cfg.gae_lambda
                )
        return _ValueForward(obs=obs, values=values, advantage=advantage, next_index=next_index)

    def _step_value_critic(self, b: Batch, forward: _ValueForward) -> CriticStep:
        """L(φ1): V regressed to r + γ·V̂(o')·(1 - done) (V̂ the target network), or to the λ-return."""
        cfg = self.config
        values = forward.values
        with torch.no_grad():
            if cfg.gae_lambda > 0.0:
                # The λ-return, from the online V the advantage was built on: V̂ is not read, so it is not
                # run (a fifth of the update's encoder passes).
                target = forward.advantage + values.detach()
            else:
                if forward.next_index is None:
                    next_target_values = self.value_target(_require(b.next_obs, "next_obs"))
                else:
                    where, ended, cut_off = forward.next_index
                    target_bank = torch.cat(
                        [self.value_target(forward.obs), self.value_target(_cut_off_obs(b, cut_off))]
                    )
                    next_target_values = _gather_next(target_bank, where, ended)
                target = td_targets(b.reward.float(), next_target_values, b.done.float(), cfg.gamma)
        loss = 0.5 * (target - values).pow(2).mean()
        self.opt_value.zero_grad(set_to_none=True)
        loss.backward()
        nn.utils.clip_grad_norm_(self.value.parameters(), cfg.max_grad_norm)
        self.opt_value.step()
        return CriticStep(
            prediction=values.detach(), target=target, advantage=forward.advantage, loss=float(loss.item())
        )

    def _next_index(self, b: Batch) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Where each row's o' is, given ``next_row``: row i's o' is row next_row[i]'s o, or row n + j for
        the j-th row cut off by a timeout (o' in no row: ``cut_off``); ``ended`` rows (done) have none,
        their V(o') is 0, which the TD target multiplies by 1 - done = 0 anyway."""
        next_row = _require(b.next_row, "next_row").long()
        has_next = next_row >= 0
        cut_off = torch.nonzero(~has_next & (b.done == 0)).squeeze(1)
        where = next_row.clone()
        where[cut_off] = b.obs.shape[0] + torch.arange(cut_off.numel(), device=next_row.device)
        ended = where < 0
        return where.clamp(min=0), ended, cut_off

    def _central_forward(self, b: Batch, probs: torch.Tensor) -> _CentralForward:
        """Q(s, ·) and COMA's advantage A2 = Q(s, a) - Σ_a' π(a'|o) Q(s, a'), from the Q before its step."""
        state = _require(b.state, "state")
        others = _require(b.others_actions, "others_actions")
        slot = _require(b.slot, "slot").long()
        value, differences = self.central.parts(state, others, slot)
        q_all = self.central.q_values(value, differences)
        return _CentralForward(
            q_all=q_all, state_value=value, advantage=coma_advantage(q_all.detach(), probs, b.action.long())
        )

    def _step_central_critic(self, b: Batch, forward: _CentralForward) -> CriticStep:
        """L(φ2): Q(s, a) regressed to R + γ·Q̂(s', a')·(1 - done), a' the action taken at t+1 (SARSA),
        or to the λ-return along each agent's steps."""
        cfg = self.config
        action = b.action.long()
        done = b.done.float()
        state = _require(b.state, "state")
        others = _require(b.others_actions, "others_actions")
        slot = _require(b.slot, "slot").long()
        joint_reward = _require(b.joint_reward, "joint_reward").float()
        next_valid = _require(b.next_valid, "next_valid").float()
        with torch.no_grad():
            # Rows without a next step carry arbitrary slot/action; clamp so gather stays in range,
            # the factor next_valid then zeroes them.
            next_q = self.central_target(
                _require(b.next_state, "next_state"),
                _require(b.next_others_actions, "next_others_actions"),
                _require(b.next_slot, "next_slot").long().clamp(0, STATE_SLOTS - 1),
            )
            next_a = _require(b.next_action, "next_action").long().clamp(0, N_ACTIONS - 1)
            next_q_taken = next_q.gather(1, next_a.unsqueeze(1)).squeeze(1)
            target = joint_reward + cfg.gamma * next_valid * (1.0 - done) * next_q_taken
        q_taken = forward.q_all.gather(1, action.unsqueeze(1)).squeeze(1)
        if cfg.q_lambda > 0.0:
            with torch.no_grad():
                q_now = self.central_target(state, others, slot).gather(1, action.unsqueeze(1)).squeeze(1)
                target = lambda_targets(
                    target, q_now, _require(b.next_row, "next_row"), cfg.gamma, cfg.q_lambda
                )
        if forward.state_value is None:
            loss = 0.5 * (target - q_taken).pow(2).mean()
        else:  # U(s) regresses to every row's target; D(s, a) to what U leaves (U held fixed there)
            value = forward.state_value
            residual = (target - value.detach() - (q_taken - value)).pow(2)
            if cfg.central_action_rows == "explored":  # D only where the action did not follow the state
                explored = torch.zeros_like(target) if b.explored is None else b.explored.to(target.dtype)
                residual = residual * explored * (len(explored) / explored.sum().clamp(min=1.0))
            loss = 0.5 * (target - value).pow(2).mean() + 0.5 * residual.mean()
        self.opt_central.zero_grad(set_to_none=True)
        loss.backward()
        nn.utils.clip_grad_norm_(self.central.parameters(), cfg.max_grad_norm)
        self.opt_central.step()
        return CriticStep(
            prediction=q_taken.detach(), target=target, advantage=forward.advantage, loss=float(loss.item())
        )

    def _policy(self, b: Batch, obs: ObsWindows) -> _Policy:
        """The masked policy before the actor's step, as both the COMA baseline and ∇J need it (``obs``:
        the batch's observations, as V cut them)."""
        dist = self.actor.distribution(obs, b.mask.bool())
        # Built in this order (log π, entropy, then the probabilities the entropy created): autograd
        # sums gradients in creation order, and this one keeps the float results bit for bit.
        log_prob = dist.log_prob(b.action.long())
        entropy = dist.entropy()
        anchor_kl = None
        if self.config.anchor_coef > 0.0:
            if self.anchor is None:
                raise RuntimeError("anchor_coef > 0 but no anchor: call anchor_to_start() first")
            with torch.no_grad():
                start = self.anchor.distribution(obs, b.mask.bool())
            anchor_kl = kl_divergence(dist, start)  # masked actions have probability 0 in both: no term
        return _Policy(log_prob=log_prob, entropy=entropy, probs=dist.probs, anchor_kl=anchor_kl)

    def _update_actor(
        self,
        actions: torch.Tensor,
        mask: torch.Tensor,
        explored: torch.Tensor | None,
        policy: _Policy,
        adv_v: torch.Tensor,
        adv_q: torch.Tensor | None,
    ) -> ActorStep:
        """∇J = α∇J1 + (1-α)∇J2 (α = 1 without the central critic), minus an optional entropy bonus; J2 on the
        rows ``coma_actions`` names, less each action's mean where ``coma_action_means`` asks (``actions``,
        ``mask``: the batch's)."""
        cfg = self.config
        log_probs, entropy = policy.log_prob, policy.entropy
        if explored is not None:  # an explored action is not the policy's: no policy gradient through it
            log_probs = log_probs * (~explored).to(log_probs.dtype)
        if cfg.normalize_advantages:
            adv_v = _standardised(adv_v)
        if adv_q is not None and cfg.coma_action_means == "subtract":
            adv_q = subtract_action_means(adv_q, actions, mask.bool().sum(dim=1) > 1)
        if adv_q is not None and cfg.coma_actions == "delta_only":
            delta = actions < N_DELTA_ACTIONS
            adv_q = torch.zeros_like(adv_q).masked_scatter(
                delta, _standardised(adv_q[delta]) if cfg.normalize_advantages else adv_q[delta]
            )
        elif adv_q is not None and cfg.normalize_advantages:
            adv_q = _standardised(adv_q)
        loss = combined_policy_loss(
            log_probs,
            adv_v,
            adv_q,
            cfg.effective_alpha,
            entropy=entropy,
            entropy_coef=cfg.entropy_coef,
        )
        if policy.anchor_kl is not None:
            loss = loss + cfg.anchor_coef * policy.anchor_kl.mean()
        self.opt_actor.zero_grad(set_to_none=True)
        loss.backward()
        grad_norm = nn.utils.clip_grad_norm_(self.actor.parameters(), cfg.max_grad_norm)
        self.opt_actor.step()
        return ActorStep(
            loss=float(loss.item()),
            entropy=float(entropy.detach().mean().item()),
            grad_norm=float(grad_norm.item()),
        )

    def _update_targets(self) -> None:
        """Soft-update the critics' target networks; Q̂ only where Q was trained."""
        _soft_update(self.value_target, self.value, self.config.target_tau)
        if self.config.use_central_critic:
            _soft_update(self.central_target, self.central, self.config.target_tau)

    def state_dict(self) -> dict[str, Any]:
        """Everything needed to resume: nets, targets, optimisers, config and layout ids.

        Plain tensors, numbers, strings and dicts only, so ``torch.load(weights_only=True)`` reads it.
        Waits for a critics' step in the background: a checkpoint holds the critics after it.
        """
        self.finish_critics()
        return {
            "format": CHECKPOINT_FORMAT,
            "obs_layout_id": OBS_LAYOUT_ID,
            "state_layout_id": STATE_LAYOUT_ID,
            "config": dataclasses.asdict(self.config),
            "actor": self.actor.state_dict(),
            "value": self.value.state_dict(),
            "central": self.central.state_dict(),
            "value_target": self.value_target.state_dict(),
            "central_target": self.central_target.state_dict(),
            "opt_actor": self.opt_actor.state_dict(),
            "opt_value": self.opt_value.state_dict(),
            "opt_central": self.opt_central.state_dict(),
        } | ({} if self.anchor is None else {"anchor": self.anchor.state_dict()})

    def load_state_dict(self, state: dict[str, Any], load_optimisers: bool = True) -> None:
        """Restore from ``state_dict()``. The config stays this learner's own (stage 2 may load stage 1).

        Raises InputError when the checkpoint was written for another observation or state layout.
        """
        if state.get("format") != CHECKPOINT_FORMAT:
            raise InputError(
                f"unknown checkpoint format {state.get('format')!r}, expected {CHECKPOINT_FORMAT}"
            )
        for key, expected in (("obs_layout_id", OBS_LAYOUT_ID), ("state_layout_id", STATE_LAYOUT_ID)):
            if state.get(key) != expected:
                raise InputError(
                    f"checkpoint {key} {state.get(key)!r} does not match this build's {expected!r}"
                )
        self.finish_critics()  # its step must not land on the loaded weights
        self.actor.load_state_dict(state["actor"])
        self.value.load_state_dict(state["value"])
        # A Q with another head (a stage-1 checkpoint, where Q is never trained, started under the other
        # ``central_head``) is not this learner's: its Q stays as initialised.
        same_central = state["central"].keys() == self.central.state_dict().keys()
        if same_central:
            self.central.load_state_dict(state["central"])
        self.value_target.load_state_dict(state["value_target"])
        if same_central:
            self.central_target.load_state_dict(state["central_target"])
        if self.config.anchor_coef > 0.0 and "anchor" in state:  # a resumed anchored stage keeps its π₀
            self.anchor = _frozen_copy(self.actor)
            self.anchor.load_state_dict(state["anchor"])
        if load_optimisers:
            self.opt_actor.load_state_dict(state["opt_actor"])
            self.opt_value.load_state_dict(state["opt_value"])
            if same_central:
                self.opt_central.load_state_dict(state["opt_central"])
