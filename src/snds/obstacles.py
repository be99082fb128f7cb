r"""Obstacles and workspace limits: any policy's field, modulated so that it goes around them.

The modulation of Khansari-Zadeh & Billard (Auton. Robots 2012) in the form of Huber, Billard
& Slotine (RA-L 2019): near each obstacle k the velocity :math:`v = \pi(x)` is rewritten in a
basis of the reference direction :math:`r_k(x)` (from the obstacle's reference point, its
centre, to x) and the tangent plane of the obstacle's distance level set through x (normal
:math:`n_k(x)`), and the radial part is damped while the tangent part is sped up:

.. math:: M_k(x) = E_k D_k E_k^{-1}, \quad E_k = [r_k, e_1, \dots, e_{n-1}], \quad
          D_k = \mathrm{diag}(\lambda_r, \lambda_e, \dots, \lambda_e).

Written without a matrix inverse: with :math:`a = n^\top v / n^\top r` (the radial
coordinate, since every :math:`e_i \perp n`), :math:`M v = \lambda_r a r + \lambda_e (v - a
r)`. Here :math:`\lambda_r = 1 - h` when v approaches the obstacle (:math:`a < 0`) and 1
when it moves away (Huber's removal of the "tail effect"), :math:`\lambda_e = 1 + h`, and the
weight :math:`h \in [0, 1]` is 1 on the (inflated) boundary and 0 beyond the obstacle's
influence distance, so the field is exactly unchanged there. On the boundary
:math:`n^\top M v = 0`: the flow cannot enter (impenetrability). Several obstacles compose
as :math:`M = M_K \cdots M_1` with Khansari's weights :math:`w_k` (1 at obstacle k's
boundary, 0 at every other boundary), :math:`h_k \to w_k h_k`. An obstacle moving with
velocity :math:`u_k` modulates the velocity relative to it:
:math:`\dot x = M (v - u) + u`, :math:`u = \sum_k w_k h_k u_k`.

Distance functions. Each shape gives :math:`d(x)`, a lower bound of the Euclidean distance
from x to the physical shape that is exact for spheres and boxes (for an ellipsoid it is
:math:`(\sqrt{\sum_i (y_i / a_i)^2} - 1) \min_i a_i`, exact along the shortest axis), convex
outside the shape with the reference point inside its sublevel sets (so
:math:`n^\top r > 0`), and its gradient. With the safety margin m and influence distance
:math:`\rho`, :math:`\Gamma(x) = 1 + (d(x) - m) / \rho` is the paper's distance function:
:math:`\Gamma > 1` in free space, 1 on the inflated boundary, and :math:`\Gamma > 1` implies a
clearance :math:`d > m` from the physical shape. :math:`h = \mathrm{clip}(2 - \Gamma, 0,
1)^2`. A :class:`Workspace` (the inside of a box) is the same with the distance to its walls
(a smooth minimum over the faces, below the true one) and the reference direction pointing
inwards.

Discrete time: a robot steps :math:`x \leftarrow x + h \dot x`. :func:`avoid_step` halves a
step until every :math:`\Gamma > 1` at the state reached (and, away from every obstacle's
influence, until a stable policy's V decreases, as :func:`snds.rollout.guarded_step` does),
and holds the state if no halving is safe: a guarded rollout never ends a step inside an
inflated obstacle. See docs/obstacles.md for which guarantee holds for which scene.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import math
import time as _time
from abc import ABC, abstractmethod
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, ClassVar

import numpy as np
import torch
from scipy.spatial.transform import Rotation
from torch import Tensor

from snds.data.demonstrations import Demonstrations
from snds.errors import ConfigError
from snds.evaluate import reproduce
from snds.metrics import dtw
from snds.policy import Policy, float64_copy
from snds.rollout import policy_guard
from snds.stability import settle_level

__all__ = [
    "SHAPES",
    "WORKSPACES",
    "Box",
    "Ellipsoid",
    "ModulatedPolicy",
    "Obstacle",
    "ObstacleReport",
    "RolloutCheck",
    "Scene",
    "Sphere",
    "Workspace",
    "avoid_step",
    "avoiding_rollout",
    "check_obstacles",
    "load_scene",
    "modulate_twist",
    "parse_obstacle",
    "parse_workspace",
    "step_fraction",
]

#: Smallest :math:`n^\top r` used in the radial coordinate (the shapes make it positive).
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
        return {"shape": _shape_name(type(self)), **dataclasses.asdict(self)}

    def _center(self, x: Tensor) -> Tensor:
        return torch.as_tensor(self._center_array, dtype=x.dtype, device=x.device)

    @functools.cached_property
    def _center_array(self) -> np.ndarray:
        # Cached on the frozen instance (cached_property writes its __dict__, not a field).
        return np.asarray(self.center, dtype=np.float64)


def _shape_name(cls: type) -> str:
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


def _safe_normalize(v: Tensor) -> Tensor:
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
        offset = x - self._center(x)
        return offset.norm(dim=-1) - self.radius, _safe_normalize(offset)

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
                f"a {_shape_name(cls)} needs CX,CY[,CZ] then as many half-sizes, got "
                f"{len(numbers)} numbers"
            )
        half = len(numbers) // 2
        return cls(center=tuple(numbers[:half]), half_sizes=tuple(numbers[half:]), **options)

    def size(self) -> float:
        return float(max(self.half_sizes))

    def _frame(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """The rotation (n, n) and the states in the shape's frame, (*, n)."""
        rotation = torch.as_tensor(self._rotation_array, dtype=x.dtype, device=x.device)
        return rotation, (x - self._center(x)) @ rotation

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

#: Spec options: name -> (constructor field, parser). Vectors are separated by "/".
_OPTIONS: dict[str, tuple[str, Callable[[str], Any]]] = {
    "margin": ("margin", float),
    "influence": ("influence", float),
    "angle": ("angles", lambda s: (float(s),)),
    "angles": ("angles", lambda s: tuple(float(p) for p in s.split("/"))),
    "velocity": ("velocity", lambda s: tuple(float(p) for p in s.split("/"))),
}


def _parse(text: str, registry: dict[str, type[Obstacle]], flag: str) -> Obstacle:
    name, colon, body = text.partition(":")
    if name not in registry or not colon:
        raise ConfigError(
            f"{flag} {text!r}: expected SHAPE:NUMBERS with SHAPE one of {', '.join(registry)}"
        )
    numbers: list[float] = []
    options: dict[str, Any] = {}
    for part in body.split(","):
        part = part.strip()
        key, equals, value = part.partition("=")
        if equals and key not in _OPTIONS:
            raise ConfigError(
                f"{flag} {text!r}: unknown option {key!r} (options: {', '.join(_OPTIONS)})"
            )
        if not equals and options:
            raise ConfigError(f"{flag} {text!r}: numbers must come before key=value options")
        try:
            if equals:
                target, convert = _OPTIONS[key]
                options[target] = convert(value)
            else:
                numbers.append(float(part))
        except ValueError:
            raise ConfigError(f"{flag} {text!r}: {part!r} is not a number") from None
    try:
        return registry[name].from_numbers(numbers, **options)
    except ConfigError as error:
        raise ConfigError(f"{flag} {text!r}: {error}") from None


def parse_obstacle(text: str) -> Obstacle:
    """An obstacle from a spec ``SHAPE:NUMBERS[,key=value...]`` (docs/obstacles.md).

    ``sphere:CX,CY[,CZ],R``; ``ellipsoid:CX,CY[,CZ],A1,A2[,A3]`` (semi-axes); ``box:CX,CY[,CZ],
    H1,H2[,H3]`` (half-widths); options ``margin=M``, ``influence=D``, ``angle=DEG`` (2-D),
    ``angles=A/B/C`` (3-D, x-y-z Euler, degrees), ``velocity=V1/V2[/V3]``.

    Raises:
        ConfigError: naming the spec and its problem.
    """
    return _parse(text, SHAPES, "--obstacle")


def parse_workspace(text: str) -> Obstacle:
    """A workspace from ``box:CX,CY[,CZ],H1,H2[,H3][,margin=M,...]``: the box to stay in."""
    return _parse(text, WORKSPACES, "--workspace")


def _from_dict(entry: Any, registry: dict[str, type[Obstacle]], where: str) -> Obstacle:
    if isinstance(entry, str):
        return _parse(entry, registry, where)
    if not isinstance(entry, dict) or entry.get("shape") not in registry:
        raise ConfigError(
            f'{where}: expected a spec string or an object with "shape" one of '
            f"{', '.join(registry)}, got {entry!r}"
        )
    cls = registry[entry["shape"]]
    fields = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(entry) - fields - {"shape"})
    if unknown:
        raise ConfigError(
            f"{where}: unknown key {unknown[0]!r} (keys: {', '.join(sorted(fields))})"
        )
    try:
        return cls(**{k: v for k, v in entry.items() if k != "shape"})
    except TypeError as error:
        raise ConfigError(f"{where}: {error}") from None
    except ConfigError as error:
        raise ConfigError(f"{where}: {error}") from None


@dataclass(frozen=True, kw_only=True)
class Scene:
    """Obstacles and an optional workspace, all of one dimension, in user units.

    Attributes:
        obstacles: The obstacles (free space outside each).
        workspace: The box the motion must stay in, or None.
    """

    obstacles: tuple[Obstacle, ...] = ()
    workspace: Workspace | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "obstacles", tuple(self.obstacles))
        dims = {body.dim for body in self.bodies}
        if len(dims) > 1:
            raise ConfigError(f"obstacles of different dimensions: {sorted(dims)}")

    @property
    def bodies(self) -> tuple[Obstacle, ...]:
        """The obstacles, then the workspace if any."""
        return self.obstacles + ((self.workspace,) if self.workspace is not None else ())

    @property
    def dim(self) -> int | None:
        """The dimension of the scene (None if it is empty)."""
        return self.bodies[0].dim if self.bodies else None

    @property
    def moving(self) -> bool:
        """Whether any obstacle moves."""
        return any(body.velocity is not None for body in self.bodies)

    def at(self, t: float) -> Scene:
        """The scene at time t."""
        if not self.moving:
            return self
        workspace = None if self.workspace is None else self.workspace.at(t)
        return Scene(obstacles=tuple(o.at(t) for o in self.obstacles), workspace=workspace)

    def check(self, dim: int, target: np.ndarray) -> None:
        """Refuses a scene of another dimension, or whose inflated obstacles hold the target.

        Raises:
            ConfigError: naming the first obstacle at fault.
        """
        for body in self.bodies:
            if body.dim != dim:
                raise ConfigError(f"a {body.dim}-D {_shape_name(type(body))} for a {dim}-D model")
        x = torch.tensor(np.asarray(target, dtype=np.float64))[None]
        for body in self.bodies:
            if float(body.gamma(x)[0]) <= 1.0:
                raise ConfigError(
                    f"the target {np.round(target, 6).tolist()} is not in free space: it is "
                    f"within the margin of the {_shape_name(type(body))} at "
                    f"{list(body.center)}"
                )

    def gammas(self, x: Tensor) -> Tensor:
        r""":math:`\Gamma_k(x)` of every body, shape (*, K)."""
        return torch.stack([body.gamma(x) for body in self.bodies], dim=-1)

    def clearances(self, x: Tensor) -> Tensor:
        """Distance from states to each body's physical shape (lower bound), (*, K)."""
        return torch.stack([body.distance(x)[0] for body in self.bodies], dim=-1)

    def free(self, x: Tensor) -> Tensor:
        r"""Whether states are in free space (every :math:`\Gamma > 1`), shape (*,)."""
        if not self.bodies:
            return torch.ones(x.shape[:-1], dtype=torch.bool, device=x.device)
        return (self.gammas(x) > 1.0).all(dim=-1)

    def gammas_after(self, x: Tensor, h: Tensor) -> Tensor:
        r""":math:`\Gamma_k` at states (B, n) of the scene as it is h (B,) seconds later, (B, K).

        A translating shape at t + h seen from x is the shape at t seen from x - h u.
        """
        gammas = []
        for body in self.bodies:
            shifted = x
            if body.velocity is not None:
                speed = torch.tensor(body.velocity, dtype=x.dtype, device=x.device)
                shifted = x - h.unsqueeze(-1) * speed
            gammas.append(body.gamma(shifted))
        if not gammas:
            return x.new_zeros((*x.shape[:-1], 0))
        return torch.stack(gammas, dim=-1)

    def influenced(self, x: Tensor) -> Tensor:
        """Whether any body modulates the field at states (within its influence), (*,)."""
        if not self.bodies:
            return torch.zeros(x.shape[:-1], dtype=torch.bool, device=x.device)
        return (self.gammas(x) < 2.0).any(dim=-1)

    def modulate(self, x: Tensor, v: Tensor, target: Tensor | None = None) -> Tensor:
        r"""The modulated velocities :math:`M(x) (\tilde v - u) + u` at states x, (*, n) each.

        With a ``target`` (n,), :math:`\tilde v` is v turned towards the target's direction
        by the fraction :math:`\eta = 1 - \prod_k (1 - h_k)` of the angle between them
        (:func:`_turn`; the rotation of nonlinear dynamics of Huber, Slotine & Billard, 2023,
        towards the linear "convergence dynamics"), keeping its speed: on every boundary the
        modulated field is then that of :math:`-(x - x^*)`, whose only boundary equilibria
        around separate convex obstacles are saddle points. A nonlinear field that converges
        onto a point of an obstacle (a demonstrated path through it) would otherwise make
        that point a stable equilibrium. Without a target, :math:`\tilde v = v`.

        Exactly ``v`` wherever no body is within its influence distance.
        """
        return self.modulate_and_gammas(x, v, target)[0]

    def modulate_and_gammas(
        self, x: Tensor, v: Tensor, target: Tensor | None = None
    ) -> tuple[Tensor, Tensor]:
        r""":meth:`modulate`, and :math:`\Gamma_k(x)` of every body, (*, K), from one pass."""
        bodies = self.bodies
        if not bodies:
            return v, x.new_zeros((*x.shape[:-1], 0))
        parts, gammas = [], []
        for body in bodies:
            d, gradient = body.distance(x)
            gamma = 1.0 + (d - body.margin) / body.reach
            gammas.append(gamma)
            weight = (2.0 - gamma).clamp(0.0, 1.0) ** 2
            offset = x - body._center(x)
            normal = _safe_normalize(gradient)
            radial = _safe_normalize(-offset if body.free_inside else offset)
            # At the reference point itself (only a workspace's centre can be in reach) the
            # normal stands in for the undefined direction.
            degenerate = offset.norm(dim=-1, keepdim=True) == 0
            radial = torch.where(degenerate, normal, radial)
            parts.append((weight, normal, radial))
        weights = torch.stack([p[0] for p in parts], dim=-1)  # (*, K)
        effective = weights * _shares(weights)
        if target is not None:
            # Turned only as far as v heads into a body: a field passing by keeps its course.
            unit = _safe_normalize(v)
            into = torch.stack(
                [(-(unit * radial).sum(-1)).clamp(0.0, 1.0) for _, _, radial in parts], dim=-1
            )
            turn = 1.0 - (1.0 - weights * into).prod(dim=-1, keepdim=True)
            v = torch.where(turn > 0, _turn(v, target.to(x) - x, turn), v)
        drift = torch.zeros_like(v)
        for k, body in enumerate(bodies):
            if body.velocity is not None:
                speed = torch.tensor(body.velocity, dtype=v.dtype, device=v.device)
                drift = drift + effective[..., k : k + 1] * speed
        relative = v - drift
        out = relative
        for k, (_, normal, radial) in enumerate(parts):
            e = effective[..., k : k + 1]
            alignment = (normal * radial).sum(-1, keepdim=True).clamp_min(_MIN_ALIGNMENT)
            a = (normal * out).sum(-1, keepdim=True) / alignment
            # Within the margin (Gamma < 1) the radial eigenvalue turns negative: out again.
            push = torch.where(gammas[k] < 1.0, (2.0 - gammas[k]) ** 2, 1.0).unsqueeze(-1)
            lam_r = torch.where(a < 0, 1.0 - e * push, torch.ones_like(e))
            modulated = lam_r * a * radial + (1.0 + e) * (out - a * radial)
            out = torch.where(e > 0, modulated, out)
        return out + drift, torch.stack(gammas, dim=-1)

    def to_dict(self) -> dict:
        """JSON-ready form (what :func:`load_scene` reads)."""
        return {
            "obstacles": [o.to_dict() for o in self.obstacles],
            "workspace": None if self.workspace is None else self.workspace.to_dict(),
        }

    @classmethod
    def from_dict(cls, data: Any, where: str = "scene") -> Scene:
        """A scene from :meth:`to_dict`'s form; obstacles may also be spec strings."""
        if not isinstance(data, dict):
            raise ConfigError(
                f'{where}: expected an object with "obstacles", got {type(data).__name__}'
            )
        unknown = sorted(set(data) - {"obstacles", "workspace"})
        if unknown:
            raise ConfigError(f"{where}: unknown key {unknown[0]!r} (keys: obstacles, workspace)")
        entries = data.get("obstacles") or []
        if not isinstance(entries, list):
            raise ConfigError(f'{where}: "obstacles" must be a list')
        obstacles = tuple(
            _from_dict(e, SHAPES, f"{where}: obstacle {i}") for i, e in enumerate(entries)
        )
        space = data.get("workspace")
        workspace = None if space is None else _from_dict(space, WORKSPACES, f"{where}: workspace")
        return cls(obstacles=obstacles, workspace=workspace)


def _turn(v: Tensor, towards: Tensor, fraction: Tensor) -> Tensor:
    r"""Velocities v (*, n) turned towards directions (*, n) by ``fraction`` (*, 1) of the
    angle between them, in the plane they span, keeping their length. A velocity exactly
    opposite to its direction (no plane) is left as it is."""
    speed = v.norm(dim=-1, keepdim=True)
    unit = _safe_normalize(v)
    goal = _safe_normalize(towards)
    cosine = (unit * goal).sum(-1, keepdim=True)
    across = goal - cosine * unit
    sine = across.norm(dim=-1, keepdim=True)
    angle = torch.atan2(sine, cosine) * fraction
    turned = speed * (torch.cos(angle) * unit + torch.sin(angle) * _safe_normalize(across))
    return torch.where((sine > 0) & (speed > 0), turned, v)


def _shares(h: Tensor) -> Tensor:
    r"""Khansari-Zadeh & Billard's weights :math:`w_k = \prod_{i \ne k} d_i / (d_k + d_i)` in
    terms of :math:`d = 1 / h - 1`, shape (*, K): 1 for body k on its boundary (h_k = 1), 0 for
    every other body there, and 1 for a body alone in reach."""
    count = h.shape[-1]
    shares = torch.ones_like(h)
    for k in range(count):
        for i in range(count):
            if i == k:
                continue
            num = h[..., k] * (1.0 - h[..., i])
            den = num + (1.0 - h[..., k]) * h[..., i]
            factor = torch.where(den > 0, num / torch.where(den > 0, den, 1.0), 0.5)
            shares[..., k] = shares[..., k] * factor
    return shares


def load_scene(path: str | Path) -> Scene:
    """A scene file: JSON (``.json``) or YAML (``.yaml``/``.yml``, needs pyyaml).

    Raises:
        ConfigError: for a missing or malformed file, naming it.
    """
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{path}: no such scene file")
    text = path.read_text()
    if path.suffix in (".yaml", ".yml"):
        try:
            import yaml
        except ImportError:
            raise ConfigError(f"{path}: YAML scenes need pyyaml (or use JSON)") from None
        try:
            data = yaml.safe_load(text)
        except yaml.YAMLError as error:
            raise ConfigError(f"{path}: not valid YAML ({str(error).splitlines()[0]})") from None
    elif path.suffix == ".json":
        try:
            data = json.loads(text)
        except json.JSONDecodeError as error:
            raise ConfigError(f"{path}: not valid JSON ({error})") from None
    else:
        raise ConfigError(f"{path}: a scene file is .json, .yaml or .yml")
    return Scene.from_dict(data, where=str(path))


class ModulatedPolicy(Policy):
    r"""Any policy with a scene's obstacles: :math:`\pi_\text{mod}(x) = M(x)\pi(x)`.

    Takes and returns user units as every :class:`~snds.policy.Policy`; the base policy's
    target stays an equilibrium (:math:`\pi(x^*) = 0`) and the field is exactly the base
    policy's outside every obstacle's influence. Obstacles are taken at time 0; a moving
    scene is followed in time by :func:`avoiding_rollout`. It carries no Lyapunov function:
    going around an obstacle may raise the base policy's V.

    Arguments:
        base: The policy to modulate (SNDS, BC, a baseline, ...).
        scene: The obstacles and workspace, user units.
    """

    kind = "modulated"

    def __init__(self, base: Policy, scene: Scene) -> None:
        super().__init__(dim=base.dim, normalization=base.normalization)
        self.register_buffer("center", base.center.detach().clone())
        self.base = base
        self.scene = scene
        self.lyapunov = None

    @property
    def method(self) -> str:
        """The base policy's method."""
        return self.base.method

    def export_metadata(self) -> dict[str, str]:
        """What an ONNX export records of the obstacles (``snds.obstacles``, the scene as
        JSON): the graph computes the modulated field, not the step guard of
        :func:`avoid_step`, which a controller applies itself."""
        return {"snds.obstacles": json.dumps(self.scene.to_dict())}

    def field(self, x: Tensor) -> Tensor:
        """The modulated field in model coordinates, (*, n) -> (*, n)."""
        center = self.center.to(x.dtype)
        user = center + self.length * x
        velocity = self.base.field(x) * (self.length / self.time)
        return self.scene.modulate(user, velocity, center) * (self.time / self.length)


def modulate_twist(
    scene: Scene, position: Tensor, twist: Tensor, target: Tensor | None = None
) -> Tensor:
    """A pose policy's twist (*, 6) with its linear part modulated at positions (*, 3) (turned
    towards the target position (3,) if given, see :meth:`Scene.modulate`)."""
    linear = scene.modulate(position, twist[..., :3], target)
    return torch.cat([linear, twist[..., 3:]], dim=-1)


# --- discrete time -------------------------------------------------------------------------


Guard = tuple[Callable[[Tensor], Tensor], Callable[[Tensor, Tensor], Tensor]]


def _modulated(policy: Policy, scene: Scene, x: Tensor) -> tuple[Tensor, Tensor]:
    """The policy's velocity at x modulated by the scene (turned towards its target), and
    the bodies' Gamma, as :meth:`Scene.modulate_and_gammas`."""
    return scene.modulate_and_gammas(x, policy(x), policy.center.to(x.dtype))


@torch.no_grad()
def avoid_step(
    policy: Policy,
    scene: Scene,
    x: Tensor,
    *,
    dt: float | Tensor,
    t: float = 0.0,
    guard: Guard | None = None,
    sufficient: float = 0.5,
    max_halvings: int = 40,
    velocity: Tensor | None = None,
    gammas: Tensor | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    r"""One guarded Euler step of the modulated policy per state.

    The velocity is :math:`M(x)\pi(x)` with the scene at time t; each state's step is halved
    until every :math:`\Gamma > 1` at the state reached (the scene at t + h) and, for a state
    outside every influence region with a ``guard`` (V and its rate, see
    :func:`snds.rollout.policy_guard`), until V decreases by Armijo's condition. A state
    for which no halving is safe stays where it is (step 0): the step never ends inside an
    inflated obstacle. Only the states are checked, not the segments between them: a chord
    of length l between two free states dips at most about :math:`l^2 / (8 R)` into the
    margin of a ball of inflated radius R.

    Arguments:
        policy: The base policy (user units).
        scene: The obstacles.
        x: States, (B, n).
        dt: The nominal step, one or one per state (B,).
        t: Time of the states (moving obstacles).
        guard: V and its decrease rate, or None (no V condition).
        sufficient: Armijo's fraction c of the promised decrease.
        max_halvings: Halvings tried before holding the state.
        velocity: The modulated velocity at x, (B, n), if known (else computed).
        gammas: With it, every body's Gamma at x, (B, K).

    Returns:
        The next states (B, n), the steps taken (B,) (0: held), and the velocities used (B, n).
    """
    now = scene.at(t)
    if velocity is None or gammas is None:
        velocity, gammas = _modulated(policy, now, x)
    if isinstance(dt, Tensor):
        h = dt.to(x).clone()
    else:
        h = torch.full(x.shape[:-1], float(dt), dtype=x.dtype)
    free_far = ~(gammas < 2.0).any(dim=-1)
    value = required = None
    if guard is not None:
        lyapunov, rate = guard
        value = lyapunov(x)
        required = sufficient * rate(x, value)

    def safe(index: Tensor, candidate: Tensor) -> Tensor:
        # Free, or for a state already within a margin (a robot that lagged behind its
        # command) no deeper: it may slide along or out, never further in.
        later = now.gammas_after(candidate, h[index])
        ok = ((later > 1.0) | (later >= gammas[index])).all(dim=-1)
        if value is not None:
            new = guard[0](candidate)
            old = value[index]
            decrease = (new <= old - h[index] * required[index]) & (new < old)
            ok = ok & (decrease | ~free_far[index] | (old <= 0))
        return ok

    candidate = x + h.unsqueeze(-1) * velocity
    pending = torch.arange(len(x))
    pending = pending[~safe(pending, candidate)]
    for _ in range(max_halvings):
        if len(pending) == 0:
            break
        h[pending] = 0.5 * h[pending]
        candidate[pending] = x[pending] + h[pending].unsqueeze(-1) * velocity[pending]
        pending = pending[~safe(pending, candidate[pending])]
    h[pending] = 0.0
    candidate[pending] = x[pending]
    return candidate, h, velocity


@torch.no_grad()
def avoiding_rollout(
    policy: Policy,
    scene: Scene,
    x0: Tensor,
    *,
    dt: float | Tensor,
    steps: int,
    guard: bool = True,
) -> tuple[Tensor, Tensor]:
    """Rollouts of :func:`avoid_step` from a batch of starts, the scene moving with time.

    Arguments:
        policy: The base policy (user units).
        scene: The obstacles.
        x0: Start states, (B, n).
        dt: The nominal step, one or one per start (B,).
        steps: Number of steps.
        guard: Also ask a stable policy's V to decrease where no obstacle is in reach.

    Returns:
        The states, (steps + 1, B, n), and the steps taken, (steps, B).
    """
    guard_ = policy_guard(policy) if guard and policy.stable else None
    if scene.moving and isinstance(dt, Tensor):
        raise ConfigError("rollouts among moving obstacles need one time step for all starts")
    x, states, taken = x0, [x0], []
    for step in range(steps):
        # The obstacles do not wait: time advances by the nominal step, taken or shortened.
        t = step * float(dt) if scene.moving else 0.0
        x, h, _ = avoid_step(policy, scene, x, dt=dt, t=t, guard=guard_)
        states.append(x)
        taken.append(h)
    return torch.stack(states), torch.stack(taken)


# --- the stability report under obstacles ----------------------------------------------------


@dataclass(frozen=True)
class RolloutCheck:
    """Outcome of rollouts under obstacles from one set of starts.

    Attributes:
        starts: Number of rollouts.
        reached: Rollouts that ended within the tolerance of the target.
        converged_fraction: reached / starts.
        stalled: Rollouts that did not (the rest), listed in ``stall_points``.
        stall_points: Where they ended, clustered within 5% of the extent: each {"center",
            "count", "gamma", "speed", "kind"}: "saddle" (the field vanishes on an inflated
            boundary: the measure-zero set the modulation cannot avoid), "held" (the field
            points into an obstacle and the guard holds the state: a concave junction of
            overlapping obstacles), "attractor" (the field vanishes in free space) or
            "moving" (too slow for the horizon).
        penetrated: Rollouts with a state inside an inflated obstacle (Gamma <= 1); must be 0.
        min_clearance: Smallest distance of a state to a physical obstacle surface (or
            workspace wall), user units; compare with ``margin``.
        margin: The smallest margin in the scene.
        held_steps: Steps at which the guard held a state (no halving was safe).
    """

    starts: int
    reached: int
    converged_fraction: float
    stalled: int
    stall_points: list
    penetrated: int
    min_clearance: float
    margin: float
    held_steps: int

    def to_dict(self) -> dict:
        """JSON-ready form."""
        return dataclasses.asdict(self)


@dataclass(frozen=True)
class ObstacleReport:
    """Outcome of :func:`check_obstacles`.

    Attributes:
        scene: The scene, as :meth:`Scene.to_dict`.
        random: Rollouts from random starts in the free part of the box.
        demos: Rollouts from the demonstrations' starts (those in free space).
        blocked_demos: Demonstrations whose path comes within the margin of an obstacle.
        dtw_free: Mean DTW (paper eq. 7, user units) of the rollouts from the starts of the
            demonstrations the obstacles leave free, to those demonstrations (None if none).
        dtw_free_without_obstacles: The same rollouts without the obstacles, for comparison.
        free_demos: Indices of those demonstrations.
        box: Half-width of the box of random starts, user units.
        horizon: Rollout duration, seconds.
        dt: Nominal step, seconds.
        tolerance: Distance counted as arrived, user units.
        cpu_seconds: Process CPU time of the check.
        wall_seconds: Wall-clock time of the check.
    """

    scene: dict
    random: RolloutCheck
    demos: RolloutCheck
    blocked_demos: list
    dtw_free: float | None
    dtw_free_without_obstacles: float | None
    free_demos: list
    box: float
    horizon: float
    dt: float
    tolerance: float
    cpu_seconds: float
    wall_seconds: float

    def to_dict(self) -> dict:
        """JSON-ready form."""
        return dataclasses.asdict(self)


def free_starts(
    scene: Scene, center: np.ndarray, half_width: float, count: int, rng: np.random.Generator
) -> np.ndarray:
    """``count`` uniform states of the box around ``center`` that are in free space, (count, n)."""
    found: list[np.ndarray] = []
    total = 0
    for _ in range(1000):
        draw = center + rng.uniform(-half_width, half_width, size=(2 * count, len(center)))
        keep = draw[scene.free(torch.as_tensor(draw)).numpy()]
        found.append(keep)
        total += len(keep)
        if total >= count:
            return np.concatenate(found)[:count]
    raise ConfigError("the obstacles leave almost no free space in the box of random starts")


@torch.no_grad()
def _roll_out(
    policy: Policy,
    scene: Scene,
    starts: Tensor,
    target: Tensor,
    *,
    dt: float,
    horizon: float,
    tolerance: float,
    step_tolerance: float,
    max_step: float,
    extent: float,
    speed: float,
) -> RolloutCheck:
    """Adaptive guarded rollouts (error-controlled step sizes, as
    :func:`snds.stability.check_stability`'s) that stop once provably settled at the target."""
    count = len(starts)
    x = starts.clone()
    clock = torch.zeros(count, dtype=x.dtype)
    h = torch.full((count,), dt, dtype=x.dtype)
    guard = policy_guard(policy) if policy.stable else None
    level = None
    if guard is not None and not scene.moving:
        radius = 0.5 * tolerance / policy.normalization.length
        ball = target[None] + 0.5 * tolerance * _unit_directions(len(target), x.dtype)
        if not bool(scene.influenced(ball).any()) and not bool(scene.influenced(target[None])[0]):
            level = settle_level(policy.lyapunov, radius, dim=len(target))
    min_clear = scene.clearances(x).min(dim=-1).values
    entered = ~scene.free(x)
    held = 0
    active = torch.arange(count)
    moving = scene.moving
    velocity, near = _modulated(policy, scene, x)
    while len(active):
        xa = x[active]
        nominal = torch.minimum(h[active], horizon - clock[active])
        # Among moving obstacles every rollout shares one clock and takes the nominal step
        # (the obstacles do not wait for a shortened one); else the steps adapt per rollout.
        t = float(clock[active[0]]) if moving else 0.0
        known = {} if moving else {"velocity": velocity[active], "gammas": near[active]}
        # Twenty halvings (1e-6 of the period) tell a stall from a slow passage.
        candidate, taken, va = avoid_step(
            policy, scene, xa, dt=nominal, t=t, guard=guard, max_halvings=20, **known
        )
        held += int((taken == 0).sum())
        if moving:
            accept = torch.ones(len(active), dtype=torch.bool)
            tried = nominal
        else:
            v_new, g_new = _modulated(policy, scene, candidate)
            error = 0.5 * taken * (v_new - va).norm(dim=-1)
            accept = (error <= step_tolerance) | (nominal <= dt * 2.0**-10)
            grow = (0.9 * (step_tolerance / error.clamp_min(1e-300)).sqrt()).clamp(0.2, 4.0)
            # The error control sets the next period from a step the guard left alone; a
            # step the guard shortened keeps its period (the guard will shorten it again),
            # and one it all but held (a stall) lets the period grow, to reach the horizon.
            shortened = taken < nominal
            stuck = taken == 0
            following = torch.where(shortened, nominal, taken * grow)
            following = torch.where(stuck, 4.0 * nominal, following)
            h[active] = torch.where(accept, following, nominal * grow.clamp_max(0.9)).clamp(
                dt * 2.0**-10, max_step
            )
            # The period passes whatever part of it the guard let the state move.
            tried = nominal
        done = active[accept]
        x[done] = candidate[accept]
        if not moving:
            velocity[done], near[done] = v_new[accept], g_new[accept]
        clock[done] = clock[done] + tried[accept]
        later = scene.at(t + float(nominal.max())) if moving else scene
        clear = later.clearances(x[done]).min(dim=-1).values
        min_clear[done] = torch.minimum(min_clear[done], clear)
        entered[done] = entered[done] | ~later.free(x[done])
        finished = clock[active] >= horizon * (1 - 1e-12)
        if level is not None:
            finished = finished | (guard[0](x[active]) < level)
        active = active[~finished]
    distance = (x - target).norm(dim=-1)
    arrived = distance <= tolerance
    stalls = _cluster(policy, scene, x[~arrived], extent, speed)
    margins = [b.margin for b in scene.bodies] or [0.0]
    return RolloutCheck(
        starts=count,
        reached=int(arrived.sum()),
        converged_fraction=float(arrived.double().mean()) if count else float("nan"),
        stalled=int((~arrived).sum()),
        stall_points=stalls,
        penetrated=int(entered.sum()),
        min_clearance=float(min_clear.min()) if count else float("nan"),
        margin=float(min(margins)),
        held_steps=held,
    )


def _unit_directions(dim: int, dtype: torch.dtype, count: int = 256) -> Tensor:
    generator = torch.Generator().manual_seed(0)
    d = torch.randn(count, dim, generator=generator, dtype=dtype)
    return d / d.norm(dim=-1, keepdim=True)


def _cluster(policy: Policy, scene: Scene, ends: Tensor, extent: float, speed: float) -> list[dict]:
    """Clusters stalled end points; each {"center", "count", "gamma", "speed", "kind"}:
    "saddle" where the modulated field itself vanishes on a boundary, "held" where it still
    points into an obstacle and only the guard stops it (a concave junction of overlapping
    obstacles), "attractor" where the field vanishes in free space, else "moving"."""
    clusters: list[dict] = []
    for point in ends:
        for cluster in clusters:
            if float((point - cluster["point"]).norm()) <= 0.05 * extent:
                cluster["count"] += 1
                break
        else:
            clusters.append({"point": point, "count": 1})
    clusters.sort(key=lambda c: -c["count"])
    out = []
    for cluster in clusters[:20]:
        p = cluster["point"][None]
        velocity, gammas = _modulated(policy, scene, p)
        gamma = float(gammas.min()) if gammas.numel() else math.inf
        fast = float(velocity.norm())
        on_boundary = gamma < 1.0 + 1e-3
        still = fast < 1e-3 * speed
        kind = (
            ("saddle" if still else "held") if on_boundary else ("attractor" if still else "moving")
        )
        out.append(
            {
                "center": p[0].tolist(),
                "count": cluster["count"],
                "gamma": gamma,
                "speed": fast,
                "kind": kind,
            }
        )
    return out


@torch.no_grad()
def check_obstacles(
    policy: Policy,
    demos: Demonstrations,
    scene: Scene,
    *,
    rollouts: int = 1000,
    box_factor: float = 3.0,
    horizon_factor: float = 10.0,
    tolerance_factor: float = 0.01,
    step_tolerance_factor: float = 1e-3,
    seed: int = 0,
) -> ObstacleReport:
    """The stability report under obstacles: random free starts, the demonstrations' starts,
    and DTW to the demonstrations the obstacles leave free.

    Random starts are uniform in the free part of the box of half-width ``box_factor`` x the
    extent around the target (rejection sampling); rollouts of :func:`avoid_step` with
    error-controlled steps (from the demonstrations' mean step, at most 1/50 of the horizon)
    run for ``horizon_factor`` x the longest demonstration's duration, or until a stable
    policy's V shows them settled in a ball that no obstacle reaches. Everything in float64.

    Arguments:
        policy: Any policy (a float64 copy is evaluated).
        demos: The demonstrations (extent, step, horizon, starts).
        scene: The obstacles.
        rollouts: Random starts.
        box_factor: Half-width of their box, in extents.
        horizon_factor: Rollout duration, in longest-demonstration durations.
        tolerance_factor: Arrival tolerance, in extents.
        step_tolerance_factor: Local error per step, in extents.
        seed: Seed of the random starts.
    """
    wall, cpu = _time.perf_counter(), _time.process_time()
    policy = float64_copy(policy)
    scene.check(demos.dim, demos.target)
    rng = np.random.default_rng(seed)
    extent, target = demos.extent(), torch.tensor(demos.target)
    dt, horizon = demos.mean_dt(), horizon_factor * demos.max_duration()
    tolerance = tolerance_factor * extent
    settings = dict(
        dt=dt,
        horizon=horizon,
        tolerance=tolerance,
        step_tolerance=step_tolerance_factor * extent,
        max_step=horizon / 50,
        extent=extent,
        speed=demos.max_speed(),
    )
    starts = free_starts(scene, demos.target, box_factor * extent, rollouts, rng)
    random = _roll_out(policy, scene, torch.as_tensor(starts), target, **settings)
    demo_starts = torch.tensor(np.stack([d.positions[0] for d in demos]))
    in_free = scene.free(demo_starts)
    from_demos = _roll_out(policy, scene, demo_starts[in_free], target, **settings)
    blocked, free_demos = [], []
    for i, demo in enumerate(demos):
        path = torch.tensor(demo.positions)
        (free_demos if bool(scene.free(path).all()) else blocked).append(i)
    dtw_free = dtw_plain = None
    if free_demos:
        paths = _reproduce_avoiding(policy, scene, demos, free_demos)
        plain = reproduce(policy, demos, free_demos)
        dtw_free = float(np.mean([dtw(p, demos[i].positions) for p, i in zip(paths, free_demos)]))
        dtw_plain = float(np.mean([dtw(p, demos[i].positions) for p, i in zip(plain, free_demos)]))
    return ObstacleReport(
        scene=scene.to_dict(),
        random=random,
        demos=from_demos,
        blocked_demos=blocked,
        dtw_free=dtw_free,
        dtw_free_without_obstacles=dtw_plain,
        free_demos=free_demos,
        box=box_factor * extent,
        horizon=horizon,
        dt=dt,
        tolerance=tolerance,
        cpu_seconds=_time.process_time() - cpu,
        wall_seconds=_time.perf_counter() - wall,
    )


def _reproduce_avoiding(
    policy: Policy, scene: Scene, demos: Demonstrations, indices: list[int]
) -> list[np.ndarray]:
    """Guarded rollouts from demonstrations' starts, each with its own mean step and length."""
    steps = [len(demos[i].times) - 1 for i in indices]
    dt = torch.tensor([demos[i].duration / k for i, k in zip(indices, steps)], dtype=torch.float64)
    x0 = torch.as_tensor(np.stack([demos[i].positions[0] for i in indices]))
    states, _ = avoiding_rollout(policy, scene, x0, dt=dt, steps=max(steps))
    paths = states.transpose(0, 1).numpy()
    return [paths[row, : k + 1] for row, k in enumerate(steps)]


def rollout_numpy_avoiding(
    policy: Policy, scene: Scene, x0: np.ndarray, *, dt: float, steps: int
) -> np.ndarray:
    """NumPy convenience: guarded rollouts under obstacles, float64, (B, steps + 1, n)."""
    policy = float64_copy(policy)
    states, _ = avoiding_rollout(
        policy, scene, torch.as_tensor(np.asarray(x0, dtype=np.float64)), dt=dt, steps=steps
    )
    return states.transpose(0, 1).numpy()


@torch.no_grad()
def step_fraction(
    scene: Scene, x: Tensor, v: Tensor, dt: float, *, max_halvings: int = 40
) -> Tensor:
    """The largest fraction 2^-k (k <= ``max_halvings``; else 0) of a step of ``dt`` along
    velocities v (B, n) from states x (B, n) that ends in free space, shape (B,)."""
    fraction = torch.ones(len(x), dtype=x.dtype)
    pending = torch.arange(len(x))
    pending = pending[~scene.free(x + dt * v)]
    for _ in range(max_halvings):
        if len(pending) == 0:
            break
        fraction[pending] = 0.5 * fraction[pending]
        reached = x[pending] + (dt * fraction[pending]).unsqueeze(-1) * v[pending]
        pending = pending[~scene.free(reached)]
    fraction[pending] = 0.0
    return fraction
