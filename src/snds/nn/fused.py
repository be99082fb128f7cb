"""The training path's fused operations, and the switch that turns them off.

Where autograd records a pass (training), :mod:`snds.nn` computes the same maths with fewer
or faster operations: sin and cos of the coupling layers' Fourier angles from one pass, and
weights in the memory layout that makes the products with a handful of output columns fast
(docs/design.md, "Training in seconds"). Without autograd (evaluation, checks, export) the
plain operations run, and so they do while a graph is traced: exported graphs are unchanged.
"""

from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["ENABLED", "SinCos", "active", "sincos"]

#: Whether the fused path is taken where autograd records; False gives the reference path,
#: the same maths in plain operations (for tests and benchmarks).
ENABLED = True


def active() -> bool:
    """Whether the fused path applies: :data:`ENABLED`, autograd recording, and no graph
    being traced (``torch.export``, ONNX export, ``torch.compile`` and ``torch.jit.trace``
    see the plain operations, whatever the grad mode)."""
    return (
        ENABLED
        and torch.is_grad_enabled()
        and not torch.compiler.is_compiling()
        and not torch.jit.is_tracing()
    )


class SinCos(torch.autograd.Function):
    """(sin a, cos a) from one pass, differentiated with the values it computed.

    Autograd on ``sin`` and ``cos`` separately recomputes each other's function in the
    backward pass (d sin = cos da, d cos = -sin da); this computes each of the two once. The
    backward pass is built from differentiable operations, so it can be differentiated again,
    and ``torch.func.vmap`` batches it by its generated rule.
    """

    generate_vmap_rule = True

    @staticmethod
    def forward(angles: Tensor) -> tuple[Tensor, Tensor]:  # noqa: D102
        return torch.sin(angles), torch.cos(angles)

    @staticmethod
    def setup_context(ctx, inputs, output) -> None:  # noqa: ANN001, D102
        ctx.save_for_backward(*output)

    @staticmethod
    def backward(ctx, grad_sin: Tensor | None, grad_cos: Tensor | None) -> Tensor | None:  # noqa: ANN001, D102
        sin, cos = ctx.saved_tensors
        grad = None
        if grad_sin is not None:
            grad = grad_sin * cos
        if grad_cos is not None:
            grad = -grad_cos * sin if grad is None else grad - grad_cos * sin
        return grad


def sincos(angles: Tensor) -> tuple[Tensor, Tensor]:
    """sin and cos of ``angles`` (any shape), each computed once in the forward pass and
    reused by the backward pass; the values are those of ``torch.sin`` and ``torch.cos``."""
    # Through ``Function.apply``, the documented entry. Calling the engine's ``apply`` past
    # it (skipping its argument binding, a private path) saved 27 us of CPU a call, 7.5 calls
    # a step: 1.9% of the default training step, not worth a path a torch upgrade may break
    # (benchmarks/torch_internals.py; benchmarks/results/torch_internals.json).
    return SinCos.apply(angles)
