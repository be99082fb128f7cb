r"""State spaces: the few operations in which positions in :math:`\mathbb{R}^n` and poses in
SE(3) differ.

A state is one row of :attr:`Space.dim` numbers, a velocity one row of
:attr:`Space.tangent_dim` numbers, both in user units. Rollouts, the guarded step, the
stability check, the metrics, the plots and the export ask the space of a policy
(:attr:`snds.policy.Policy.space`) how a state moves along a velocity (:meth:`Space.advance`),
how far two states are apart (:meth:`Space.errors`, one distance per component: position,
and angle for a pose), what scale each of those has for a task of a given extent, and how
random states are drawn; everything else is one code path.

- :class:`Euclidean`: positions :math:`x \in \mathbb{R}^n`; :math:`x + h v`.
- :class:`Phased`: positions :math:`x \in \mathbb{R}^n` followed by a phase
  :math:`\psi \in \mathbb{R}^m` (:mod:`snds.phase`); a step is the Euclidean one, the
  errors are the positions' alone.
- :class:`SE3`: poses :math:`(p, q)` of a position and a unit quaternion (x, y, z, w), 7
  numbers; velocities are twists :math:`(v, \omega)` with the angular velocity in the world
  frame; a step is :math:`p + h v`, :math:`\exp(h \omega)\, q` (so orientations stay on
  SO(3)).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import roma
import torch
from torch import Tensor

from snds.so3 import random_quaternions, relative_rotvec, rotate

__all__ = ["SE3", "Euclidean", "Phased", "Space"]


class Space(ABC):
    """The set of a policy's states (see the module docstring).

    Attributes:
        dim: Numbers per state row.
        tangent_dim: Numbers per velocity row.
        position_dim: The leading numbers of a state that are a position (what DTW and the
            path plots compare).
        phase_dim: The trailing numbers of a state that are a phase (:mod:`snds.phase`; 0:
            none). A pose has more numbers than its position and no phase.
        error_names: Names of the components of :meth:`errors`; the first is always the
            distance of the positions.
        velocity_names: Names of the blocks of a velocity row, the first the positions' own
            velocity ("velocity"; a twist adds "angular_velocity").
        velocity_sizes: Their sizes, summing to :attr:`tangent_dim`.
        velocity_units: For each block, the error component (an index into
            :attr:`error_names`) whose unit it moves in per second.
        state_text: What a state row holds, in words (exported models' metadata).
        velocity_text: What a velocity row holds, in words.
    """

    dim: int
    tangent_dim: int
    position_dim: int
    phase_dim: ClassVar[int] = 0
    error_names: tuple[str, ...]
    velocity_names: tuple[str, ...]
    velocity_sizes: tuple[int, ...]
    velocity_units: tuple[int, ...]
    state_text: str
    velocity_text: str

    @abstractmethod
    def advance(self, x: Tensor, h: Tensor, velocity: Tensor) -> Tensor:
        """States (B, dim) moved along their velocities (B, tangent_dim) for h (B,) seconds."""

    @abstractmethod
    def errors(self, x: Tensor, y: Tensor) -> Tensor:
        """How far states x (*, dim) are from y (*, dim) or (dim,): one distance per component
        of :attr:`error_names`, user units, shape (*, k)."""

    @abstractmethod
    def error_scales(self, extent: float) -> np.ndarray:
        """The size of each error component for a task of this position extent, shape (k,):
        tolerances are fractions of it."""

    @abstractmethod
    def tangent_scales(self, extent: float) -> np.ndarray:
        """The size of each velocity component's displacement unit, shape (tangent_dim,):
        a displacement divided by it is in extents (positions) or half-turns (angles)."""

    @abstractmethod
    def uniform(
        self, center: np.ndarray, half_width: float, count: int, rng: np.random.Generator
    ) -> np.ndarray:
        """Random states, shape (count, dim): positions uniform in the cube of this
        half-width around the center's position (and orientations uniform on SO(3))."""

    @abstractmethod
    def grid(
        self, center: np.ndarray, half_width: float, count: int, rng: np.random.Generator
    ) -> np.ndarray:
        """At least ``count`` states with positions on a regular grid over the cube,
        corners included, shape (>= count, dim)."""

    def scaled_errors(self, x: Tensor, y: Tensor, extent: float) -> Tensor:
        """:meth:`errors` divided by :meth:`error_scales`, shape (*, k)."""
        scales = torch.as_tensor(self.error_scales(extent), dtype=x.dtype, device=x.device)
        return self.errors(x, y) / scales

    def positions(self, x: np.ndarray) -> np.ndarray:
        """The position part of states (*, dim), shape (*, position_dim)."""
        return x[..., : self.position_dim]


def _grid(center: np.ndarray, half_width: float, count: int) -> np.ndarray:
    """A regular grid of k^n >= count points over the cube around ``center`` (n,)."""
    n = center.shape[0]
    per_axis = max(2, int(np.ceil(count ** (1.0 / n) - 1e-9)))
    axis = np.linspace(-half_width, half_width, per_axis)
    mesh = np.meshgrid(*([axis] * n), indexing="ij")
    return center + np.stack([m.ravel() for m in mesh], axis=-1)


@dataclass(frozen=True)
class Euclidean(Space):
    """Positions in :math:`\\mathbb{R}^n`; a step is :math:`x + h v`.

    Attributes:
        dim: n.
    """

    dim: int
    error_names: ClassVar[tuple[str, ...]] = ("distance",)
    velocity_names: ClassVar[tuple[str, ...]] = ("velocity",)
    velocity_units: ClassVar[tuple[int, ...]] = (0,)

    @property
    def velocity_sizes(self) -> tuple[int, ...]:  # type: ignore[override]
        return (self.dim,)

    @property
    def state_text(self) -> str:  # type: ignore[override]
        return f"position ({self.dim} numbers, user units)"

    @property
    def velocity_text(self) -> str:  # type: ignore[override]
        return f"velocity ({self.dim} numbers, user units per second)"

    @property
    def tangent_dim(self) -> int:  # type: ignore[override]
        return self.dim

    @property
    def position_dim(self) -> int:  # type: ignore[override]
        return self.dim

    def advance(self, x: Tensor, h: Tensor, velocity: Tensor) -> Tensor:
        return x + h.unsqueeze(-1) * velocity

    def errors(self, x: Tensor, y: Tensor) -> Tensor:
        return (x - y).norm(dim=-1, keepdim=True)

    def error_scales(self, extent: float) -> np.ndarray:
        return np.array([extent])

    def tangent_scales(self, extent: float) -> np.ndarray:
        return np.full(self.dim, extent)

    def uniform(
        self, center: np.ndarray, half_width: float, count: int, rng: np.random.Generator
    ) -> np.ndarray:
        return center + rng.uniform(-half_width, half_width, size=(count, self.dim))

    def grid(
        self, center: np.ndarray, half_width: float, count: int, rng: np.random.Generator
    ) -> np.ndarray:
        return _grid(np.asarray(center, dtype=np.float64), half_width, count)


@dataclass(frozen=True)
class Phased(Euclidean):
    r"""Positions in :math:`\mathbb{R}^p` followed by a phase of m numbers that runs to 0
    (:mod:`snds.phase`): a state has dim = p + m numbers, a step is :math:`x + h v`.

    The errors, their scales and so every metric and tolerance are the positions'; random
    states draw the phase uniform in the same cube as the positions' offsets, which holds
    every phase a demonstration starts with (|psi| <= the extent).

    Attributes:
        dim: p + m.
        phase_dim: m.
    """

    dim: int
    phase_dim: int
    velocity_names: ClassVar[tuple[str, ...]] = ("velocity", "phase_rate")
    velocity_units: ClassVar[tuple[int, ...]] = (0, 0)

    @property
    def position_dim(self) -> int:  # type: ignore[override]
        return self.dim - self.phase_dim

    @property
    def velocity_sizes(self) -> tuple[int, ...]:  # type: ignore[override]
        return (self.position_dim, self.phase_dim)

    @property
    def state_text(self) -> str:  # type: ignore[override]
        return (
            f"position ({self.position_dim} numbers, user units), then phase "
            f"({self.phase_dim} numbers, user units)"
        )

    @property
    def velocity_text(self) -> str:  # type: ignore[override]
        return (
            f"velocity ({self.position_dim} numbers, user units per second), then phase rate "
            f"({self.phase_dim} numbers)"
        )

    def errors(self, x: Tensor, y: Tensor) -> Tensor:
        p = self.position_dim
        return (x[..., :p] - y[..., :p]).norm(dim=-1, keepdim=True)

    def tangent_scales(self, extent: float) -> np.ndarray:
        return np.full(self.dim, extent)

    def grid(
        self, center: np.ndarray, half_width: float, count: int, rng: np.random.Generator
    ) -> np.ndarray:
        """Positions on the grid over their cube, each with a phase uniform in its cube."""
        p = self.position_dim
        positions = _grid(np.asarray(center[:p], dtype=np.float64), half_width, count)
        phases = center[p:] + rng.uniform(-half_width, half_width, (len(positions), self.phase_dim))
        return np.concatenate([positions, phases], axis=1)


@dataclass(frozen=True)
class SE3(Space):
    r"""Poses: a position and a unit quaternion (x, y, z, qx, qy, qz, qw); velocities are
    twists :math:`(v, \omega)`, the angular velocity in the world frame.

    A step is :math:`p + h v` and :math:`q \leftarrow \exp(h \omega)\, q`, renormalised so
    that rounding cannot accumulate. The errors are the position distance and the geodesic
    angle (radians, in :math:`[0, \pi]`); an angle's scale is :math:`\pi`, the largest one.
    """

    dim: ClassVar[int] = 7
    tangent_dim: ClassVar[int] = 6
    position_dim: ClassVar[int] = 3
    error_names: ClassVar[tuple[str, ...]] = ("distance", "angle")
    velocity_names: ClassVar[tuple[str, ...]] = ("velocity", "angular_velocity")
    velocity_sizes: ClassVar[tuple[int, ...]] = (3, 3)
    velocity_units: ClassVar[tuple[int, ...]] = (0, 1)
    state_text: ClassVar[str] = "pose (x, y, z in user units; qx, qy, qz, qw, a unit quaternion)"
    velocity_text: ClassVar[str] = (
        "twist (vx, vy, vz in user units per second; wx, wy, wz in rad/s, world frame)"
    )

    def advance(self, x: Tensor, h: Tensor, velocity: Tensor) -> Tensor:
        h = h.unsqueeze(-1)
        orientation = roma.quat_normalize(rotate(h * velocity[..., 3:], x[..., 3:]))
        return torch.cat([x[..., :3] + h * velocity[..., :3], orientation], -1)

    def errors(self, x: Tensor, y: Tensor) -> Tensor:
        y = y.expand_as(x)
        distance = (x[..., :3] - y[..., :3]).norm(dim=-1)
        angle = relative_rotvec(x[..., 3:], y[..., 3:]).norm(dim=-1)
        return torch.stack([distance, angle], -1)

    def error_scales(self, extent: float) -> np.ndarray:
        return np.array([extent, np.pi])

    def tangent_scales(self, extent: float) -> np.ndarray:
        return np.array([extent] * 3 + [np.pi] * 3)

    def uniform(
        self, center: np.ndarray, half_width: float, count: int, rng: np.random.Generator
    ) -> np.ndarray:
        positions = center[:3] + rng.uniform(-half_width, half_width, size=(count, 3))
        return np.concatenate([positions, random_quaternions(count, rng)], axis=1)

    def grid(
        self, center: np.ndarray, half_width: float, count: int, rng: np.random.Generator
    ) -> np.ndarray:
        """Positions on the grid, each with an orientation uniform on SO(3) (a grid on SO(3)
        would need a count per axis three times over)."""
        positions = _grid(np.asarray(center[:3], dtype=np.float64), half_width, count)
        return np.concatenate([positions, random_quaternions(len(positions), rng)], axis=1)
