r"""Lyapunov functions that are positive definite by construction: convex, or warped."""

from __future__ import annotations

import torch
from torch import Tensor, nn

from snds.nn.flow import EuclideanizingFlow
from snds.nn.icnn import ICNN

__all__ = ["Lyapunov", "WarpedLyapunov"]


class Lyapunov(nn.Module):
    r"""The Bregman form of a convex network, plus a quadratic floor.

    .. math:: V(x) = g(x) - g(x^*) - \nabla g(x^*)^\top (x - x^*) + d \|x - x^*\|^2

    with :math:`g` an :class:`ICNN`. The paper's :math:`g(x) - g(x^*) + d\|x - x^*\|^2` goes
    negative along :math:`-\nabla g(x^*)` unless :math:`\nabla g(x^*) = 0`; subtracting the
    tangent plane at :math:`x^*` fixes that. Hence :math:`V` is convex, :math:`V(x^*) = 0`,
    :math:`V(x) \ge d \|x - x^*\|^2`, and :math:`\|\nabla V(x)\| \ge 2 d \|x - x^*\|` (strong
    convexity), so the projection never divides by zero away from the target. V is evaluated
    as :math:`\min(V, \nabla V^\top (x - x^*))`, equal in exact arithmetic (convexity) and
    free of the Bregman difference's cancellation next to the target.

    The target is the origin of the model's coordinates.

    Arguments:
        dim: State dimension n.
        hidden: Widths of the ICNN's hidden layers.
        activation: The ICNN's convex activation.
        quadratic: The coefficient d > 0 of the quadratic floor.
    """

    def __init__(
        self,
        dim: int,
        *,
        hidden: tuple[int, ...] = (64, 64),
        activation: str = "smooth_leaky",
        quadratic: float = 0.05,
    ) -> None:
        super().__init__()
        if quadratic <= 0:
            raise ValueError(f"the quadratic coefficient must be positive, got {quadratic}")
        self.icnn = ICNN(dim, hidden=hidden, activation=activation)
        self.quadratic = quadratic

    def value_and_grad(
        self, x: Tensor, *, at_target: tuple[Tensor, Tensor] | None = None
    ) -> tuple[Tensor, Tensor]:
        r"""Evaluates :math:`V` and :math:`\nabla V` analytically (no autograd needed).

        Arguments:
            x: States in model coordinates, shape (*, n).
            at_target: :math:`g(x^*)` and :math:`\nabla g(x^*)`, shapes () and (n,), when the
                caller already has them (an exported policy computes them once, not per
                call); evaluated together with ``x`` otherwise.

        Returns:
            V, shape (*,), and its gradient, shape (*, n).
        """
        if at_target is None:
            # One pass over the batch and the target together: half the calls of two passes.
            n = x.shape[-1]
            # A batch (B, n), the usual case and an export's, needs no reshapes.
            flat = x if x.dim() == 2 else x.reshape(-1, n)
            g, grad_g = self.icnn.value_and_grad(torch.cat([flat, flat.new_zeros(1, n)]))
            g0, grad_g0 = g[-1], grad_g[-1]
            g, grad_g = g[:-1], grad_g[:-1]
            if x.dim() != 2:
                g, grad_g = g.reshape(x.shape[:-1]), grad_g.reshape(x.shape)
        else:
            g, grad_g = self.icnn.value_and_grad(x)
            g0, grad_g0 = at_target
        # The Bregman divergence of a convex g is >= 0 exactly; the clamp only removes the
        # rounding error of the cancellation g(x) - g(0) - grad g(0).x near the target, which
        # in float32 could otherwise make V slightly negative there.
        bregman = (g - g0 - (x * grad_g0).sum(-1)).clamp_min(0.0)
        value = bregman + self.quadratic * (x * x).sum(-1)
        grad = grad_g - grad_g0 + 2 * self.quadratic * x
        # Near the target the Bregman difference cancels O(1) terms down to rounding noise of
        # size eps |g(0)|, far above its true O(|x|^2); the decay a = rho V divided by |grad V|
        # then blew up into a spurious velocity at the target. grad V . x >= V holds exactly
        # (it adds the reverse Bregman divergence and d |x|^2, both >= 0) and cancels only to
        # eps |grad g(0)| |x|, so the smaller of the two is V in exact arithmetic and stays
        # accurate next to the target.
        value = torch.minimum(value, (grad * x).sum(-1)).clamp_min(0.0)
        return value, grad

    def forward(self, x: Tensor) -> Tensor:
        """V at states (*, n), shape (*,)."""
        return self.value_and_grad(x)[0]


class WarpedLyapunov(nn.Module):
    r"""A convex Lyapunov function seen through a learned diffeomorphism.

    .. math:: V(x) = V_c\big(\phi(x) - \phi(x^*)\big), \qquad
        \nabla V(x) = J_\phi(x)^\top \, \nabla V_c\big(\phi(x) - \phi(x^*)\big),

    with :math:`V_c` a :class:`Lyapunov` (convex, quadratic floor d) and :math:`\phi` an
    :class:`~snds.nn.flow.EuclideanizingFlow` of additive coupling layers.

    **Why.** The sublevel sets of a convex V are convex, and a motion that V certifies never
    leaves the sublevel set it is in, so it stays inside the convex hull of its own future: a
    demonstration that winds back and forth (a snake) passes points inside the hull of its
    later wiggles, where no convex V can decrease along it. The warp bends the sublevel sets
    to follow such a path.

    **Guarantee kept.** :math:`\phi` is a bijection of :math:`\mathbb{R}^n` with an
    invertible Jacobian everywhere (every layer is), so :math:`V(x^*) = 0`, :math:`V > 0`
    elsewhere, and :math:`\nabla V \ne 0` away from the target (:math:`\nabla V_c(z) \ne 0`
    for :math:`z \ne 0` by strong convexity): the projection is defined at every state, and
    no state but the target is an equilibrium. Additive couplings shift the state by at most a
    bounded amount B, so :math:`V(x) \ge d (|x - x^*| - 2B)_+^2`: V is radially unbounded.
    Unlike the convex V it has no floor :math:`d |x - x^*|^2` in closed form, hence
    :attr:`quadratic` = 0 (the stability check then samples its settle level), and V is not
    convex along a line, which the largest-safe-step bisection assumes (it becomes a
    heuristic, as for SDS-EF); the guarded rollout step needs only a descent direction.

    The flow starts as the identity (zero weights), so a warped policy starts as the convex
    one. The target is the origin of the model's coordinates.

    Arguments:
        convex: The convex :math:`V_c`, evaluated in the warped coordinates.
        warp: The diffeomorphism :math:`\phi`.
    """

    #: No quadratic floor in x is known (see above).
    quadratic: float = 0.0

    def __init__(self, convex: Lyapunov, warp: EuclideanizingFlow) -> None:
        super().__init__()
        self.convex = convex
        self.warp = warp

    def value_and_grad(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """Evaluates :math:`V` and :math:`\\nabla V` analytically (no autograd needed).

        Arguments:
            x: States in model coordinates, shape (*, n).

        Returns:
            V, shape (*,), and its gradient, shape (*, n).
        """
        n = x.shape[-1]
        flat = x if x.dim() == 2 else x.reshape(-1, n)
        # A state exactly at the target gets z = 0 exactly, hence V = 0 there.
        z, caches = self.warp.centred(flat)
        value, grad_z = self.convex.value_and_grad(z[:-1])
        grad = self.warp.vjp(caches, torch.cat([grad_z, grad_z.new_zeros(1, n)]))[:-1]
        if x.dim() != 2:
            value, grad = value.reshape(x.shape[:-1]), grad.reshape(x.shape)
        return value, grad

    def forward(self, x: Tensor) -> Tensor:
        """V at states (*, n), shape (*,): the value of :meth:`value_and_grad`, without the
        Jacobian product through the warp that only the gradient needs."""
        n = x.shape[-1]
        flat = x if x.dim() == 2 else x.reshape(-1, n)
        z, _ = self.warp.centred(flat)
        value = self.convex(z[:-1])
        return value if x.dim() == 2 else value.reshape(x.shape[:-1])
