"""The methods a benchmark compares, in one visible registry.

Every method implements :class:`snds.method.Method` (fit demonstrations, return a
:class:`~snds.policy.Policy`); everything downstream (evaluation, the stability report,
plots, the benchmark) works on any policy.

* ``snds``: the stable policy (nominal network projected onto the Lyapunov decrease).
* ``bc``: behavioural cloning, the same nominal network, loss and budget, no projection.
* ``lpvds``, ``seds``: Gaussian-mixture blends of stable linear systems
  (:mod:`snds.baselines.lpvds`, :mod:`snds.baselines.seds`).
* ``sdsef``: Euclideanizing flows, a learned diffeomorphism pulling back a linear latent
  system (:mod:`snds.baselines.sdsef`).

:data:`METHODS` maps names to methods (for the CLI and the benchmark);
:data:`POLICY_KINDS` maps the ``kind`` written into ``model.json`` to the class that loads it.
"""

from __future__ import annotations

from snds.baselines.lpvds import LPVDS, LPVDSPolicy
from snds.baselines.sdsef import SDSEF, SDSEFPolicy
from snds.baselines.seds import SEDS, SEDSPolicy
from snds.errors import SNDSError
from snds.method import Fitted, Method, NeuralMethod
from snds.policy import Policy, PolicyConfig, StablePolicy
from snds.se3 import PosePolicy

__all__ = ["METHODS", "POLICY_KINDS", "Fitted", "Method", "NeuralMethod", "get_method"]

METHODS: dict[str, Method] = {
    "snds": NeuralMethod(
        name="snds",
        description="stable neural dynamical system (projected onto the Lyapunov decrease)",
        policy_config=PolicyConfig(),
    ),
    "bc": NeuralMethod(
        name="bc",
        description="behavioural cloning: the same network and loss, no stability guarantee",
        policy_config=PolicyConfig(stable=False),
    ),
    "lpvds": LPVDS(),
    "seds": SEDS(),
    "sdsef": SDSEF(),
}

POLICY_KINDS: dict[str, type[Policy]] = {
    "stable": StablePolicy,
    "lpvds": LPVDSPolicy,
    "seds": SEDSPolicy,
    "sdsef": SDSEFPolicy,
    # SE(3): the stable policy on position and rotation vector (snds.se3).
    "se3": PosePolicy,
}


def get_method(name: str) -> Method:
    """The method called ``name``; an :class:`~snds.errors.SNDSError` naming it if unknown."""
    try:
        return METHODS[name]
    except KeyError:
        raise SNDSError(f"unknown method {name!r}; choose from {', '.join(METHODS)}") from None
