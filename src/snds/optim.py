"""The optimiser's step: gradient clipping and fused Adam, without torch's per-call
bookkeeping (the same arithmetic, bit for bit: tests/test_train.py).

The networks are small, so a training step's cost is mostly the number of operations and
Python calls, not their size: the bookkeeping of ``clip_grad_norm_`` and ``Adam.step`` costs
more than their kernels here.
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

    For a fused Adam of one parameter group, without AMSGrad, maximisation or weight decay,
    whose state exists (from the second step on), this calls the kernel that
    ``optimizer.step()`` calls, with the same arguments, directly: the same update, bit for
    bit, without the optimiser's per-call bookkeeping, which costs more than the kernel on
    these small networks. Otherwise it calls ``optimizer.step()``.
    """
    for group in optimizer.param_groups:
        group["lr"] = lr
    group = optimizer.param_groups[0]
    params = [p for p in group["params"] if p.grad is not None]
    states = [optimizer.state.get(p) for p in params]
    direct = (
        len(optimizer.param_groups) == 1
        and hasattr(torch, "_fused_adam_")
        and group.get("fused")
        and not (group["amsgrad"] or group["maximize"] or group["weight_decay"])
        and not (group.get("differentiable") or group.get("decoupled_weight_decay"))
        and params
        and all(states)
        and len({(p.device, p.dtype) for p in params}) == 1
    )
    if not direct:
        optimizer.step()
        return
    beta1, beta2 = group["betas"]
    steps = [state["step"] for state in states]
    with torch.no_grad():
        torch._foreach_add_(steps, 1)
        torch._fused_adam_(
            params,
            [p.grad for p in params],
            [state["exp_avg"] for state in states],
            [state["exp_avg_sq"] for state in states],
            [],
            steps,
            amsgrad=False,
            lr=lr,
            beta1=beta1,
            beta2=beta2,
            weight_decay=0.0,
            eps=group["eps"],
            maximize=False,
            grad_scale=None,
            found_inf=None,
        )
