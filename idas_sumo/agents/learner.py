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
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, ClassVar, Literal, TypeVar, get_args

import numpy as np
import numpy.typing as npt
import torch
from torch import nn
from torch.distributions import kl_divergence

from idas_sumo.agents.coma import ALPHA, combined_policy_loss
from idas_sumo.agents.critic_input import STATE_LAYOUT_ID
from idas_sumo.agents.critics import DEFAULT_CENTRAL_CRITIC, build_central_critic, check_central_critic
from idas_sumo.agents.networks import Actor, ObsWindows, ValueCritic
from idas_sumo.agents.returns import GAMMA, gae_advantages, lambda_targets, td_advantages, td_targets
from idas_sumo.env.actions import N_ACTIONS
from idas_sumo.env.layout import OBS_DIM, OBS_LAYOUT_ID
from idas_sumo.env.state_layout import STATE_SLOTS
from idas_sumo.errors import InputError

__all__ = [
    "ActorStep",
    "AdvantageScale",
    "Batch",
    "CriticStep",
    "GradientPart",
    "Learner",
    "LearnerConfig",
    "PendingPart",
    "UpdateRecord",
    "prepare_optimisers",
]

CHECKPOINT_FORMAT = 1

QHorizon = Literal["episode", "agent"]
"""What the centralised critic's target sums (``LearnerConfig.q_horizon``)."""
Q_HORIZONS: tuple[str, ...] = get_args(QHorizon)

CentralAdvantage = Literal["q", "return"]
"""What J2's advantage takes for the action taken (``LearnerConfig.central_advantage``)."""
CENTRAL_ADVANTAGES: tuple[str, ...] = get_args(CentralAdvantage)


@dataclass(frozen=True)
class LearnerConfig:
    """Hyper-parameters of the learner; validated once on construction."""

    RETIRED_KEYS: ClassVar[dict[str, Any]] = {
        "central_head": "per_action",
        "central_input": "scenario_slots",
        "coma_actions": "all",
        "coma_action_means": "keep",
        "central_action_rows": "all",
    }
    """Variants measured and retired (experiments/README.md): files that hold their default still load."""

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
    q_horizon: QHorizon = "episode"
    """How far Q(s, a)'s target sums the joint reward. 'episode' (the paper, L160: to the episode's end T):
    after its agent has finished or collided the target goes on along the agents still driving (it bootstraps
    from Q̂ at the episode's next step). 'agent': only along the agent's own steps, as every shipped policy
    was trained (before 2026-11-27): Q then leaves out the joint reward that comes after its agent has left,
    and credits an agent for staying on the road while others finish (experiments/stage2_collapse)."""
    central_advantage: CentralAdvantage = "q"
    """A2 for the action taken. 'q' (the paper): the critic's advantage, COMA's Q(s, a) - Σ_a' π(a'|o) Q(s, a').
    'return' (ours): Q's own target for the row (the λ-return of the joint reward, or r + γ·Q̂(s', a')) in place
    of Q(s, a), the counterfactual baseline kept: A2 + (target - Q(s, a)). Q's differences between one agent's
    actions are mostly fitting noise here (one 0.2 s action moves the joint return far less than what Q cannot
    predict), and J2 followed them consistently into stage 2's drift (experiments/stage2_critic)."""
    normalize_advantages: bool = False
    """Standardise A1 and A2 over each batch before the policy gradient (ours; the paper does not)."""
    central_critic: str = DEFAULT_CENTRAL_CRITIC
    """The centralised critic Q, by its name in ``agents/critics.py``'s registry: 'coma' (the paper's: one
    Q-value per own action over the scenario's vehicle slots, COMA's baseline over all actions)."""
    anchor_coef: float = 0.0
    """Weight of KL(π ‖ π₀) in the actor loss, π₀ the policy the stage started from (ours; 0: none, the paper).
    A trust region around the warm start: a push of J2 that the returns do not back costs the policy its
    distance from π₀. Set by ``anchor_to_start``."""
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
        if self.q_horizon not in Q_HORIZONS:
            raise InputError(f"q_horizon must be one of {', '.join(Q_HORIZONS)}, got {self.q_horizon!r}")
        if self.central_advantage not in CENTRAL_ADVANTAGES:
            raise InputError(
                f"central_advantage must be one of {', '.join(CENTRAL_ADVANTAGES)}, got {self.central_advantage!r}"
            )
        check_central_critic(self.central_critic)

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
    team_next_row: torch.Tensor | None = None  # (B,) int64 first row of the episode's next step, -1: none
    bootstrap_obs: torch.Tensor | None = None  # (cut-off rows, OBS_DIM): o' where next_row is -1, done 0

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
    """A1 (TD error or GAE) or A2 (COMA's, or with ``central_advantage`` 'return' the target less COMA's
    baseline): what the actor is handed, before any standardisation."""
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
    """The batch's observations, their grids' runs found once for V, V̂ and the actor."""
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
    advantage: torch.Tensor
    """A2 (the critic's ``advantage``, COMA's) from this Q and the policy before the actor's step."""


@dataclass(frozen=True)
class _QNext:
    """Per row, what Q's target bootstraps from: s', the others' and the own action a' there, the slot, and
    whether there is one (1) or the return ends (0); ``row``: the row it is, for λ-returns (None: unknown)."""

    state: torch.Tensor
    others: torch.Tensor
    slot: torch.Tensor
    action: torch.Tensor
    bootstrap: torch.Tensor
    row: torch.Tensor | None


@dataclass(frozen=True)
class _Policy:
    """The masked policy on a batch, with gradients: log π(a|o) (B,), entropy (B,), π (B, A)."""

    log_prob: torch.Tensor
    entropy: torch.Tensor
    probs: torch.Tensor
    anchor_kl: torch.Tensor | None = None
    """KL(π ‖ π₀) per row (B,), with gradients; None without an anchor."""


def _moments(adv: torch.Tensor) -> tuple[float, float | None]:
    """The mean of ``adv`` and the standard deviation (torch's, n - 1) of ``adv`` less that mean, as floats
    (float32 results, exact as Python floats); no deviation for one row."""
    mean = adv.mean()
    return float(mean.item()), float((adv - mean).std().item()) if adv.numel() > 1 else None


def _standardised(adv: torch.Tensor, moments: tuple[float, float | None]) -> torch.Tensor:
    """``adv`` less the mean, over the standard deviation (+ 1e-8); only centred without a deviation. The same
    float32 operations whether ``moments`` come from ``adv`` itself or from a whole batch ``adv`` is part of."""
    mean, std = moments
    centred = adv - torch.tensor(mean, dtype=adv.dtype, device=adv.device)
    if std is None:
        return centred
    return centred / (torch.tensor(std, dtype=adv.dtype, device=adv.device) + 1e-8)


@dataclass(frozen=True)
class AdvantageScale:
    """What ``normalize_advantages`` standardises A1 and A2 with: their moments (``_moments``) over a whole
    batch. A round computed in parts (``Learner.pending_part``) gets it from all the parts' advantages
    (``over``), so each part's actor gradient uses the whole batch's, as one ``update`` on the batch does."""

    value: tuple[float, float | None]
    central: tuple[float, float | None] | None

    @staticmethod
    def over(value: Sequence[torch.Tensor], central: Sequence[torch.Tensor] | None) -> AdvantageScale:
        """The moments of the concatenated parts' A1 (``value``) and A2 (``central``; None in stage 1)."""
        return AdvantageScale(
            _moments(torch.cat(list(value))), None if central is None else _moments(torch.cat(list(central)))
        )


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


def _sample(probs: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
    """One draw per row of ``probs``: exactly ``torch.multinomial(probs, 1, generator=generator)``, draws and
    generator state alike (for one sample torch's CPU multinomial is argmax(p / q) with q ~ Exp(1) drawn into a
    tensor of ``probs``' shape: the Gumbel-max trick; ``test_agents_networks.py`` checks the equality). A masked
    action (probability exactly 0) gives 0 / q = 0 and an allowed one a positive ratio, so it never comes out."""
    q = torch.empty_like(probs).exponential_(1, generator=generator)
    return (probs / q).argmax(dim=1)


@dataclass(frozen=True)
class GradientPart:
    """``Learner.gradient_part``: one part of a batch's update, before any step. ``grads``: per network
    ("value", "central", "actor"), the gradient of its loss (a mean over the part's rows) for each of its
    parameters in order; the steps' per-row tensors cover the part's rows. Plain tensors and floats: a rollout
    worker sends it back as it is."""

    rows: int
    value: CriticStep | None
    central: CriticStep | None
    actor: ActorStep | None
    grads: dict[str, list[torch.Tensor | None]]


@dataclass(frozen=True)
class PendingPart:
    """``Learner.pending_part``: a gradient part without its actor's gradient yet (``part.actor`` None, no
    "actor" in ``part.grads``), with the masked policy's graph and A1 that ``Learner.finish_part`` needs (both
    None for an empty batch). A2 is ``part.central.advantage``."""

    part: GradientPart
    policy: _Policy | None
    value_advantage: torch.Tensor | None

    @property
    def advantages(self) -> tuple[torch.Tensor | None, torch.Tensor | None]:
        """A1 and A2 (None in stage 1) of the part's rows, before any standardisation."""
        return self.value_advantage, None if self.part.central is None else self.part.central.advantage


def _require_moments(moments: tuple[float, float | None] | None) -> tuple[float, float | None]:
    if moments is None:
        raise ValueError("AdvantageScale has no A2 moments but the central critic is on")
    return moments


_OPTIMISERS = {"value": "opt_value", "central": "opt_central", "actor": "opt_actor"}
"""Each network's optimiser, by the learner's attribute names."""


def _gradient(loss: torch.Tensor, network: nn.Module) -> list[torch.Tensor | None]:
    """d loss / d each parameter of ``network``; None for one the loss does not reach (as ``backward`` leaves
    its ``grad``: Adam then skips it)."""
    return list(torch.autograd.grad(loss, list(network.parameters()), allow_unused=True))


def _weighed_sum(grads: Sequence[torch.Tensor | None], shares: Sequence[float]) -> torch.Tensor | None:
    """One parameter's gradient over the parts, each weighed by its share of the rows; exactly the part's own
    for one part; None where no part reaches the parameter."""
    if len(grads) == 1:
        return grads[0]
    total: torch.Tensor | None = None
    for grad, share in zip(grads, shares, strict=True):
        if grad is not None:
            total = grad * share if total is None else total + grad * share
    return total


def _weighed(values: Sequence[float], shares: Sequence[float]) -> float:
    """The parts' values weighed by their shares of the rows (the value itself for one part)."""
    if len(values) == 1:
        return values[0]
    return float(sum(v * s for v, s in zip(values, shares, strict=True)))


def _merged_critic(steps: Sequence[CriticStep | None], shares: Sequence[float]) -> CriticStep:
    """One critic's step over the parts: their rows' tensors in order, the loss weighed by the rows."""
    present = [s for s in steps if s is not None]
    if len(present) == 1:
        return present[0]
    return CriticStep(
        prediction=torch.cat([s.prediction for s in present]),
        target=torch.cat([s.target for s in present]),
        advantage=torch.cat([s.advantage for s in present]),
        loss=_weighed([s.loss for s in present], shares),
    )


def prepare_optimisers() -> None:
    """Import now what a process's first Adam optimiser imports when it is built (``torch._dynamo``, about 1.3
    CPU s): the training process does it while its rollout workers start instead of while they collect."""
    import torch._dynamo  # noqa: F401


class _LazyAdam:
    """A learner's Adam optimiser for one of its networks, built on first use.

    Building the first optimiser of a process imports ``torch._dynamo`` (slow to import), which a learner
    that only acts, a rollout worker's or an evaluated policy's, never needs. Adam keeps no state until its
    first step, so building it later changes nothing; a test may put another optimiser in its place.
    """

    def __init__(self, network: str, lr: str) -> None:
        self.network, self.lr = network, lr
        self.attr = ""

    def __set_name__(self, owner: type, name: str) -> None:
        self.attr = self.slot(name)

    @staticmethod
    def slot(name: str) -> str:
        """Where a learner keeps its optimiser ``name`` once built (absent before)."""
        return f"_{name}"

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

    Q is the critic ``config.central_critic`` names in ``agents/critics.py``'s registry.
    """

    opt_actor = _LazyAdam("actor", "lr_actor")
    opt_value = _LazyAdam("value", "lr_value")
    opt_central = _LazyAdam("central", "lr_central")

    def __init__(self, config: LearnerConfig, seed: int = 0) -> None:
        self.config = config
        self.device = torch.device(config.device)
        # Seed only the initialisation, without touching the caller's global RNG; sampling in `act`
        # uses the caller's generator.
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            self.actor = Actor().to(self.device)
            self.value = ValueCritic().to(self.device)
            self.central = build_central_critic(config.central_critic).to(self.device)
        self.value_target = _frozen_copy(self.value)
        self.central_target = _frozen_copy(self.central)
        self.last_update: UpdateRecord | None = None
        """What the last ``update`` regressed to and stepped with; None before the first."""
        self.anchor: Actor | None = None
        """π₀ of ``anchor_coef``: a frozen copy of the actor the stage started from; None without one."""

    def build_optimisers(self) -> None:
        """Build the three Adam optimisers now, each of which ``_LazyAdam`` would build on first use: the training
        process calls this while its rollout workers collect a round, so the first build's import of
        ``torch._dynamo`` (about 1.3 CPU s, unless ``prepare_optimisers`` ran) runs beside their work instead of
        after it, while they wait."""
        _ = (self.opt_actor, self.opt_value, self.opt_central)

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
        """Actions (B,) for B agents; never a masked one. ``generator`` must be a CPU generator. The actor runs
        as torch's modules (what evaluation, co-simulation and the envs' ``others`` call: their outputs stay
        the same bit for bit). A training rollout draws instead from ``rollout_logits`` with each episode's
        own stream (agents/sampling.py)."""
        if obs.ndim != 2 or obs.shape[1] != OBS_DIM or mask.shape != (obs.shape[0], N_ACTIONS):
            raise ValueError(
                f"expected obs (B, {OBS_DIM}) and mask (B, {N_ACTIONS}), got {obs.shape} and {mask.shape}"
            )
        allowed = np.asarray(mask) != 0
        if not allowed.any(axis=1).all():
            raise ValueError("every agent needs at least one allowed action (hard brake is never masked)")
        with torch.inference_mode():
            obs_t = torch.from_numpy(np.ascontiguousarray(obs, dtype=np.float32)).to(self.device)
            logits = self.actor.masked_logits(obs_t, torch.from_numpy(allowed).to(self.device)).cpu()
            if deterministic:
                actions = logits.argmax(dim=1)
            else:
                actions = _sample(torch.softmax(logits, dim=1), generator)
        out: npt.NDArray[np.int64] = actions.numpy().astype(np.int64)
        assert bool(allowed[np.arange(len(out)), out].all()), "sampled a masked action"
        return out

    def rollout_logits(self, obs: npt.NDArray[np.float32]) -> npt.NDArray[np.float32]:
        """The actor's unmasked logits (B, N_ACTIONS) for a rollout step's rows: on the CPU as compiled loops
        (``Actor.inference_logits``: several times faster on a step's few dozen rows, the same function to float
        rounding, so a near-tie between two actions may go the other way than through torch's modules)."""
        if self.device.type == "cpu":
            return self.actor.inference_logits(obs)
        with torch.inference_mode():
            obs_t = torch.from_numpy(np.ascontiguousarray(obs, dtype=np.float32)).to(self.device)
            logits: npt.NDArray[np.float32] = self.actor(obs_t).cpu().numpy()
        return logits

    def update(self, batch: Batch) -> dict[str, float]:
        """One gradient step on V, (Q), and the actor from B agent-steps; returns scalar metrics.

        Losses are means over the batch (the paper writes sums; a mean keeps the step size
        independent of B). Critics step before the actor, but both advantages are computed from the
        critics as they were before their step. What each part regressed to and handed on is kept in
        ``last_update``. The same as ``apply_gradients([gradient_part(batch)])``.
        """
        return self.apply_gradients([self.gradient_part(batch)])

    def gradient_part(self, batch: Batch, scale: AdvantageScale | None = None) -> GradientPart:
        """The gradients of V's, Q's and the actor's losses (means over ``batch``) and what they were built
        from, with no step taken: every part depends only on the weights before the update.

        A round's batch may be cut into parts at episode boundaries (an agent's rows link only within its
        episode): ``apply_gradients`` then weighs each part's means by its rows, which is the mean over the
        whole batch to float rounding. With ``normalize_advantages`` the advantages are standardised with
        ``scale`` (None: this batch's own moments): a part needs the whole batch's (``pending_part``).
        """
        return self.finish_part(self.pending_part(batch), scale)

    def pending_part(self, batch: Batch) -> PendingPart:
        """``gradient_part`` up to the actor's gradient: the critics' gradients, A1 and A2 (for the whole
        batch's ``AdvantageScale``) and the policy's graph, which ``finish_part`` then differentiates."""
        if batch.action.numel() == 0:
            return PendingPart(
                GradientPart(rows=0, value=None, central=None, actor=None, grads={}), None, None
            )
        b = self._checked(batch)
        value_forward = self._value_forward(b)
        value_step, value_grads = self._value_critic_gradient(b, value_forward)
        policy = self._policy(b, value_forward.obs)
        central_step = None
        grads: dict[str, list[torch.Tensor | None]] = {"value": value_grads}
        if self.config.use_central_critic:
            central_forward = self._central_forward(b, policy.probs.detach())
            central_step, grads["central"] = self._central_critic_gradient(b, central_forward)
        part = GradientPart(
            rows=int(b.action.shape[0]), value=value_step, central=central_step, actor=None, grads=grads
        )
        return PendingPart(part, policy, value_forward.advantage)

    def finish_part(self, pending: PendingPart, scale: AdvantageScale | None = None) -> GradientPart:
        """The pending part's actor gradient (advantages standardised with ``scale`` under
        ``normalize_advantages``; None: the part's own moments), and the whole part."""
        part, policy = pending.part, pending.policy
        if policy is None or pending.value_advantage is None:
            return part
        adv_q = None if part.central is None else part.central.advantage
        actor_step, actor_grads = self._actor_gradient(policy, pending.value_advantage, adv_q, scale)
        return dataclasses.replace(part, actor=actor_step, grads={**part.grads, "actor": actor_grads})

    def apply_gradients(self, parts: Sequence[GradientPart]) -> dict[str, float]:
        """One step of each network from the parts of one batch (in the batch's row order): each part's
        gradient weighed by its share of the rows (exactly the part's own with one part), clipped, one Adam
        step; then the targets' soft update. Returns the scalar metrics, as ``update``."""
        parts = [p for p in parts if p.rows > 0]
        if not parts:
            # A round in which no learning car acted (each entered too late, or the episodes were cut
            # short): nothing to learn from, so no step; the metrics row says so with zero losses.
            return dict.fromkeys(UPDATE_STAT_NAMES, 0.0)
        rows = sum(p.rows for p in parts)
        shares = [p.rows / rows for p in parts]
        norms = {
            name: self._step_network(name, [p.grads[name] for p in parts], shares) for name in parts[0].grads
        }
        value = _merged_critic([p.value for p in parts], shares)
        central = None if parts[0].central is None else _merged_critic([p.central for p in parts], shares)
        actors = [p.actor for p in parts if p.actor is not None]
        actor = ActorStep(
            loss=_weighed([a.loss for a in actors], shares),
            entropy=_weighed([a.entropy for a in actors], shares),
            grad_norm=norms["actor"],
        )
        self._update_targets()
        self.last_update = UpdateRecord(value=value, central=central, actor=actor)
        return self.last_update.stats()

    def _step_network(
        self, name: str, grads: Sequence[list[torch.Tensor | None]], shares: Sequence[float]
    ) -> float:
        """Set network ``name``'s gradient to the parts' weighed sum, clip it, step its Adam; returns the
        gradient's norm before clipping."""
        network: nn.Module = getattr(self, name)
        optimiser: torch.optim.Optimizer = getattr(self, _OPTIMISERS[name])
        optimiser.zero_grad(set_to_none=True)
        for i, param in enumerate(network.parameters()):
            total = _weighed_sum([part[i] for part in grads], shares)
            param.grad = None if total is None else total.to(param.device)
        norm = nn.utils.clip_grad_norm_(network.parameters(), self.config.max_grad_norm)
        optimiser.step()
        return float(norm.item())

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
        obs = ObsWindows(b.obs, blocks=True)
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

    def _value_critic_gradient(
        self, b: Batch, forward: _ValueForward
    ) -> tuple[CriticStep, list[torch.Tensor | None]]:
        """L(φ1) and its gradient: V regressed to r + γ·V̂(o')·(1 - done) (V̂ the target network), or to the
        λ-return."""
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
        step = CriticStep(
            prediction=values.detach(), target=target, advantage=forward.advantage, loss=float(loss.item())
        )
        return step, _gradient(loss, self.value)

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
        """Q(s, ·) and the critic's advantage A2 (COMA's: Q(s, a) - Σ_a' π(a'|o) Q(s, a')), from the Q before its
        step."""
        state = _require(b.state, "state")
        others = _require(b.others_actions, "others_actions")
        slot = _require(b.slot, "slot").long()
        q_all = self.central(state, others, slot)
        return _CentralForward(
            q_all=q_all, advantage=self.central.advantage(q_all.detach(), probs, b.action.long())
        )

    def _central_critic_gradient(
        self, b: Batch, forward: _CentralForward
    ) -> tuple[CriticStep, list[torch.Tensor | None]]:
        """L(φ2) and its gradient: Q(s, a) regressed to R + γ·Q̂(s', a'), a' the joint action taken at t+1 (SARSA), or to the
        λ-return; s' the agent's own next step, or with ``q_horizon`` 'episode' after its last one the episode's
        next step (``_q_next``)."""
        cfg = self.config
        action = b.action.long()
        state = _require(b.state, "state")
        others = _require(b.others_actions, "others_actions")
        slot = _require(b.slot, "slot").long()
        joint_reward = _require(b.joint_reward, "joint_reward").float()
        nxt = self._q_next(b)
        with torch.no_grad():
            # Rows without a next step carry arbitrary slot/action; clamp so gather stays in range,
            # the factor ``bootstrap`` then zeroes them.
            next_q = self.central_target(nxt.state, nxt.others, nxt.slot.long().clamp(0, STATE_SLOTS - 1))
            next_a = nxt.action.long().clamp(0, N_ACTIONS - 1)
            next_q_taken = next_q.gather(1, next_a.unsqueeze(1)).squeeze(1)
            target = joint_reward + cfg.gamma * nxt.bootstrap * next_q_taken
        if cfg.q_lambda > 0.0:
            with torch.no_grad():
                q_now = self.central_target(state, others, slot).gather(1, action.unsqueeze(1)).squeeze(1)
                target = lambda_targets(target, q_now, _require(nxt.row, "next_row"), cfg.gamma, cfg.q_lambda)
        loss, q_taken = self.central.loss(forward.q_all, action, target)
        advantage = forward.advantage
        if cfg.central_advantage == "return":  # the sampled return for the action taken, the baseline kept
            advantage = advantage + (target - q_taken.detach())
        step = CriticStep(
            prediction=q_taken.detach(), target=target, advantage=advantage, loss=float(loss.item())
        )
        return step, _gradient(loss, self.central)

    def _q_next(self, b: Batch) -> _QNext:
        """Where Q's target bootstraps from. 'agent' horizon (or a batch without ``team_next_row``): the agent's
        own next step, none after it finished or collided. 'episode': the same while the agent drives on; after
        its last step the episode's next step (any agent's row there: Q̂(s', a') estimates the same joint
        return from every agent's slot), none only once the episode is over."""
        next_valid = _require(b.next_valid, "next_valid").float()
        if self.config.q_horizon == "agent" or b.team_next_row is None:
            return _QNext(
                state=_require(b.next_state, "next_state"),
                others=_require(b.next_others_actions, "next_others_actions"),
                slot=_require(b.next_slot, "next_slot"),
                action=_require(b.next_action, "next_action"),
                bootstrap=next_valid * (1.0 - b.done.float()),
                row=b.next_row,
            )
        own = _require(b.next_row, "next_row").long()
        row = torch.where(own >= 0, own, b.team_next_row.long())
        at = row.clamp(min=0)
        return _QNext(
            state=_require(b.state, "state")[at],
            others=_require(b.others_actions, "others_actions")[at],
            slot=_require(b.slot, "slot")[at],
            action=b.action[at],
            bootstrap=(row >= 0).float(),
            row=row,
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

    def _actor_gradient(
        self, policy: _Policy, adv_v: torch.Tensor, adv_q: torch.Tensor | None, scale: AdvantageScale | None
    ) -> tuple[ActorStep, list[torch.Tensor | None]]:
        """∇J = α∇J1 + (1-α)∇J2 (α = 1 without the central critic), minus an optional entropy bonus, plus an
        optional KL anchor; the step's grad_norm is filled in by ``apply_gradients``."""
        cfg = self.config
        log_probs, entropy = policy.log_prob, policy.entropy
        if cfg.normalize_advantages:
            if scale is None:
                scale = AdvantageScale.over([adv_v], None if adv_q is None else [adv_q])
            adv_v = _standardised(adv_v, scale.value)
            if adv_q is not None:
                adv_q = _standardised(adv_q, _require_moments(scale.central))
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
        step = ActorStep(
            loss=float(loss.item()), entropy=float(entropy.detach().mean().item()), grad_norm=0.0
        )
        return step, _gradient(loss, self.actor)

    def _update_targets(self) -> None:
        """Soft-update the critics' target networks; Q̂ only where Q was trained."""
        _soft_update(self.value_target, self.value, self.config.target_tau)
        if self.config.use_central_critic:
            _soft_update(self.central_target, self.central, self.config.target_tau)

    def state_dict(self) -> dict[str, Any]:
        """Everything needed to resume: nets, targets, optimisers, config and layout ids.

        Plain tensors, numbers, strings and dicts only, so ``torch.load(weights_only=True)`` reads it.
        """
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
            **{name: self._optimiser_state(name) for name in _OPTIMISERS.values()},
        } | ({} if self.anchor is None else {"anchor": self.anchor.state_dict()})

    def _optimiser_state(self, name: str) -> dict[str, Any] | None:
        """Optimiser ``name``'s state; None while it is not built (``_LazyAdam``: a fresh Adam holds none). Building
        it here would import ``torch._dynamo``, which a stop during a first round's import has left broken."""
        built: torch.optim.Optimizer | None = self.__dict__.get(_LazyAdam.slot(name))
        return None if built is None else built.state_dict()

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
        self.actor.load_state_dict(state["actor"])
        self.value.load_state_dict(state["value"])
        # A Q of another critic (a checkpoint trained with a retired or another registered critic; a stage-1
        # one never trains Q) is not this learner's: its Q stays as initialised, the actor and V load.
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
            for network, name in _OPTIMISERS.items():
                if network == "central" and not same_central:
                    continue
                saved = state[name]
                if saved is None:  # saved before it was built: a fresh one, built on first use
                    self.__dict__.pop(_LazyAdam.slot(name), None)
                else:
                    getattr(self, name).load_state_dict(saved)
