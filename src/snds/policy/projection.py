r"""The projection at the heart of SNDS: a velocity field made to decrease a Lyapunov function.

:func:`project` removes from a nominal field the part that would let V decrease more slowly
than a required rate; the rectifiers of :data:`RECTIFIERS` choose how sharply.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

__all__ = ["RECTIFIERS", "project"]


def _relu(u: Tensor) -> Tensor:
    return F.relu(u)


def _softplus(u: Tensor, sharpness: float = 50.0) -> Tensor:
    # softplus(k u) / k >= max(u, 0) for every u, so the decrease bound still holds exactly.
    return F.softplus(u, beta=sharpness)


#: Rectifiers r with r(u) >= max(u, 0): ReLU (the paper) or a smooth softplus.
RECTIFIERS = {"relu": _relu, "softplus": _softplus}


def project(f: Tensor, grad_v: Tensor, decay: Tensor, *, rectifier: str = "relu") -> Tensor:
    r"""Removes the part of a velocity field that would let V decrease too slowly.

    .. math:: \pi = f - \nabla V \, \frac{r(\nabla V^\top f + a)}{\|\nabla V\|^2}

    With :math:`r(u) \ge \max(u, 0)`, :math:`\nabla V^\top \pi = \nabla V^\top f -
    r(\nabla V^\top f + a) \le -a` holds exactly wherever :math:`\nabla V \ne 0`; where
    :math:`f` already decreases V fast enough (and r is ReLU), :math:`\pi = f`. No regulariser
    is added to the denominator, since one would break the inequality; where
    :math:`\nabla V = 0` (only at the target, for a strongly convex V) :math:`\pi = f`.

    Arguments:
        f: Nominal velocities, shape (*, n).
        grad_v: Gradient of the Lyapunov function at the same states, shape (*, n).
        decay: Required decrease rate a(x) >= 0, shape (*,).
        rectifier: A key of :data:`RECTIFIERS`.

    Returns:
        The projected velocities, shape (*, n).
    """
    norm2 = (grad_v * grad_v).sum(-1)
    excess = RECTIFIERS[rectifier]((grad_v * f).sum(-1) + decay)
    safe = torch.where(norm2 > 0, norm2, 1.0)
    return f - grad_v * (excess / safe).unsqueeze(-1)
