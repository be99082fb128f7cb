r"""The decrease condition of a stable policy, checked on given states.

:func:`decrease_violations` counts the states where :math:`\nabla V^\top \pi \le -a(x)` fails
beyond rounding; :func:`largest_safe_step` finds the longest Euler step that decreases V at
every given state. The stability check (:mod:`snds.stability`) runs both on its samples and
on the states its rollouts visit.
"""

from __future__ import annotations

import torch

from snds.policy import FieldTerms, Policy

__all__ = ["decrease_violations", "largest_safe_step"]


@torch.no_grad()
def decrease_violations(
    policy: Policy, x: torch.Tensor, *, rtol: float = 1e-9, terms: FieldTerms | None = None
) -> int:
    r"""Counts states where :math:`\nabla V^\top \pi \le -a(x)` fails beyond rounding.

    Checked in model coordinates (a positive rescaling of user units, so the sign of the
    condition is the same). The tolerance is relative to the size of the terms that cancel,
    :math:`\|\nabla V\| \|f\| + a`, since the projection makes the two sides equal whenever
    it is active.

    Arguments:
        policy: A stable policy, evaluated in the dtype of ``x`` (use float64).
        x: States in user units, shape (B, n).
        rtol: Relative rounding tolerance.
        terms: The policy's :meth:`~snds.policy.Policy.field_terms` at ``x`` in model
            coordinates, if the caller has them.
    """
    xm = policy.to_model(x)
    if terms is None:
        terms = policy.field_terms(xm)
    # A policy need not use the V it carries (behavioural cloning keeps it unused).
    value, grad = (
        (terms.value, terms.grad) if terms.value is not None else policy.lyapunov.value_and_grad(xm)
    )
    f = terms.nominal if terms.nominal is not None else policy.nominal(xm)
    decay = policy.decay(value, xm)
    lhs = (grad * terms.field).sum(-1)
    scale = grad.norm(dim=-1) * f.norm(dim=-1) + decay
    return int((lhs > -decay + rtol * scale).sum())


@torch.no_grad()
def largest_safe_step(
    policy: Policy,
    x: torch.Tensor,
    *,
    upper: float,
    iterations: int = 60,
    terms: FieldTerms | None = None,
) -> float:
    r"""The largest Euler step h with :math:`V(x + h \pi(x)) \le V(x)` at every given state.

    Along a descent direction of a convex V, :math:`h \mapsto V(x + h \pi(x))` is convex and
    starts decreasing, so the steps that decrease V form an interval :math:`(0, h^*(x))`; the
    largest step safe at every state is :math:`\min_x h^*(x)`, found by halving, then bisection
    on one shared h. For a V that is not convex (a warped V, SDS-EF's) the safe steps
    of a state need not form an interval, and the answer is a heuristic: every given state is
    safe at the step returned, not necessarily at every shorter one.

    Arguments:
        policy: A stable policy, in the dtype of ``x``.
        x: States in user units, shape (B, n); the target itself is skipped.
        upper: The largest step tried, in seconds.
        iterations: Halvings of ``upper`` tried before giving up.
        terms: The policy's :meth:`~snds.policy.Policy.field_terms` at ``x`` in model
            coordinates, if the caller has them.

    Returns:
        The step in seconds, to a relative precision of 1e-7 (``upper`` if every state is
        safe at ``upper``; 0 if none is safe at ``upper`` / 2^iterations).
    """
    xm = policy.to_model(x)
    away = xm.norm(dim=-1) > 0
    xm = xm[away]
    if terms is None:
        value, velocity = policy.lyapunov(xm), policy.field(xm)
    else:
        value, velocity = terms.value[away], terms.field[away]
    # At tiny steps V's change falls below the rounding error of V itself (a Bregman
    # difference of terms of the size of g, which may be 1e3 and more), which may show as a
    # rise: seen at 5.5e-8 V near the target of a trained model. An overshooting step raises V
    # by a fraction of V itself, far more than this allowance, and the relative part moves
    # the bisection's answer by about 1e-7 of it.
    allowance = 1e-7 * value + 1e-12

    def safe(h: float, rows: torch.Tensor | slice = slice(None)) -> torch.Tensor:
        """Which of the states ``rows`` a step of h seconds keeps from raising V."""
        moved = xm[rows] + (h / policy.time) * velocity[rows]
        return policy.lyapunov(moved) <= value[rows] + allowance[rows]

    if safe(upper).all():
        return upper
    # Bracket by halving (a safe step is usually within a few octaves of ``upper``).
    high, unsafe = upper, ~safe(upper)
    for _ in range(iterations):
        low = 0.5 * high
        at_low = safe(low)
        if at_low.all():
            break
        high, unsafe = low, ~at_low
    else:
        return 0.0
    # Bisect the octave to a relative precision of 1e-7 on the states unsafe at ``high``
    # only: the others are safe on all of (0, high] when V is convex along the step. For a
    # V that is not, the answer is checked on every state, and the search goes on below it
    # until every state is safe there.
    rows = unsafe.nonzero()[:, 0]
    while True:
        while high - low > 1e-7 * low:
            middle = 0.5 * (low + high)
            low, high = (middle, high) if safe(middle, rows).all() else (low, middle)
        at_low = safe(low)
        if at_low.all():
            return low
        high, low, rows = low, 0.5 * low, (~at_low).nonzero()[:, 0]
        while not safe(low, rows).all():
            high, low = low, 0.5 * low
            if low < upper * 2.0**-iterations:
                return 0.0
