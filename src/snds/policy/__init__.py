r"""Policies: velocity fields in user units; SNDS projects a network onto a Lyapunov decrease.

:class:`Policy` is what every method of the library learns (SNDS and the baselines): a
velocity field over normalised model coordinates, with a Lyapunov function where the method
has one. The guarantee of SNDS is :func:`project`; :class:`StablePolicy` wires networks to it.

The package: :mod:`~snds.policy.base` (:class:`Policy`, what every method learns),
:mod:`~snds.policy.projection` (:func:`project`, the guarantee), :mod:`~snds.policy.config`
(:class:`PolicyConfig`, the architecture) and :mod:`~snds.policy.stable`
(:class:`StablePolicy`).
"""

from snds.policy.base import FieldTerms, LyapunovFunction, Policy, float64_copy
from snds.policy.config import DEFAULT_WARP_LAYERS, PolicyConfig
from snds.policy.projection import RECTIFIERS, project
from snds.policy.stable import StablePolicy

__all__ = [
    "DEFAULT_WARP_LAYERS",
    "RECTIFIERS",
    "FieldTerms",
    "LyapunovFunction",
    "Policy",
    "PolicyConfig",
    "StablePolicy",
    "float64_copy",
    "project",
]
