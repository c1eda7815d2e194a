"""What an episode amounted to, and the one definition of success for training, validation and evaluation."""

from __future__ import annotations

from dataclasses import dataclass, field

from idas_sumo.env.scenario import Scenario

END_REASONS: tuple[str, ...] = ("finished", "collided", "removed", "timeout")
HARD_BRAKE_DETECT_MPS2 = -3.0  # a SUMO-driven car decelerating harder than this counts as a hard brake


def is_success(collisions: int, all_finished: bool) -> bool:
    """The paper's success: no collision and every controlled car finished (in time)."""
    return collisions == 0 and all_finished


def is_perfect(success: bool, impedes: int, hard_brakes_merge_zone: int) -> bool:
    """Success without any reward deduction: no impede, no flow penalty (no hard brake in the merging zone)."""
    return success and impedes == 0 and hard_brakes_merge_zone == 0


@dataclass
class EpisodeOutcome:
    """One episode's facts, and the one definition of success (docs/design-notes.md, "Definitions").

    Counts cover the steps in which some agent acted (a copy waiting for its next car scores nothing),
    except collisions, which count whenever the episode runs (a car may collide as it enters).
    """

    scenario: Scenario
    end_reasons: dict[str, str] = field(default_factory=dict)
    """Per controlled car that entered: 'finished', 'collided', 'removed' or 'timeout'."""
    collisions: int = 0
    """Collision pairs (any cars): SUMO's reports and the engine's geometric cross-check."""
    geometric_collisions: int = 0
    """Of those, the pairs only the geometric cross-check found (``geometric_collisions``)."""
    hard_brakes: int = 0
    """Hard brakes: agents choosing the hard-brake action, SUMO-driven cars decelerating harder than
    ``HARD_BRAKE_DETECT_MPS2``."""
    hard_brakes_merge_zone: int = 0
    """Of those, the ones within ``MERGE_ZONE_RADIUS_M`` of the merge point (each costs the flow penalty)."""
    impedes: int = 0
    """Agent-steps with an impede penalty."""
    returns: dict[str, float] = field(default_factory=dict)
    """Per agent: the sum of its rewards (its own parts: finish + collide + impede, and any extra own term)."""
    finish_times_s: dict[str, float] = field(default_factory=dict)
    """Per finished agent: the simulated time it crossed the finish line."""
    decision_steps: int = 0
    """Steps in which at least one agent acted."""
    agent_steps: int = 0
    start_time_s: float = 0.0
    """When the first agent could act (the insertion step ends at 0.2 s)."""
    end_time_s: float = 0.0
    timed_out: bool = False

    @property
    def duration_s(self) -> float:
        return self.end_time_s - self.start_time_s

    @property
    def all_finished(self) -> bool:
        """Every controlled car of the scenario finished."""
        return all(self.end_reasons.get(a) == "finished" for a in self.scenario.controlled_ids)

    @property
    def success(self) -> bool:
        return is_success(self.collisions, self.all_finished)

    @property
    def perfect(self) -> bool:
        return is_perfect(self.success, self.impedes, self.hard_brakes_merge_zone)
