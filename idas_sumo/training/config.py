"""The one training configuration: a frozen dataclass loaded from TOML, then CLI flags override it.

Defaults are the paper's (Section V): Robot World 20k episodes with J1 only, Intelligent World 50k
episodes with J1 + J2 (α = 0.7), IDAS-direct 70k episodes in the Intelligent World from scratch.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar, Literal

from idas_sumo.agents.learner import LearnerConfig
from idas_sumo.config import MAX_EPISODES, MAX_SCENARIOS, from_dict, load_toml, to_plain
from idas_sumo.env.config import EnvConfig
from idas_sumo.env.scenario import TrafficConfig
from idas_sumo.env.state_layout import STATE_SLOTS
from idas_sumo.errors import InputError
from idas_sumo.sim.multinet import MAX_COPIES
from idas_sumo.training.geometry import GeometryConfig
from idas_sumo.training.worker_count import rollout_workers

__all__ = [
    "RESUME_FIELDS",
    "STAGES",
    "VALIDATION_CRITERIA",
    "Stage",
    "TrainConfig",
    "ValidationCriterion",
    "load_train_config",
    "train_config_from_dict",
]

Stage = Literal["robot", "intelligent", "direct", "curriculum"]
ValidationCriterion = Literal["joint_return", "success_then_return"]
VALIDATION_CRITERIA: tuple[str, ...] = ("joint_return", "success_then_return")

STAGES: tuple[str, ...] = ("robot", "intelligent", "direct", "curriculum")

ROBOT_EPISODES = 20_000  # paper: stage 1, Robot World
INTELLIGENT_EPISODES = 50_000  # paper: stage 2, Intelligent World
DIRECT_EPISODES = 70_000  # paper: IDAS-direct, no curriculum
RESUME_FIELDS: tuple[str, ...] = (
    "workers",
    "copies",
    "robot_episodes",
    "intelligent_episodes",
    "direct_episodes",
)
"""What a resumed run takes from the new config: how many processes and episodes side by side, and how far to train (a larger
budget extends a finished run). Everything else is the run's own, from its checkpoint."""


class ConfigValueError(InputError, ValueError):
    """A value out of range; a ValueError too so ``from_dict`` prefixes the file name."""


def _robot_traffic() -> TrafficConfig:
    return TrafficConfig(max_controlled=1)


def _intelligent_traffic() -> TrafficConfig:
    return TrafficConfig(max_controlled=0)


@dataclass(frozen=True)
class TrainConfig:
    """Everything a training run needs besides the network file and the output directory."""

    RETIRED_KEYS: ClassVar[dict[str, Any]] = {"critic_exploration": 0.0, "standstill": "keeps_command"}
    """Variants measured and retired (experiments/README.md): files that hold their default still load."""
    FLAT_FIELDS: ClassVar[tuple[str, ...]] = ("env",)
    """``env``'s keys sit flat in a recipe and a checkpoint (``max_episode_s = 40``, ``[reward]``), as always."""

    stage: Stage = "curriculum"
    """What to train: 'robot' (stage 1 only, gives IDAS-V), 'intelligent' (stage 2 only; from
    ``init_from`` when given, else from scratch), 'direct' (IDAS-direct: stage 2 from scratch for
    ``direct_episodes``) or 'curriculum' (robot, then intelligent from the robot weights: IDAS)."""
    robot_episodes: int = ROBOT_EPISODES
    """Episodes of the Robot World stage (paper: 20000)."""
    intelligent_episodes: int = INTELLIGENT_EPISODES
    """Episodes of the Intelligent World stage (paper: 50000)."""
    direct_episodes: int = DIRECT_EPISODES
    """Episodes of IDAS-direct (paper: 70000)."""
    robot_traffic: TrafficConfig = field(default_factory=_robot_traffic)
    """Scenario generator of the Robot World: one learning agent among SUMO's robot cars
    (``max_controlled`` = 1), the paper's traffic (8 cars, staggered entries)."""
    intelligent_traffic: TrafficConfig = field(default_factory=_intelligent_traffic)
    """Scenario generator of the Intelligent World: 8 learning agents (paper L211), split at random over
    the roads, entering at random times (L225), no robot cars."""
    learner: LearnerConfig = field(default_factory=LearnerConfig)
    """Learner hyper-parameters; ``use_central_critic`` is set per stage (off in 'robot', on otherwise)."""
    env: EnvConfig = field(default_factory=EnvConfig)
    """The episode rules of training and validation (evaluation has its own): ``max_episode_s``,
    ``[reward]``, ``safety_mask`` (every shipped policy was trained with 'own_lane', the paper's) and
    ``junction`` (which merge of a net with several; "": its only one), flat keys in a recipe."""
    episodes_per_update: int = 16
    """Episodes collected with one policy before one learner update on all their agent-steps (ours; the
    paper gives no batch size. Every shipped recipe uses 16: with 4, stage 2 drifted within 150 episodes)."""
    checkpoint_every: int = 1000
    """Write ``checkpoint.pt`` every this many episodes (also at every stage end and on Ctrl-C)."""
    workers: int = 0
    """Rollout processes; 1 collects in the training process; 0 (the default): one per CPU this process may use,
    at most one per ``EPISODES_PER_WORKER`` episodes of a round (``rollout_workers``). Results do not depend on
    it."""
    copies: int = 16
    """Episodes a rollout worker runs side by side in one SUMO run (1 to MAX_COPIES). Results do not
    depend on it."""
    seed: int = 0
    """Seeds network initialisation, scenarios and action sampling."""
    init_from: str = ""
    """Optional checkpoint whose weights start the first stage (e.g. a robot run for stage 'intelligent')."""
    validate_every: int = 0
    """Score the greedy policy on held-out scenarios every this many episodes and keep the best
    weights as ``<stage>_best.pt``; 0: never (ours, not the paper's)."""
    validation_scenarios: int = 40
    """Held-out scenarios per validation, drawn from the stage's traffic generator."""
    validation_seed: int = 123
    """Seed of the held-out scenarios: apart from ``seed`` and from evaluation's 2019."""
    validation_max_episode_s: float = 0.0
    """The validation episodes' timeout (s); 0 (the default): the training episodes' ``max_episode_s``. Ours:
    60 validates at evaluation's length, where a late entry that 40 s cannot finish does not count as a
    failure (``experiments/validation_60s``)."""
    validation_criterion: ValidationCriterion = "joint_return"
    """What picks ``<stage>_best.pt``: 'joint_return' (the paper's objective) or 'success_then_return'
    (ours: the success rate first, the joint return among equals)."""
    geometry: GeometryConfig | None = None
    """``[geometry]``: train each round on a generated merge drawn from these ranges (training/geometry.py);
    None (no table): every round on the run's net. Validation runs on the run's net unless the table's
    ``validation_geometries`` draws merges for it."""

    @property
    def longest_episode_s(self) -> float:
        """The longest episode the run drives (its training or its validation episodes): what its net's roads
        must hold."""
        return max(self.env.max_episode_s, self.validation_max_episode_s)

    @property
    def validation_limit_s(self) -> float | None:
        """The validation episodes' own timeout, or None where they keep the training episodes'."""
        return self.validation_max_episode_s or None

    def __post_init__(self) -> None:
        for name in (
            "robot_episodes",
            "intelligent_episodes",
            "direct_episodes",
            "episodes_per_update",
            "checkpoint_every",
            "validation_scenarios",
        ):
            if getattr(self, name) < 1:
                raise ConfigValueError(f"{name} must be at least 1, got {getattr(self, name)}")
        for name in ("validation_scenarios", "episodes_per_update"):  # drawn up front: a count is memory
            if getattr(self, name) > MAX_SCENARIOS:
                raise ConfigValueError(f"{name} must be at most {MAX_SCENARIOS}, got {getattr(self, name)}")
        for name in (
            "robot_episodes",
            "intelligent_episodes",
            "direct_episodes",
            "checkpoint_every",
            "validate_every",
        ):
            if getattr(self, name) > MAX_EPISODES:
                raise ConfigValueError(f"{name} must be at most {MAX_EPISODES}, got {getattr(self, name)}")
        if self.geometry is not None and self.geometry.validation_geometries > self.validation_scenarios:
            # Each validation merge is a net built up front: more merges than scenarios only costs builds.
            raise ConfigValueError(
                f"geometry.validation_geometries ({self.geometry.validation_geometries}) must be at most "
                f"validation_scenarios ({self.validation_scenarios}): each validation merge needs a scenario"
            )
        for name in ("seed", "validate_every", "validation_seed", "workers"):
            if getattr(self, name) < 0:
                raise ConfigValueError(f"{name} must be non-negative, got {getattr(self, name)}")
        if not 1 <= self.copies <= MAX_COPIES:
            raise ConfigValueError(f"copies must be in [1, {MAX_COPIES}], got {self.copies}")
        if self.validation_max_episode_s != 0.0:
            try:  # the same bounds as every episode's timeout
                dataclasses.replace(self.env, max_episode_s=self.validation_max_episode_s)
            except ValueError as err:
                raise ConfigValueError(f"validation_max_episode_s: {err}") from None
        if self.validation_criterion not in VALIDATION_CRITERIA:
            raise ConfigValueError(
                f"validation_criterion must be one of {', '.join(VALIDATION_CRITERIA)}, "
                f"got {self.validation_criterion!r}"
            )
        if self.stage not in STAGES:
            raise ConfigValueError(f"stage must be one of {', '.join(STAGES)}, got {self.stage!r}")
        if self.robot_traffic.max_controlled < 1:
            raise ConfigValueError("robot_traffic.max_controlled must be at least 1 (the learning agents)")
        for name in ("robot_traffic", "intelligent_traffic"):
            traffic: TrafficConfig = getattr(self, name)
            if traffic.max_total > STATE_SLOTS:
                what = "n_vehicles" if traffic.n_vehicles else "2 * max_vehicles_per_road"
                raise ConfigValueError(
                    f"{name}: {what} must be at most {STATE_SLOTS} "
                    f"(the critic's state has {STATE_SLOTS} vehicle slots)"
                )

    def rollout_workers(self, gui: bool = False) -> int:
        """The rollout processes a run starts (``worker_count.rollout_workers``: ``workers``, or for 0 one per
        CPU and per ``EPISODES_PER_WORKER`` episodes of a round, whose size the stages' budgets may cut)."""
        budget = max(self.robot_episodes, self.intelligent_episodes, self.direct_episodes)
        return rollout_workers(self.workers, self.episodes_per_update, budget, gui)

    def with_overrides(
        self,
        stage: str | None = None,
        episodes: int | None = None,
        workers: int | None = None,
        seed: int | None = None,
        copies: int | None = None,
        safety_mask: str | None = None,
        junction: str | None = None,
    ) -> TrainConfig:
        """The command line's flags on top of the file: ``episodes`` sets every stage's count."""
        changes: dict[str, Any] = {}
        if stage is not None:
            changes["stage"] = stage
        if episodes is not None:
            changes.update(robot_episodes=episodes, intelligent_episodes=episodes, direct_episodes=episodes)
        if workers is not None:
            changes["workers"] = workers
        if seed is not None:
            changes["seed"] = seed
        if copies is not None:
            changes["copies"] = copies
        env: dict[str, Any] = {}
        if safety_mask is not None:
            env["safety_mask"] = safety_mask
        if junction is not None:
            env["junction"] = junction or None
        if env:
            changes["env"] = dataclasses.replace(self.env, **env)
        return dataclasses.replace(self, **changes)

    def as_dict(self) -> dict[str, Any]:
        """Plain nested dict (TOML/checkpoint friendly), the episode rules flat as a recipe writes them."""
        return to_plain(self)


def train_config_from_dict(data: Any, where: str) -> TrainConfig:
    """Validate a plain dict (a TOML table or a checkpoint's config) into a TrainConfig."""
    try:
        return from_dict(TrainConfig, data, where)
    except InputError as err:
        msg = str(err)
        if msg.startswith(where):
            raise
        raise InputError(f"{where}: {msg}") from None  # e.g. LearnerConfig's own range checks


def load_train_config(path: str | Path) -> TrainConfig:
    """Read a training TOML (see ``scenarios/train_default.toml``); errors name the file and key."""
    p = Path(path)
    return train_config_from_dict(load_toml(p), str(p))
