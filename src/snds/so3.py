r"""SO(3) maths on unit quaternions (x, y, z, w; roma's order, and SciPy's): the log and exp
maps relative to a target orientation, the left Jacobian of the exponential map and its
inverse, and uniform random orientations.

:math:`q` and :math:`-q` are one orientation; every function here is blind to that sign.
"""

from __future__ import annotations

import importlib
from types import ModuleType

import numpy as np
import torch
from torch import Tensor

__all__ = [
    "geodesic_angle",
    "left_jacobian",
    "left_jacobian_inverse",
    "random_quaternions",
    "relative_rotvec",
    "roma",
    "rotate",
]


def roma() -> ModuleType:
    """The roma package, imported at its first use: importing it imports torch's compiler
    stack (about a second), which a position model never needs."""
    return importlib.import_module("roma")


def relative_rotvec(q: Tensor, q_target: Tensor) -> Tensor:
    r"""The rotation vector :math:`\log(q \, q^{*-1})`, angle in :math:`[0, \pi]`.

    Canonical (shortest arc), so :math:`q` and :math:`-q` (and :math:`\pm q^*`) give the same
    vector.

    Arguments:
        q: Unit quaternions (x, y, z, w), shape (*, 4).
        q_target: The target orientation, shape (4,) or (*, 4).

    Returns:
        Rotation vectors, shape (*, 3).
    """
    quat = roma()
    relative = quat.quat_product(q, quat.quat_conjugation(q_target.expand_as(q)))
    return quat.unitquat_to_rotvec(relative, shortest_arc=True)


def rotate(rotvec: Tensor, q: Tensor) -> Tensor:
    r""":math:`\exp(r) \, q`: the orientation ``q`` (*, 4) turned by ``rotvec`` (*, 3) in the
    world frame."""
    quat = roma()
    return quat.quat_product(quat.rotvec_to_unitquat(rotvec), q)


def _hat(r: Tensor) -> Tensor:
    """The skew matrix [r]_x, shape (*, 3, 3), with [r]_x u = r x u."""
    zero = torch.zeros_like(r[..., 0])
    x, y, z = r[..., 0], r[..., 1], r[..., 2]
    return torch.stack(
        [
            torch.stack([zero, -z, y], -1),
            torch.stack([z, zero, -x], -1),
            torch.stack([-y, x, zero], -1),
        ],
        -2,
    )


def left_jacobian(r: Tensor) -> Tensor:
    r"""The left Jacobian of SO(3), :math:`\exp(r + \delta) \approx \exp(J_l(r)\delta)\exp(r)`.

    .. math:: J_l(r) = I + \frac{1 - \cos\theta}{\theta^2} [r]_\times
              + \frac{\theta - \sin\theta}{\theta^3} [r]_\times^2, \qquad \theta = |r|,

    with the Taylor series of the coefficients below :math:`\theta = 10^{-3}` (where the
    closed forms lose their digits to cancellation). roma offers no Jacobian of the exponential
    map, hence these few lines.

    Arguments:
        r: Rotation vectors, shape (*, 3).

    Returns:
        The matrices, shape (*, 3, 3).
    """
    theta2 = (r * r).sum(-1)
    theta = theta2.sqrt()
    small = theta < 1e-3
    safe = torch.where(small, torch.ones_like(theta), theta)
    a = torch.where(small, 0.5 - theta2 / 24, (1 - torch.cos(safe)) / safe**2)
    b = torch.where(small, 1 / 6 - theta2 / 120, (safe - torch.sin(safe)) / safe**3)
    hat = _hat(r)
    eye = torch.eye(3, dtype=r.dtype, device=r.device).expand_as(hat)
    return eye + a[..., None, None] * hat + b[..., None, None] * (hat @ hat)


def left_jacobian_inverse(r: Tensor) -> Tensor:
    r"""The inverse of :func:`left_jacobian`, for :math:`|r| < 2\pi`.

    .. math:: J_l^{-1}(r) = I - \tfrac12 [r]_\times + \Big(\frac{1}{\theta^2}
              - \frac{1 + \cos\theta}{2 \theta \sin\theta}\Big) [r]_\times^2

    (series below :math:`\theta = 10^{-3}`; the coefficient tends to :math:`1 / \pi^2` at
    :math:`\theta = \pi`, where its closed form is 0/0).

    Arguments:
        r: Rotation vectors, shape (*, 3).

    Returns:
        The matrices, shape (*, 3, 3).
    """
    theta2 = (r * r).sum(-1)
    theta = theta2.sqrt()
    small = theta < 1e-3
    near_pi = (torch.pi - theta).abs() < 1e-6
    safe = torch.where(small | near_pi, torch.full_like(theta, 1.0), theta)
    c = 1 / safe**2 - (1 + torch.cos(safe)) / (2 * safe * torch.sin(safe))
    c = torch.where(small, 1 / 12 + theta2 / 720, c)
    c = torch.where(near_pi, torch.full_like(theta, 1 / torch.pi**2), c)
    hat = _hat(r)
    eye = torch.eye(3, dtype=r.dtype, device=r.device).expand_as(hat)
    return eye - 0.5 * hat + c[..., None, None] * (hat @ hat)


def geodesic_angle(q1: np.ndarray, q2: np.ndarray) -> np.ndarray:
    """Angle (radians, [0, pi]) of the rotation between orientations (*, 4), sign-blind."""
    dots = np.abs(np.sum(np.asarray(q1) * np.asarray(q2), axis=-1))
    return 2.0 * np.arccos(np.clip(dots, 0.0, 1.0))


def random_quaternions(count: int, rng: np.random.Generator) -> np.ndarray:
    """Orientations uniform on SO(3) (the Haar measure: normalised 4-D Gaussians), shape
    (count, 4)."""
    quats = rng.standard_normal((count, 4))
    return quats / np.linalg.norm(quats, axis=1, keepdims=True)
