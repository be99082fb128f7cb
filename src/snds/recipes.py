"""Named presets of the library: a policy architecture with its training settings.

``snds train`` starts from these, and so do the benchmarks and the tests, so that a Python
user who calls :func:`snds.fit` with ``RECIPES[name].train`` on a policy built from
``RECIPES[name].policy`` trains exactly what the command line trains. The measurements that
chose each preset are in ``docs/design.md`` ("Presets").
"""

from __future__ import annotations

from dataclasses import dataclass, field

from snds.phase import Phase
from snds.policy import PolicyConfig
from snds.spaces import SE3, Euclidean, Phased, Space
from snds.train import TrainConfig

__all__ = ["ARCHITECTURES", "RECIPES", "SPACE_RECIPES", "Recipe", "recipe_for"]


@dataclass(frozen=True)
class Recipe:
    """A preset: how to build a policy and how to train it.

    Attributes:
        policy: The architecture of the policy (:class:`snds.policy.PolicyConfig`).
        train: The optimisation settings (:class:`snds.train.TrainConfig`).
        phase: The phase appended to the demonstrations' states before training
            (:class:`snds.phase.Phase`: which demonstration a rollout follows and how far
            along it is, so that paths that cross or wind are retraced); None: none, the
            policy is a field over positions (or poses) alone.
    """

    policy: PolicyConfig = field(default_factory=PolicyConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    phase: Phase | None = field(default_factory=Phase)


#: The presets by name.
#:
#: - ``default``: the library's defaults, for positions in R^n and poses in SE(3), with a
#:   phase of 3 codes in the state (:class:`snds.phase.Phase`).
#: - ``compact``: smaller networks (hidden (64, 64), 64 Fourier features), for controllers
#:   that evaluate large batches.
#: - ``pose``: the former training settings of SE(3) pose models, kept for their models:
#:   V's shape penalty on (``shape_weight`` 0.01), no noise on the training states
#:   (``position_noise`` 0), no noise correction, no tracking, no alignment term
#:   (``align_weight`` 0).
RECIPES: dict[str, Recipe] = {
    "default": Recipe(),
    "compact": Recipe(policy=PolicyConfig(hidden=(64, 64), fourier_features=64)),
    "pose": Recipe(
        train=TrainConfig(
            shape_weight=0.01,
            position_noise=0.0,
            noise_correction=0.0,
            tracking_gain=0.0,
            align_weight=0.0,
        )
    ),
}

#: The recipes that differ from ``default`` in the policy's network sizes only: the choices
#: of ``snds train --architecture``.
ARCHITECTURES: tuple[str, ...] = ("default", "compact")

#: The recipe whose training settings each state space trains with by default.
SPACE_RECIPES: dict[type[Space], str] = {Euclidean: "default", Phased: "default", SE3: "default"}


def recipe_for(space: Space) -> Recipe:
    """The recipe a policy in ``space`` trains with by default (:data:`SPACE_RECIPES`):
    ``default`` for positions and poses, with a phase or not."""
    return RECIPES[SPACE_RECIPES[type(space)]]
