"""The methods a benchmark compares, behind one small interface and one visible registry.

A :class:`Method` fits a :class:`~snds.policy.Policy` to demonstrations and reports how long
that took; the policy then predicts velocities, exposes its Lyapunov function where it has
one, and is saved and loaded by :mod:`snds.io`. Everything downstream (evaluation, the
stability report, plots, the benchmark) works on any policy.

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

from abc import ABC, abstractmethod
from dataclasses import dataclass, field

from snds.data.demonstrations import Demonstrations, Normalization, Split
from snds.errors import SNDSError
from snds.policy import Policy, PolicyConfig, StablePolicy


@dataclass(frozen=True)
class Fitted:
    """A fitted policy and how it was fitted.

    Attributes:
        policy: The policy, in the dtype it was trained in.
        seconds: Wall time of the fit (the optimisation or solve, not data loading).
        record: JSON-ready description of the fit (settings, steps, ...), saved beside it.
    """

    policy: Policy
    seconds: float
    record: dict = field(default_factory=dict)


class Method(ABC):
    """A way to learn a policy from demonstrations.

    Attributes:
        name: Its key in :data:`METHODS` and in result tables.
        description: One line for tables and help texts.
        has_lyapunov: Whether its policies carry a Lyapunov function, so whether the decrease
            condition can be checked (a method without one reports 0 samples checked).
    """

    name: str
    description: str
    has_lyapunov: bool

    @abstractmethod
    def fit(
        self,
        demos: Demonstrations,
        split: Split,
        *,
        seed: int = 0,
        steps: int | None = None,
        progress: bool = False,
    ) -> Fitted:
        """Fits a policy to the training samples of ``split``.

        Arguments:
            demos: All demonstrations of the task, in user units.
            split: Which samples train.
            seed: Seed of every random choice of the fit.
            steps: Optimiser steps instead of the method's default (ignored by methods that
                solve a convex program).
            progress: Show a progress bar (only on a terminal).
        """


@dataclass(frozen=True)
class NeuralMethod(Method):
    """SNDS and BC: a :class:`~snds.policy.StablePolicy` trained by :func:`snds.train.fit`.

    Attributes:
        policy_config: The architecture; ``stable=False`` gives behavioural cloning.
    """

    name: str
    description: str
    policy_config: PolicyConfig
    has_lyapunov: bool

    def fit(
        self,
        demos: Demonstrations,
        split: Split,
        *,
        seed: int = 0,
        steps: int | None = None,
        progress: bool = False,
    ) -> Fitted:
        from snds.train import TrainConfig, fit

        config = TrainConfig(seed=seed) if steps is None else TrainConfig(seed=seed, steps=steps)
        policy = StablePolicy(
            dim=demos.dim,
            normalization=Normalization.fit(demos),
            config=self.policy_config,
            seed=seed,
        )
        result = fit(policy, demos, split, config, progress=progress)
        record = {
            "train": config.to_dict(),
            "train_result": {
                "seconds": result.seconds,
                "steps": result.steps,
                "restarts": result.restarts,
                "stopped": result.stopped,
            },
        }
        return Fitted(policy=policy, seconds=result.seconds, record=record)


# The baselines subclass Method and Fitted above, so they are imported once those exist.
from snds.baselines.lpvds import LPVDS, LPVDSPolicy  # noqa: E402
from snds.baselines.sdsef import SDSEF, SDSEFPolicy  # noqa: E402
from snds.baselines.seds import SEDS, SEDSPolicy  # noqa: E402

METHODS: dict[str, Method] = {
    "snds": NeuralMethod(
        name="snds",
        description="stable neural dynamical system (projected onto the Lyapunov decrease)",
        policy_config=PolicyConfig(),
        has_lyapunov=True,
    ),
    "bc": NeuralMethod(
        name="bc",
        description="behavioural cloning: the same network and loss, no stability guarantee",
        policy_config=PolicyConfig(stable=False),
        has_lyapunov=False,
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
}


def get_method(name: str) -> Method:
    """The method called ``name``; an :class:`~snds.errors.SNDSError` naming it if unknown."""
    try:
        return METHODS[name]
    except KeyError:
        raise SNDSError(f"unknown method {name!r}; choose from {', '.join(METHODS)}") from None
