"""The interface every learning method implements: fit demonstrations, return a policy.

A :class:`Method` fits a :class:`~snds.policy.Policy` to demonstrations and reports how long
that took (:class:`Fitted`); the policy then predicts velocities, exposes its Lyapunov
function where it has one, and is saved and loaded by :mod:`snds.io`. SNDS and BC are one
:class:`NeuralMethod` each; the baselines live in :mod:`snds.baselines`; the registry that
names them all is :mod:`snds.methods`.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import ClassVar

from snds.batched import fit_many
from snds.data.demonstrations import Demonstrations, Normalization, Split
from snds.data.poses import PoseDemonstrations
from snds.policy import Policy, PolicyConfig, StablePolicy
from snds.recipes import recipe_for
from snds.se3 import make_pose_policy
from snds.spaces import SE3, Euclidean, Space
from snds.train import TrainConfig, TrainResult, fit


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
        spaces: The state spaces whose demonstrations it fits (positions only, unless a
            method says more).
    """

    name: str
    description: str
    has_lyapunov: bool
    spaces: ClassVar[tuple[type[Space], ...]] = (Euclidean,)

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


def train_network(
    policy: Policy,
    demos: Demonstrations,
    split: Split,
    config: TrainConfig,
    *,
    progress: bool = False,
) -> Fitted:
    """Trains a network policy with :func:`snds.train.fit` and records how (for any method
    whose policy is trained by gradient descent on the velocity loss: SNDS, BC, SDS-EF)."""
    result = fit(policy, demos, split, config=config, progress=progress)
    return Fitted(policy=policy, seconds=result.seconds, record=_record(config, result))


def _record(config: TrainConfig, result: TrainResult) -> dict:
    return {
        "train": config.to_dict(),
        "train_result": {
            "seconds": result.seconds,
            "steps": result.steps,
            "restarts": result.restarts,
            "stopped": result.stopped,
        },
    }


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
    """A fresh stable (or, with ``config.stable`` False, unconstrained) network policy for
    ``demos``, in their space: a :class:`~snds.policy.StablePolicy` for positions, a
    :class:`~snds.se3.PosePolicy` for poses.

    Arguments:
        demos: The demonstrations (they fix the normalisation, and for poses the chart).
        config: The architecture.
        seed: Seed of the initial weights.
    """
    return POLICY_FOR_DATA[type(demos)](demos, config=config, seed=seed)


@dataclass(frozen=True)
class NeuralMethod(Method):
    """SNDS and BC: a network policy (:func:`make_policy`: positions or poses) trained by
    :func:`snds.train.fit` with the recipe of its state space (:func:`snds.recipes.recipe_for`).

    Attributes:
        policy_config: The architecture; ``stable=False`` gives behavioural cloning, which
            has no Lyapunov function (:attr:`has_lyapunov` follows it).
    """

    name: str
    description: str
    policy_config: PolicyConfig
    spaces: ClassVar[tuple[type[Space], ...]] = (Euclidean, SE3)

    @property
    def has_lyapunov(self) -> bool:  # type: ignore[override]
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
        policy, config = self._setup(demos, seed, steps)
        return train_network(policy, demos, split, config, progress=progress)

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
                record=_record(config, result) | {"batched": len(setups)},
            )
            for policy, config, result in zip(policies, configs, results)
        ]

    def _setup(
        self, demos: Demonstrations, seed: int, steps: int | None
    ) -> tuple[StablePolicy, TrainConfig]:
        """The untrained policy and the training settings of a fit."""
        policy = make_policy(demos, config=self.policy_config, seed=seed)
        base = recipe_for(policy.space).train
        config = replace(base, seed=seed, steps=base.steps if steps is None else steps)
        return policy, config
