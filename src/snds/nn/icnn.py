r"""Input-convex neural networks (Amos et al., 2017) with an analytic input gradient."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from snds.nn import fused

__all__ = ["CONVEX_ACTIVATIONS", "ICNN"]


def _softplus(u: Tensor) -> tuple[Tensor, Tensor]:
    return F.softplus(u), torch.sigmoid(u)


def _smooth_leaky(u: Tensor, slope: float = 0.1) -> tuple[Tensor, Tensor]:
    # A softplus with a linear floor: convex, non-decreasing, smooth, and its slope never
    # falls below `slope`, so gradients reach the first layers even for very negative inputs.
    return slope * u + (1 - slope) * F.softplus(u), slope + (1 - slope) * torch.sigmoid(u)


#: Convex, non-decreasing, smooth activations, each returning (s(u), s'(u)).
CONVEX_ACTIVATIONS = {"softplus": _softplus, "smooth_leaky": _smooth_leaky}


class ICNN(nn.Module):
    r"""A scalar function :math:`g(x)` that is convex in :math:`x` by construction.

    .. math:: z_1 = s(A_0 x + b_0), \quad z_{k+1} = s(A_k x + W_k z_k + b_k),
              \quad g(x) = w^\top z_K + a^\top x

    with :math:`W_k \ge 0`, :math:`w \ge 0` (a softplus of free parameters) and :math:`s`
    convex and non-decreasing: a non-negative sum of convex non-decreasing functions of
    convex functions stays convex. The input skips :math:`A_k` are unconstrained.

    Arguments:
        dim: Input dimension n.
        hidden: Widths of the hidden layers, at least one.
        activation: A key of :data:`CONVEX_ACTIVATIONS`.
    """

    def __init__(
        self, dim: int, *, hidden: tuple[int, ...] = (64, 64), activation: str = "smooth_leaky"
    ) -> None:
        super().__init__()
        if not hidden:
            raise ValueError("an ICNN needs at least one hidden layer")
        if activation not in CONVEX_ACTIVATIONS:
            raise ValueError(
                f"unknown convex activation {activation!r}; choose from {list(CONVEX_ACTIVATIONS)}"
            )
        self.activation = activation
        self.skips = nn.ModuleList(nn.Linear(dim, size) for size in hidden)
        # Raw weights on the previous layer; their softplus is the non-negative weight. The
        # initial value makes softplus(raw) about 1/width, so the layers neither blow up nor die.
        self.raw_weights = nn.ParameterList(
            nn.Parameter(torch.randn(size, prev) * 0.1 + _inverse_softplus(1.0 / prev))
            for prev, size in zip(hidden[:-1], hidden[1:])
        )
        self.raw_out = nn.Parameter(
            torch.randn(hidden[-1]) * 0.1 + _inverse_softplus(1.0 / hidden[-1])
        )
        self.linear_out = nn.Parameter(torch.zeros(dim))

    def weights(self) -> list[Tensor]:
        """The non-negative weights W_k on the previous layer, each (h_{k+1}, h_k)."""
        return [F.softplus(raw) for raw in self.raw_weights]

    def value_and_grad(self, x: Tensor) -> tuple[Tensor, Tensor]:
        r"""Evaluates :math:`g` and :math:`\nabla g` with one forward and one backward pass.

        The backward pass is written out, not taken from autograd, so that the policy can be
        exported (ONNX, ``torch.export``) and evaluated in microseconds; it stays
        differentiable with respect to the parameters for training.

        Arguments:
            x: States, shape (*, n).

        Returns:
            The values, shape (*,), and the gradients, shape (*, n).
        """
        act = CONVEX_ACTIVATIONS[self.activation]
        weights = self.weights()
        # The skips' weights A_k (h, n) as the products use them. In training (autograd on),
        # A_k^T is copied to row-major (n, h) and A_k is its column-major view: the products
        # with n columns, (B, h) @ (h, n) here and (h, B) @ (B, n) in their backward pass,
        # are several times slower on the CPU otherwise (docs/design.md). The same values.
        if fused.active():
            skips_t = [skip.weight.T.contiguous() for skip in self.skips]
            skips = [a.T for a in skips_t]
        else:
            skips = [skip.weight for skip in self.skips]
            skips_t = [a.T for a in skips]
        slopes = []
        z = None
        for k, skip in enumerate(self.skips):
            u = (
                torch.addmm(skip.bias, x, skips_t[k])
                if x.dim() == 2
                else x @ skips_t[k] + skip.bias
            )
            if z is not None:
                u = u + z @ weights[k - 1].T
            z, slope = act(u)
            slopes.append(slope)
        out = F.softplus(self.raw_out)
        value = z @ out + x @ self.linear_out
        # Backward: e is dg/dz_k; delta = e * s'(u_k) is dg/du_k. The output weights and the
        # linear term broadcast over the batch (no expand: fewer nodes in an export).
        grad = self.linear_out
        e = out
        for k in range(len(self.skips) - 1, -1, -1):
            delta = e * slopes[k]
            grad = delta @ skips[k] + grad
            if k > 0:
                e = delta @ weights[k - 1]
        return value, grad

    def forward(self, x: Tensor) -> Tensor:
        """Evaluates g at states (*, n), returning shape (*,)."""
        return self.value_and_grad(x)[0]


def _inverse_softplus(y: float) -> float:
    # On the CPU even under a default device: snds.io builds policies on "meta" to check shapes.
    return float(torch.log(torch.expm1(torch.tensor(y, device="cpu"))))
