"""The methods a benchmark compares, in one visible registry.

A method is a name and how to build its policy. Today every method is a
:class:`~snds.policy.StablePolicy` with some :class:`~snds.policy.PolicyConfig`, trained with
the same loss and budget, so they differ only in what the config switches on:

* ``snds``: the stable policy (nominal network projected onto the Lyapunov decrease).
* ``bc``: behavioural cloning, the same nominal network without the projection.

Baselines built from other classes will add a field saying how to build them; until then a
method is fully described by its config.
"""

from __future__ import annotations

from dataclasses import dataclass

from snds.errors import SNDSError
from snds.policy import PolicyConfig


@dataclass(frozen=True)
class MethodSpec:
    """One method of the benchmark.

    Attributes:
        name: Its key in :data:`METHODS` and in result tables.
        description: One line for tables and help texts.
        policy_config: The architecture of its policy.
        has_lyapunov: Whether it carries a Lyapunov function, so whether the decrease
            condition can be checked (a method without one reports 0 samples checked).
    """

    name: str
    description: str
    policy_config: PolicyConfig
    has_lyapunov: bool


METHODS: dict[str, MethodSpec] = {
    "snds": MethodSpec(
        name="snds",
        description="stable neural dynamical system (projected onto the Lyapunov decrease)",
        policy_config=PolicyConfig(),
        has_lyapunov=True,
    ),
    "bc": MethodSpec(
        name="bc",
        description="behavioural cloning: the same network and loss, no stability guarantee",
        policy_config=PolicyConfig(stable=False),
        has_lyapunov=False,
    ),
}


def get_method(name: str) -> MethodSpec:
    """The method called ``name``; an :class:`~snds.errors.SNDSError` naming it if unknown."""
    try:
        return METHODS[name]
    except KeyError:
        raise SNDSError(f"unknown method {name!r}; choose from {', '.join(METHODS)}") from None
