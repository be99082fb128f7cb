r"""A scene of obstacles and the modulation of a velocity field around them.

See the package's documentation (:mod:`snds.obstacles`) for the maths.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

from snds.errors import ConfigError
from snds.obstacles.shapes import (
    SHAPES,
    WORKSPACES,
    Obstacle,
    Workspace,
    safe_normalize,
    shape_name,
)
from snds.obstacles.spec import obstacle_from_dict
from snds.policy import Policy

__all__ = ["ModulatedPolicy", "Scene", "load_scene", "modulate_twist", "step_fraction"]

#: Smallest :math:`n^\top r` used in the radial coordinate (the shapes make it positive).
_MIN_ALIGNMENT = 1e-12


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
                raise ConfigError(f"a {body.dim}-D {shape_name(type(body))} for a {dim}-D model")
        x = torch.tensor(np.asarray(target, dtype=np.float64))[None]
        for body in self.bodies:
            if float(body.gamma(x)[0]) <= 1.0:
                raise ConfigError(
                    f"the target {np.round(target, 6).tolist()} is not in free space: it is "
                    f"within the margin of the {shape_name(type(body))} at "
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
            offset = x - body.center_tensor(x)
            normal = safe_normalize(gradient)
            radial = safe_normalize(-offset if body.free_inside else offset)
            # At the reference point itself (only a workspace's centre can be in reach) the
            # normal stands in for the undefined direction.
            degenerate = offset.norm(dim=-1, keepdim=True) == 0
            radial = torch.where(degenerate, normal, radial)
            parts.append((weight, normal, radial))
        weights = torch.stack([p[0] for p in parts], dim=-1)  # (*, K)
        effective = weights * _shares(weights)
        if target is not None:
            # Turned only as far as v heads into a body: a field passing by keeps its course.
            unit = safe_normalize(v)
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
            obstacle_from_dict(e, SHAPES, f"{where}: obstacle {i}") for i, e in enumerate(entries)
        )
        space = data.get("workspace")
        workspace = (
            None if space is None else obstacle_from_dict(space, WORKSPACES, f"{where}: workspace")
        )
        return cls(obstacles=obstacles, workspace=workspace)


def _turn(v: Tensor, towards: Tensor, fraction: Tensor) -> Tensor:
    r"""Velocities v (*, n) turned towards directions (*, n) by ``fraction`` (*, 1) of the
    angle between them, in the plane they span, keeping their length. A velocity exactly
    opposite to its direction (no plane) is left as it is."""
    speed = v.norm(dim=-1, keepdim=True)
    unit = safe_normalize(v)
    goal = safe_normalize(towards)
    cosine = (unit * goal).sum(-1, keepdim=True)
    across = goal - cosine * unit
    sine = across.norm(dim=-1, keepdim=True)
    angle = torch.atan2(sine, cosine) * fraction
    turned = speed * (torch.cos(angle) * unit + torch.sin(angle) * safe_normalize(across))
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
    scene is followed in time by :func:`snds.rollout.rollout`. It carries no Lyapunov function:
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
        :class:`snds.steppers.GuardedEuler`, which a controller applies itself."""
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
