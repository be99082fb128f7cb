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
- :class:`Phased`: the states of another space (positions or poses) followed by a phase
  :math:`\psi \in \mathbb{R}^m` (:mod:`snds.phase`); a step is the base space's, and the
  phase moves along its rate; the errors are the base space's alone.
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
import torch
from torch import Tensor

from snds.so3 import random_quaternions, relative_rotvec, roma, rotate

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
class Phased(Space):
    r"""The states of another space followed by a phase of m numbers that runs to 0
    (:mod:`snds.phase`): positions :math:`x \in \mathbb{R}^p` or poses, then
    :math:`\psi \in \mathbb{R}^m`. A step moves the base state as its space does and the
    phase along its rate, :math:`\psi + h \dot\psi`.

    The errors, their scales and so every metric and tolerance are the base space's; random
    states draw the phase uniform in the same cube as the positions' offsets, which holds
    every phase a demonstration starts with (:math:`|\psi| \le` the extent).

    Attributes:
        base: The space of the states without their phase.
        phase_dim: m.
    """

    base: Space
    phase_dim: int

    @property
    def dim(self) -> int:  # type: ignore[override]
        return self.base.dim + self.phase_dim

    @property
    def tangent_dim(self) -> int:  # type: ignore[override]
        return self.base.tangent_dim + self.phase_dim

    @property
    def position_dim(self) -> int:  # type: ignore[override]
        return self.base.position_dim

    @property
    def error_names(self) -> tuple[str, ...]:  # type: ignore[override]
        return self.base.error_names

    @property
    def velocity_names(self) -> tuple[str, ...]:  # type: ignore[override]
        return (*self.base.velocity_names, "phase_rate")

    @property
    def velocity_sizes(self) -> tuple[int, ...]:  # type: ignore[override]
        return (*self.base.velocity_sizes, self.phase_dim)

    @property
    def velocity_units(self) -> tuple[int, ...]:  # type: ignore[override]
        # A phase is a length: it moves in the positions' unit per second.
        return (*self.base.velocity_units, 0)

    @property
    def state_text(self) -> str:  # type: ignore[override]
        return f"{self.base.state_text}, then phase ({self.phase_dim} numbers, position units)"

    @property
    def velocity_text(self) -> str:  # type: ignore[override]
        return (
            f"{self.base.velocity_text}, then phase rate ({self.phase_dim} numbers, position "
            "units per second)"
        )

    def split(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """The base states and the phases of states (*, dim): (*, base.dim), (*, m)."""
        return x[..., : self.base.dim], x[..., self.base.dim :]

    def advance(self, x: Tensor, h: Tensor, velocity: Tensor) -> Tensor:
        state, phase = self.split(x)
        rate = velocity[..., self.base.tangent_dim :]
        moved = self.base.advance(state, h, velocity[..., : self.base.tangent_dim])
        return torch.cat([moved, phase + h.unsqueeze(-1) * rate], -1)

    def errors(self, x: Tensor, y: Tensor) -> Tensor:
        return self.base.errors(x[..., : self.base.dim], y[..., : self.base.dim])

    def error_scales(self, extent: float) -> np.ndarray:
        return self.base.error_scales(extent)

    def tangent_scales(self, extent: float) -> np.ndarray:
        return np.append(self.base.tangent_scales(extent), np.full(self.phase_dim, extent))

    def _with_phases(
        self, states: np.ndarray, center: np.ndarray, half_width: float, rng: np.random.Generator
    ) -> np.ndarray:
        offsets = rng.uniform(-half_width, half_width, (len(states), self.phase_dim))
        return np.concatenate([states, center[self.base.dim :] + offsets], axis=1)

    def uniform(
        self, center: np.ndarray, half_width: float, count: int, rng: np.random.Generator
    ) -> np.ndarray:
        center = np.asarray(center, dtype=np.float64)
        states = self.base.uniform(center[: self.base.dim], half_width, count, rng)
        return self._with_phases(states, center, half_width, rng)

    def grid(
        self, center: np.ndarray, half_width: float, count: int, rng: np.random.Generator
    ) -> np.ndarray:
        """The base space's grid, each state with a phase uniform in its cube."""
        center = np.asarray(center, dtype=np.float64)
        states = self.base.grid(center[: self.base.dim], half_width, count, rng)
        return self._with_phases(states, center, half_width, rng)


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
        orientation = roma().quat_normalize(rotate(h * velocity[..., 3:], x[..., 3:]))
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
