r"""Obstacle shapes: the distance functions the modulation reads.

Each shape gives :math:`d(x)`, a lower bound of the Euclidean distance from x to the physical
shape that is exact for spheres and boxes (for an ellipsoid it is
:math:`(\sqrt{\sum_i (y_i / a_i)^2} - 1) \min_i a_i`, exact along the shortest axis), convex
outside the shape with the reference point inside its sublevel sets (so
:math:`n^\top r > 0`), and its gradient. With the safety margin m and influence distance
:math:`\rho`, :math:`\Gamma(x) = 1 + (d(x) - m) / \rho` is the paper's distance function:
:math:`\Gamma > 1` in free space, 1 on the inflated boundary, and :math:`\Gamma > 1` implies a
clearance :math:`d > m` from the physical shape. A :class:`Workspace` (the inside of a box) is
the same with the distance to its walls (a smooth minimum over the faces, below the true one)
and the reference direction pointing inwards.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np
import torch
from scipy.spatial.transform import Rotation
from torch import Tensor

from snds.errors import ConfigError

__all__ = [
    "SHAPES",
    "WORKSPACES",
    "Box",
    "Ellipsoid",
    "Obstacle",
    "Sphere",
    "Workspace",
    "safe_normalize",
    "shape_name",
]


_MIN_ALIGNMENT = 1e-12


def _vector(values: Sequence[float], name: str) -> tuple[float, ...]:
    try:
        out = tuple(float(v) for v in values)
    except (TypeError, ValueError):
        raise ConfigError(f"{name} must be a list of numbers, got {values!r}") from None
    if not all(math.isfinite(v) for v in out):
        raise ConfigError(f"{name} must be finite, got {list(out)}")
    return out


def _rotation(angles: tuple[float, ...], dim: int) -> np.ndarray:
    """The rotation matrix (dim, dim) of orientation angles in degrees: one angle in 2-D
    (counter-clockwise), three extrinsic x-y-z Euler angles in 3-D; none is the identity."""
    if not angles:
        return np.eye(dim)
    if dim == 2:
        c, s = math.cos(math.radians(angles[0])), math.sin(math.radians(angles[0]))
        return np.array([[c, -s], [s, c]])
    return Rotation.from_euler("xyz", angles, degrees=True).as_matrix()


@dataclass(frozen=True, kw_only=True)
class Obstacle(ABC):
    r"""A region the motion must keep out of, with one interface for every shape.

    Attributes:
        center: The reference point (the shape's centre), user units, shape (n,).
        margin: Safety margin m >= 0: the motion keeps a distance > m from the shape.
        influence: Distance beyond the margin at which the modulation fades out to the
            identity (None: the shape's :meth:`size`).
        velocity: A constant velocity of the shape, user units per second (None: fixed).
    """

    center: tuple[float, ...]
    margin: float = 0.0
    influence: float | None = None
    velocity: tuple[float, ...] | None = None

    #: Whether the free space is the inside of the shape (a workspace) or the outside.
    free_inside: ClassVar[bool] = False

    def __post_init__(self) -> None:
        object.__setattr__(self, "center", _vector(self.center, "center"))
        if self.dim < 1:
            raise ConfigError("an obstacle needs a centre with at least one coordinate")
        if not (math.isfinite(self.margin) and self.margin >= 0):
            raise ConfigError(f"margin must be a number >= 0, got {self.margin}")
        if self.influence is not None and not (
            math.isfinite(self.influence) and self.influence > 0
        ):
            raise ConfigError(f"influence must be a number > 0, got {self.influence}")
        if self.velocity is not None:
            object.__setattr__(self, "velocity", _vector(self.velocity, "velocity"))
            if len(self.velocity) != self.dim:
                raise ConfigError(
                    f"velocity has {len(self.velocity)} components, the centre {self.dim}"
                )
        self._validate()

    @abstractmethod
    def _validate(self) -> None:
        """Checks the shape's own fields (raises :class:`ConfigError`)."""

    @classmethod
    @abstractmethod
    def from_numbers(cls, numbers: list[float], **options: Any) -> Obstacle:
        """The shape of a spec's positional numbers (see :func:`parse_obstacle`)."""

    @abstractmethod
    def size(self) -> float:
        """A characteristic half-size of the shape (the default influence distance)."""

    @abstractmethod
    def distance(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """A lower bound d of the Euclidean distance from states to the physical shape
        (negative inside), shape (*,), and its gradient, shape (*, n); x is (*, n)."""

    @abstractmethod
    def solid(self) -> Obstacle:
        """The shape in 3-D: itself for a 3-D shape; a 2-D one extruded as its 3-D analogue
        (a disc as a ball, an ellipse as an ellipsoid, a rectangle as a box) centred on the
        plane, with the smallest half-size off the plane."""

    @abstractmethod
    def surface_points(self, count: int) -> np.ndarray:
        """Points on the physical boundary of a 3-D shape, (M, 3): their convex hull is the
        shape (a collision body for the simulator)."""

    @property
    def dim(self) -> int:
        """The state dimension n."""
        return len(self.center)

    @property
    def reach(self) -> float:
        """The influence distance :math:`\\rho` beyond the margin."""
        return self.size() if self.influence is None else float(self.influence)

    def at(self, t: float) -> Obstacle:
        """The shape at time t (moved by t times its velocity)."""
        if self.velocity is None or t == 0:
            return self
        moved = tuple(c + t * v for c, v in zip(self.center, self.velocity))
        return dataclasses.replace(self, center=moved)

    def gamma(self, x: Tensor) -> Tensor:
        r""":math:`\Gamma(x) = 1 + (d(x) - m) / \rho`, shape (*,): > 1 in free space."""
        d, _ = self.distance(x)
        return 1.0 + (d - self.margin) / self.reach

    def to_dict(self) -> dict:
        """JSON-ready form, with the shape's name (a key of :data:`SHAPES`)."""
        return {"shape": shape_name(type(self)), **dataclasses.asdict(self)}

    def center_tensor(self, x: Tensor) -> Tensor:
        """The reference point in the dtype and device of states x, shape (n,)."""
        return torch.as_tensor(self._center_array, dtype=x.dtype, device=x.device)

    @functools.cached_property
    def _center_array(self) -> np.ndarray:
        # Cached on the frozen instance (cached_property writes its __dict__, not a field).
        return np.asarray(self.center, dtype=np.float64)


def shape_name(cls: type) -> str:
    """The spec name of a shape class (a key of :data:`SHAPES` or :data:`WORKSPACES`)."""
    for registry in (SHAPES, WORKSPACES):
        for name, shape in registry.items():
            if shape is cls:
                return name
    return cls.__name__.lower()


def _fibonacci_sphere(count: int) -> np.ndarray:
    index = np.arange(count) + 0.5
    polar = np.arccos(1 - 2 * index / count)
    azimuth = np.pi * (1 + 5**0.5) * index
    return np.stack(
        [np.cos(azimuth) * np.sin(polar), np.sin(azimuth) * np.sin(polar), np.cos(polar)], -1
    )


def safe_normalize(v: Tensor) -> Tensor:
    """Vectors (*, n) divided by their length; a zero vector stays zero."""
    norm = v.norm(dim=-1, keepdim=True)
    return v / torch.where(norm > 0, norm, torch.ones_like(norm))


@dataclass(frozen=True, kw_only=True)
class Sphere(Obstacle):
    """A ball (a disc in 2-D): :math:`d(x) = |x - c| - R`, exact.

    Attributes:
        radius: R > 0, user units.
    """

    radius: float

    def _validate(self) -> None:
        if not (math.isfinite(self.radius) and self.radius > 0):
            raise ConfigError(f"radius must be a number > 0, got {self.radius}")

    @classmethod
    def from_numbers(cls, numbers: list[float], **options: Any) -> Sphere:
        if len(numbers) < 2:
            raise ConfigError("a sphere needs CX,CY[,CZ],R")
        return cls(center=tuple(numbers[:-1]), radius=numbers[-1], **options)

    def size(self) -> float:
        return float(self.radius)

    def distance(self, x: Tensor) -> tuple[Tensor, Tensor]:
        offset = x - self.center_tensor(x)
        return offset.norm(dim=-1) - self.radius, safe_normalize(offset)

    def solid(self) -> Sphere:
        if self.dim == 3:
            return self
        return dataclasses.replace(self, center=(*self.center[:2], 0.0), velocity=None)

    def surface_points(self, count: int) -> np.ndarray:
        return np.asarray(self.center) + self.radius * _fibonacci_sphere(count)


@dataclass(frozen=True, kw_only=True)
class _Oriented(Obstacle):
    """A shape with half-sizes along its own axes, turned by ``angles``.

    Attributes:
        half_sizes: Half-sizes along the shape's axes (semi-axes, half-widths), user units.
        angles: Orientation in degrees: one angle in 2-D (counter-clockwise), three extrinsic
            x-y-z Euler angles in 3-D; empty: aligned with the coordinate axes.
    """

    half_sizes: tuple[float, ...]
    angles: tuple[float, ...] = ()

    def _validate(self) -> None:
        object.__setattr__(self, "half_sizes", _vector(self.half_sizes, "half_sizes"))
        object.__setattr__(self, "angles", _vector(self.angles, "angles"))
        if len(self.half_sizes) != self.dim:
            raise ConfigError(
                f"{len(self.half_sizes)} half-sizes for a centre of {self.dim} coordinates"
            )
        if not all(h > 0 for h in self.half_sizes):
            raise ConfigError(f"half-sizes must be > 0, got {list(self.half_sizes)}")
        wanted = {2: 1, 3: 3}.get(self.dim)
        if self.angles and len(self.angles) != wanted:
            raise ConfigError(
                f"orientation of a {self.dim}-D shape: "
                + (
                    "angle=DEG (one angle) in 2-D, angles=A/B/C (x-y-z Euler, degrees) in 3-D"
                    if wanted
                    else "only 2-D and 3-D shapes can be turned"
                )
                + f", got {len(self.angles)} angles"
            )

    @classmethod
    def from_numbers(cls, numbers: list[float], **options: Any) -> _Oriented:
        if len(numbers) < 2 or len(numbers) % 2:
            raise ConfigError(
                f"a {shape_name(cls)} needs CX,CY[,CZ] then as many half-sizes, got "
                f"{len(numbers)} numbers"
            )
        half = len(numbers) // 2
        return cls(center=tuple(numbers[:half]), half_sizes=tuple(numbers[half:]), **options)

    def size(self) -> float:
        return float(max(self.half_sizes))

    def _frame(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """The rotation (n, n) and the states in the shape's frame, (*, n)."""
        rotation = torch.as_tensor(self._rotation_array, dtype=x.dtype, device=x.device)
        return rotation, (x - self.center_tensor(x)) @ rotation

    @functools.cached_property
    def _rotation_array(self) -> np.ndarray:
        return _rotation(self.angles, self.dim)

    def solid(self) -> _Oriented:
        if self.dim == 3:
            return self
        angles = (0.0, 0.0, self.angles[0]) if self.angles else ()
        return dataclasses.replace(
            self,
            center=(*self.center[:2], 0.0),
            half_sizes=(*self.half_sizes[:2], min(self.half_sizes[:2])),
            angles=angles,
            velocity=None,
        )

    def _placed(self, local: np.ndarray) -> np.ndarray:
        return np.asarray(self.center) + local @ _rotation(self.angles, 3).T


@dataclass(frozen=True, kw_only=True)
class Ellipsoid(_Oriented):
    r"""An ellipsoid (an ellipse in 2-D) with semi-axes ``half_sizes`` a, turned by ``angles``.

    :math:`d(x) = (\sqrt{\sum_i (y_i / a_i)^2} - 1) \min_i a_i` with y the state in the
    ellipsoid's frame: the gap between the ellipsoid and its homothetic copy through x,
    which is at most the Euclidean distance (exact along the shortest axis). The inflated
    shape :math:`\{d \le m\}` is the ellipsoid scaled by :math:`1 + m / \min_i a_i`: along
    longer axes the margin is :math:`m \, a_i / \min a` (conservative, never less than m).
    """

    def distance(self, x: Tensor) -> tuple[Tensor, Tensor]:
        rotation, y = self._frame(x)
        axes = torch.tensor(self.half_sizes, dtype=x.dtype, device=x.device)
        shortest = min(self.half_sizes)
        scaled = y / axes
        level = scaled.norm(dim=-1)
        safe = torch.where(level > 0, level, torch.ones_like(level)).unsqueeze(-1)
        gradient = (shortest * scaled / axes / safe) @ rotation.T
        return (level - 1.0) * shortest, gradient

    def surface_points(self, count: int) -> np.ndarray:
        return self._placed(np.asarray(self.half_sizes) * _fibonacci_sphere(count))


@dataclass(frozen=True, kw_only=True)
class Box(_Oriented):
    r"""A box (a rectangle in 2-D) with half-widths ``half_sizes``, turned by ``angles``.

    :math:`d(x)` is the exact Euclidean distance outside, :math:`|\max(|y| - h, 0)|`, and the
    largest of :math:`|y_i| - h_i` (negative) inside; the inflated shape is the box with
    rounded edges.
    """

    def distance(self, x: Tensor) -> tuple[Tensor, Tensor]:
        rotation, y = self._frame(x)
        half = torch.tensor(self.half_sizes, dtype=x.dtype, device=x.device)
        excess = y.abs() - half
        outside = excess.clamp_min(0.0)
        length = outside.norm(dim=-1)
        deepest = excess.max(dim=-1)
        sign = torch.where(y >= 0, 1.0, -1.0).to(x.dtype)
        inner = torch.nn.functional.one_hot(deepest.indices, self.dim).to(x.dtype)
        safe = torch.where(length > 0, length, torch.ones_like(length)).unsqueeze(-1)
        local = torch.where((length > 0).unsqueeze(-1), outside / safe, inner) * sign
        return length + deepest.values.clamp_max(0.0), local @ rotation.T

    def surface_points(self, count: int) -> np.ndarray:
        corners = np.array(np.meshgrid(*[[-1.0, 1.0]] * 3, indexing="ij")).reshape(3, -1).T
        return self._placed(corners * np.asarray(self.half_sizes))


@dataclass(frozen=True, kw_only=True)
class Workspace(_Oriented):
    r"""The inside of a box that the motion must stay in, with half-widths ``half_sizes``.

    d is a smooth minimum of the distances to the 2n walls, :math:`-\tau \log \sum_j
    e^{-d_j / \tau}` with :math:`\tau` = ``smoothing`` (default 2% of the smallest
    half-width): never more than the true distance to the walls, concave, largest at the
    centre; the motion keeps more than ``margin`` from every wall. The reference direction
    points from x to the centre.

    Attributes:
        smoothing: :math:`\tau`, user units (None: 2% of the smallest half-width).
    """

    smoothing: float | None = None
    free_inside: ClassVar[bool] = True

    def _validate(self) -> None:
        super()._validate()
        if self.smoothing is not None and not (
            math.isfinite(self.smoothing) and self.smoothing > 0
        ):
            raise ConfigError(f"smoothing must be a number > 0, got {self.smoothing}")

    def size(self) -> float:
        # The walls' influence reaches a fifth of the way in by default.
        return 0.2 * float(min(self.half_sizes))

    def distance(self, x: Tensor) -> tuple[Tensor, Tensor]:
        rotation, y = self._frame(x)
        half = torch.tensor(self.half_sizes, dtype=x.dtype, device=x.device)
        tau = 0.02 * min(self.half_sizes) if self.smoothing is None else self.smoothing
        walls = torch.cat([half - y, half + y], dim=-1)  # (*, 2n)
        d = -tau * torch.logsumexp(-walls / tau, dim=-1)
        share = torch.softmax(-walls / tau, dim=-1)
        local = share[..., self.dim :] - share[..., : self.dim]
        return d, local @ rotation.T

    def solid(self) -> Workspace:
        return self

    def surface_points(self, count: int) -> np.ndarray:
        raise ConfigError("a workspace is the inside of a box: it has no collision body")


#: ``--obstacle`` shapes: spec name -> class.
SHAPES: dict[str, type[Obstacle]] = {"sphere": Sphere, "ellipsoid": Ellipsoid, "box": Box}
#: ``--workspace`` shapes.
WORKSPACES: dict[str, type[Obstacle]] = {"box": Workspace}
