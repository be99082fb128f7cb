"""What fitting a method returns (:class:`Fitted`), and the fit of a network policy by
gradient descent that SNDS, BC and SDS-EF share (:func:`train_network`).

This sits below :mod:`snds.methods` and :mod:`snds.baselines`: the baselines return a
:class:`Fitted` and the registry of :mod:`snds.methods` names the baselines, so the two
cannot be one module without an import cycle.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from snds.data.demonstrations import Demonstrations, Split
from snds.data.poses import PoseDemonstrations
from snds.errors import SNDSError
from snds.policy import Policy
from snds.spaces import SE3, Euclidean, Phased, Space
from snds.train import TrainConfig, TrainResult, fit

__all__ = ["Fitted", "refuse_other_spaces", "train_network", "training_record"]


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


def training_record(config: TrainConfig, result: TrainResult) -> dict:
    """The record of a gradient-descent fit: its settings and what the optimisation did."""
    return {
        "train": config.to_dict(),
        "train_result": {
            "seconds": result.seconds,
            "steps": result.steps,
            "restarts": result.restarts,
            "stopped": result.stopped,
        },
    }


def train_network(
    policy: Policy,
    demos: Demonstrations,
    split: Split,
    *,
    config: TrainConfig,
    progress: bool = False,
) -> Fitted:
    """Trains a network policy with :func:`snds.train.fit` and records how (for any method
    whose policy is trained by gradient descent on the velocity loss: SNDS, BC, SDS-EF)."""
    result = fit(policy, demos, split, config=config, progress=progress)
    return Fitted(policy=policy, seconds=result.seconds, record=training_record(config, result))


def refuse_other_spaces(
    name: str, spaces: tuple[type[Space], ...], demos: Demonstrations | PoseDemonstrations
) -> None:
    """Raises unless ``demos`` lie in one of a method's ``spaces``: a method of positions must
    not take a pose's quaternion or a phase for more positions.

    Raises:
        SNDSError: One line naming the method, what the demonstrations are and the methods
            that fit them.
    """
    phased = getattr(demos, "phase_dim", 0) > 0
    posed = isinstance(demos, PoseDemonstrations)
    kind = Phased if phased else SE3 if posed else Euclidean
    if kind in spaces:
        return
    what = "poses" if posed else "positions"
    what += " with a phase (snds train's default)" if phased else ""
    hint = "train with --phase-codes 0 or " if phased and not posed else ""
    raise SNDSError(f"{name} fits positions only, not {what}: {hint}use snds or bc")
