"""The optimiser's step: gradient clipping without torch's per-call grouping work (the same
arithmetic, bit for bit: tests/test_train.py), and fused Adam.

The networks are small, so a training step's cost is mostly the number of operations and
Python calls, not their size.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

__all__ = ["adam", "adam_step", "clip_gradients"]


def adam(parameters: Sequence[torch.Tensor], lr: float) -> torch.optim.Adam:
    """A fused Adam over ``parameters``: it updates every parameter in one kernel."""
    return torch.optim.Adam(parameters, lr=lr, fused=True)


def clip_gradients(parameters: Sequence[torch.Tensor], max_norm: float) -> torch.Tensor:
    """Scales the gradients of ``parameters`` to a total 2-norm of at most ``max_norm``;
    returns the norm before clipping (NaN or inf if a gradient is).

    The same operations, in the same order, as ``torch.nn.utils.clip_grad_norm_(parameters,
    max_norm, foreach=True)`` on parameters of one device and dtype (so the same bits), without
    its per-call grouping work; other parameter sets go through it. Taking the parameters as a
    list (not a module) spares a walk of the module tree on every step.
    """
    grads = [p.grad for p in parameters if p.grad is not None]
    kinds = {(g.device, g.dtype) for g in grads}
    if len(kinds) != 1 or any(g.is_sparse for g in grads):
        return torch.nn.utils.clip_grad_norm_(parameters, max_norm, foreach=True)
    with torch.no_grad():
        total = torch.linalg.vector_norm(torch.stack(torch._foreach_norm(grads, 2.0)), 2.0)
        torch._foreach_mul_(grads, torch.clamp(max_norm / (total + 1e-6), max=1.0))
    return total


def adam_step(optimizer: torch.optim.Adam, lr: float) -> None:
    """``optimizer.step()`` at learning rate ``lr`` (which it keeps in its parameter groups).

    Through the public step: calling its fused kernel (``torch._fused_adam_``) directly saved
    about 65 us of a 10 ms training step (0.6 %, ``benchmarks/results/adam_step.json``), not
    worth a private torch call.
    """
    for group in optimizer.param_groups:
        group["lr"] = lr
    optimizer.step()
