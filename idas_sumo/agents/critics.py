"""Centralised critics by name: the learner builds ``LearnerConfig.central_critic`` from this registry.

The extension point for the centralised critic (as EPyMARL's ``critic_registry``): the core registers the
paper's COMA critic Q(s, a, b) as "coma", the default; a variant registers its own class (a subclass of
``networks.CentralCriticBase``) under a name of its own, before the config that names it is built.
"""

from __future__ import annotations

from collections.abc import Callable

from idas_sumo.agents.networks import CentralCritic, CentralCriticBase
from idas_sumo.config import did_you_mean
from idas_sumo.errors import InputError

__all__ = [
    "CENTRAL_CRITICS",
    "DEFAULT_CENTRAL_CRITIC",
    "build_central_critic",
    "check_central_critic",
    "register_central_critic",
]

CriticFactory = Callable[[], CentralCriticBase]

CENTRAL_CRITICS: dict[str, CriticFactory] = {}
"""Every registered centralised critic, by name: a callable that builds a fresh one (its class)."""

DEFAULT_CENTRAL_CRITIC = "coma"
"""The paper's critic: per-action Q-values over the scenario's vehicle slots, COMA's baseline over all actions."""


def register_central_critic(name: str) -> Callable[[CriticFactory], CriticFactory]:
    """Decorator: register a critic class (or any callable that builds one) under ``name``; a taken name is
    refused."""

    def register(factory: CriticFactory) -> CriticFactory:
        if name in CENTRAL_CRITICS:
            raise ValueError(f"a central critic named {name!r} is registered already")
        CENTRAL_CRITICS[name] = factory
        return factory

    return register


def check_central_critic(name: str) -> None:
    """Refuse a name no critic is registered under, in one line with the closest registered one."""
    if name not in CENTRAL_CRITICS:
        raise InputError(
            f"central_critic {name!r} is not a registered critic "
            f"(registered: {', '.join(sorted(CENTRAL_CRITICS))}){did_you_mean(name, CENTRAL_CRITICS)}"
        )


def build_central_critic(name: str) -> CentralCriticBase:
    """A fresh critic of the registered ``name`` (its initialisation draws from torch's global generator)."""
    check_central_critic(name)
    critic = CENTRAL_CRITICS[name]()
    if not isinstance(critic, CentralCriticBase):
        raise TypeError(f"central critic {name!r} built a {type(critic).__name__}, not a CentralCriticBase")
    return critic


register_central_critic(DEFAULT_CENTRAL_CRITIC)(CentralCritic)
