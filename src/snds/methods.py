"""The learning methods, what each must do, and the registry that names them.

Every method fits a :class:`~snds.policy.Policy` to demonstrations (:class:`Method`) and
reports how long that took (:class:`~snds.fitting.Fitted`); the policy then predicts
velocities, exposes its Lyapunov function where it has one, and is saved and loaded by
:mod:`snds.models`. Everything downstream (evaluation, the stability report, plots, the
benchmark) works on any policy.

* ``snds``: the stable policy, the nominal network projected onto the Lyapunov decrease
  (:data:`SNDS`); it reaches the target from every state, by construction.
* ``bc``: behavioural cloning (:data:`BC`), the same nominal network, loss and budget with no
  projection; it has no Lyapunov function and **no guarantee**.
* ``lpvds``, ``seds``: Gaussian-mixture blends of stable linear systems
  (:mod:`snds.baselines.lpvds`, :mod:`snds.baselines.seds`).
* ``sdsef``: Euclideanizing flows, a learned diffeomorphism pulling back a linear latent
  system (:mod:`snds.baselines.sdsef`).

:data:`METHODS` maps names to methods (for the CLI and the benchmark);
:data:`POLICY_KINDS` maps the ``kind`` written into ``model.json`` to the class that loads it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import ClassVar, Protocol, runtime_checkable

from snds.baselines.lpvds import LPVDS, LPVDSPolicy
from snds.baselines.sdsef import SDSEF, SDSEFPolicy
from snds.baselines.seds import SEDS, SEDSPolicy
from snds.batched import fit_many
from snds.data.demonstrations import Demonstrations, Normalization, Split
from snds.data.poses import PoseDemonstrations
from snds.errors import SNDSError
from snds.fitting import Fitted, train_network, training_record
from snds.policy import Policy, PolicyConfig, StablePolicy
from snds.recipes import RECIPES, SPACE_RECIPES, Recipe
from snds.se3 import PosePolicy, make_pose_policy
from snds.spaces import SE3, Euclidean, Phased, Space
from snds.train import TrainConfig

__all__ = [
    "BC",
    "METHODS",
    "POLICY_FOR_DATA",
    "POLICY_KINDS",
    "SNDS",
    "Fitted",
    "Method",
    "NeuralMethod",
    "get_method",
    "make_policy",
]


@runtime_checkable
class Method(Protocol):
    """A way to learn a policy from demonstrations.

    Attributes:
        name: Its key in :data:`METHODS` and in result tables.
        description: One line for tables and help texts.
        has_lyapunov: Whether its policies carry a Lyapunov function, so whether the decrease
            condition can be checked (a method without one reports 0 samples checked).
        spaces: The state spaces whose demonstrations it fits.
    """

    name: str
    description: str
    has_lyapunov: bool
    spaces: ClassVar[tuple[type[Space], ...]]

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
        ...


def _position_policy(demos: Demonstrations, *, config: PolicyConfig, seed: int) -> StablePolicy:
    config = replace(config, phase_dim=demos.phase_dim)
    return StablePolicy(
        dim=demos.dim, normalization=Normalization.fit(demos), config=config, seed=seed
    )


#: How a fresh network policy is made for each kind of demonstrations: positions, or poses
#: (:func:`snds.se3.make_pose_policy`).
POLICY_FOR_DATA = {Demonstrations: _position_policy, PoseDemonstrations: make_pose_policy}


def make_policy(
    demos: Demonstrations | PoseDemonstrations, *, config: PolicyConfig, seed: int = 0
) -> StablePolicy:
    """A fresh network policy for ``demos``, in their space: a
    :class:`~snds.policy.StablePolicy` for positions, a :class:`~snds.se3.PosePolicy` for
    poses. With ``config.stable`` True it reaches the target by construction; with False it
    is the unconstrained nominal network of behavioural cloning, with no guarantee.

    Arguments:
        demos: The demonstrations (they fix the normalisation, and for poses the chart).
        config: The architecture.
        seed: Seed of the initial weights.
    """
    return POLICY_FOR_DATA[type(demos)](demos, config=config, seed=seed)


@dataclass(frozen=True)
class NeuralMethod:
    """A network policy (:func:`make_policy`: positions or poses) trained by
    :func:`snds.train.fit` with the recipe of its state space (:meth:`recipe`):
    :data:`SNDS` and :data:`BC`.

    Attributes:
        name: Its key in :data:`METHODS`.
        description: One line for tables and help texts.
        policy_config: The architecture; ``stable=False`` gives behavioural cloning, which
            has no Lyapunov function (:attr:`has_lyapunov` follows it) and no guarantee.
    """

    name: str
    description: str
    policy_config: PolicyConfig
    spaces: ClassVar[tuple[type[Space], ...]] = (Euclidean, SE3, Phased)

    @property
    def has_lyapunov(self) -> bool:
        """Whether its policies carry V: those of a stable configuration."""
        return self.policy_config.stable

    def fit(
        self,
        demos: Demonstrations,
        split: Split,
        *,
        seed: int = 0,
        steps: int | None = None,
        progress: bool = False,
    ) -> Fitted:
        """Fits a fresh policy (see :meth:`Method.fit`)."""
        policy, config = self._setup(demos, seed, steps)
        return train_network(policy, demos, split, config=config, progress=progress)

    def fit_many(
        self,
        demos: Sequence[Demonstrations],
        splits: Sequence[Split],
        *,
        seeds: Sequence[int],
        steps: int | None = None,
        progress: bool = False,
    ) -> list[Fitted]:
        """Fits one policy per (demonstrations, split, seed) as one stacked model
        (:func:`snds.batched.fit_many`): the policies :meth:`fit` gives one by one, up to
        rounding. Each :attr:`Fitted.seconds` is its share, the stacked fit's wall time over
        the number of fits; the record holds that number as ``batched``.
        """
        setups = [self._setup(d, seed, steps) for d, seed in zip(demos, seeds, strict=True)]
        policies, configs = [p for p, _ in setups], [c for _, c in setups]
        results = fit_many(policies, demos, splits, configs, progress=progress)
        return [
            Fitted(
                policy=policy,
                seconds=result.seconds / len(setups),
                record=training_record(config, result) | {"batched": len(setups)},
            )
            for policy, config, result in zip(policies, configs, results)
        ]

    def recipe(self, space: type[Space], *, steps: int | None = None) -> Recipe:
        """What its fits in ``space`` build and train, as a recipe for
        :func:`snds.run.train_run`: the architecture :attr:`policy_config` and the training
        settings of the space's recipe (:data:`snds.recipes.SPACE_RECIPES`), with ``steps``
        optimiser steps if given; no phase of its own (the data carry theirs)."""
        train = RECIPES[SPACE_RECIPES[space]].train
        if steps is not None:
            train = replace(train, steps=steps)
        return Recipe(policy=self.policy_config, train=train, phase=None)

    def _setup(
        self, demos: Demonstrations, seed: int, steps: int | None
    ) -> tuple[StablePolicy, TrainConfig]:
        """The untrained policy and the training settings of a fit."""
        policy = make_policy(demos, config=self.policy_config, seed=seed)
        config = replace(self.recipe(type(policy.space), steps=steps).train, seed=seed)
        return policy, config


#: The stable neural dynamical system: the nominal network projected onto the Lyapunov
#: decrease, so every rollout reaches the target.
SNDS = NeuralMethod(
    name="snds",
    description="stable neural dynamical system (projected onto the Lyapunov decrease)",
    policy_config=PolicyConfig(),
)
#: Behavioural cloning: the nominal network of :data:`SNDS` with the same loss and budget,
#: used as the velocity field itself, without the projection. Its policy has no Lyapunov
#: function and no guarantee: it may stop short of the target, circle, or leave the data for
#: good. It is the ablation that shows what the projection buys.
BC = NeuralMethod(
    name="bc",
    description="behavioural cloning: the same network and loss, no stability guarantee",
    policy_config=PolicyConfig(stable=False),
)

METHODS: dict[str, Method] = {
    "snds": SNDS,
    "bc": BC,
    "lpvds": LPVDS(),
    "seds": SEDS(),
    "sdsef": SDSEF(),
}

POLICY_KINDS: dict[str, type[Policy]] = {
    # SNDS and BC (config.stable says which): the policy of :data:`SNDS` and :data:`BC`.
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
