r"""Sound per-cell bounds that prove one Euler step decreases V.

For the stable policy :math:`\pi` (ReLU rectifier), :math:`\nabla V^\top \pi \le -a` holds
exactly. A deployed step moves a state by some :math:`\Delta` with
:math:`|\Delta - h \pi(x)| \le \eta\, h |\pi(x)|` (:math:`\eta` covers the rounding of the
controller's arithmetic). Taylor's theorem with the Hessian on the segment gives

.. math:: V(x + \Delta) - V(x) \le h \nabla V^\top \pi + h\, \eta\, |\nabla V(x)|\, |\pi(x)|
          + \tfrac12 M (1 + \eta)^2 h^2 |\pi(x)|^2,

with M an upper bound of the largest eigenvalue of :math:`\nabla^2 V` on the segment. Over a
cell X, with :math:`a \ge a_-`, :math:`|\pi| \le P`, :math:`|\nabla V| \le G`, and M over X
grown by :math:`(1 + \eta) h P` on every side (the segments' region), the step decreases V
by at least

.. math:: h a_- - h \eta G P - \tfrac12 M (1 + \eta)^2 h^2 P^2,

and the cell is proven if this is positive. P comes from :math:`|\pi|^2 \le |f|^2 +
(a / |\nabla V|)^2` (the projection removes a part of f along :math:`\nabla V` and adds
:math:`-a \nabla V / |\nabla V|^2`), so none of it needs the projection's own interval.
Near the target :math:`a \approx \rho V` is quadratic and :math:`|\pi|` linear, so the bound
tends to a constant and cells of a size proportional to their distance prove.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from snds.certify import interval as ia
from snds.certify.model import PolicyModel, f_quadratic, rate_bounds, v_forms

__all__ = ["CellBounds", "cell_bounds", "gershgorin"]


@dataclass(frozen=True)
class CellBounds:
    """Bounds over C cells, each (C,); ``decrease`` is a lower bound of V(x) - V(x + step).

    Attributes:
        a_lo: Lower bound of the descent -grad V . pi = max(a, -grad V . f) (the ReLU
            projection leaves f alone where it already descends faster than a).
        speed: P, upper bound of |pi(x)|.
        grad_hi: G, upper bound of |grad V(x)|.
        quadratic: Q, upper bound of Delta^T H Delta / h^2 over the steps Delta and the
            Hessians H on their segments.
        decrease: Lower bound of the guaranteed decrease (proven where > 0).
        largest_step: A step (model time) up to which the same bounds prove every shorter
            step too: min(h, 2 (a_lo - eta G P) / Q) (0 where they prove none).
    """

    a_lo: np.ndarray
    speed: np.ndarray
    grad_hi: np.ndarray
    quadratic: np.ndarray
    decrease: np.ndarray
    largest_step: np.ndarray

    @property
    def proven(self) -> np.ndarray:
        """Cells where every step decreases V."""
        return self.decrease > 0


def gershgorin(hess: ia.Iv) -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper bounds (C,) of the eigenvalues of symmetric interval matrices
    (C, n, n, 1), by Gershgorin's discs."""
    mag = hess.mag[..., 0]
    n = mag.shape[-1]
    diag = np.arange(n)
    off = ia.up(mag.sum(-1) - mag[:, diag, diag], n + 2)
    top = (hess.hi[..., 0][:, diag, diag] + off).max(-1)
    bottom = (hess.lo[..., 0][:, diag, diag] - off).min(-1)
    return bottom - np.abs(bottom) * 1e-15, top + np.abs(top) * 1e-15


def _norm_hi(x: np.ndarray) -> np.ndarray:
    return ia.up(np.sqrt(ia.up((x * x).sum(-1), x.shape[-1] + 2)), 2)


def _norm_lo(x: np.ndarray) -> np.ndarray:
    return np.sqrt((x * x).sum(-1) * (1 - 8 * x.shape[-1] * ia.UNIT)) * (1 - 4 * ia.UNIT)


def _mean_value(center: ia.Iv, jacobian: ia.Iv, half: np.ndarray, direct: ia.Iv) -> ia.Iv:
    """Enclosure (C, k) of a function over cells from its value at the centre (C, k) plus the
    interval Jacobian (C, n, k) times the half-widths, intersected with the direct one."""
    spread = ia.up((jacobian.mag * half[:, :, None]).sum(1), half.shape[1] + 2)
    lo = np.maximum(center.lo - spread, direct.lo)
    hi = np.minimum(center.hi + spread, direct.hi)
    return ia.from_bounds(lo, np.maximum(hi, lo))


def _meet(a: ia.Iv, b: ia.Iv) -> ia.Iv:
    """An interval holding the intersection of two that both hold the true values."""
    lo, hi = np.maximum(a.lo, b.lo), np.minimum(a.hi, b.hi)
    return ia.from_bounds(lo, np.maximum(lo, hi))


def _projection(f: ia.Iv, grad: ia.Iv, a_lo: np.ndarray, a_hi: np.ndarray) -> ia.Iv:
    """pi = f - grad V relu(grad V . f + a) / |grad V|^2 in intervals, (C, n)."""
    excess = (grad * f).sum(-1) + ia.from_bounds(a_lo, a_hi)
    relu = ia.from_bounds(np.maximum(excess.lo, 0.0), np.maximum(excess.hi, 0.0))
    norm2 = grad.square().sum(-1)
    low = np.maximum(norm2.lo, 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        inverse = ia.from_bounds(
            (1.0 / norm2.hi) * (1 - 4 * ia.UNIT),
            np.where(low > 0, (1.0 / low) * (1 + 4 * ia.UNIT), np.inf),
        )
    return f - grad * (relu * inverse)[:, None]


def cell_bounds(
    model: PolicyModel, lo: np.ndarray, hi: np.ndarray, *, step: float, eta: float
) -> CellBounds:
    """Bounds of the decrease of V by one step over cells [lo, hi] (C, n), model coordinates.

    Arguments:
        model: The policy.
        lo: Lower corners (C, n).
        hi: Upper corners (C, n).
        step: h, the step in model time (seconds / :attr:`PolicyModel.time`).
        eta: Relative error allowed to a deployed step (see the module's docstring).
    """
    with np.errstate(all="ignore"):
        return _cell_bounds(model, lo, hi, step=step, eta=eta)


def _cell_bounds(
    model: PolicyModel, lo: np.ndarray, hi: np.ndarray, *, step: float, eta: float
) -> CellBounds:
    center = 0.5 * lo + 0.5 * hi
    half = ia.up(np.maximum(hi - center, center - lo), 2)
    n = lo.shape[1]
    forms = v_forms(model, center, half, order=1)
    v_lo = np.maximum(forms.value.lo[:, 0], 0.0)
    v_hi = forms.value.hi[:, 0]
    grad = forms.grad.interval()[..., 0]
    grad_lo, grad_hi = _norm_lo(grad.mig), _norm_hi(grad.mag)
    rate_lo, rate_hi = rate_bounds(model, lo, hi)
    a_lo = np.maximum(v_lo * rate_lo * (1 - 4 * ia.UNIT), 0.0)
    a_hi = ia.up(v_hi * np.maximum(rate_hi, 0.0), 2)
    f = f_quadratic(model, center, half).interval()
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        ratio = np.where(grad_lo > 0, ia.up(a_hi / grad_lo, 2), np.inf)
        speed = ia.up(np.sqrt(ia.up((f.mag**2).sum(-1) + ratio**2, n + 3)), 2)
        reach = ia.up((1 + eta) * step * speed, 3)
    finite = np.isfinite(reach) & (grad_lo > 0)
    curvature = np.full(len(lo), np.inf)
    quadratic = np.full(len(lo), np.inf)
    if finite.any():
        c, w, r = center[finite], half[finite], reach[finite, None]
        hess = v_forms(model, c, ia.up(w + r, 1), order=2).hess.interval()[..., 0]
        top = gershgorin(ia.Iv(hess.m[..., None], hess.r[..., None]))[1]
        curvature[finite] = np.maximum(top, 0.0)
        # Along the step itself: pi^T H pi over the cell's pi and the segments' H, from the
        # projection's own formula in intervals (tighter than the top eigenvalue |pi|^2 where
        # pi is not along the top eigenvector).
        velocity = _projection(f[finite], grad[finite], a_lo[finite], a_hi[finite])
        directional = (hess * velocity[:, :, None] * velocity[:, None, :]).sum(-1).sum(-1).hi
        rows = ia.up(hess.mag.sum(-1).max(-1), n + 2)
        p2 = ia.up(speed[finite] ** 2, 1)
        best = np.minimum(directional, curvature[finite] * p2)
        quadratic[finite] = ia.up(np.maximum(best, 0.0) + (2 * eta + eta**2) * rows * p2, 6)
    with np.errstate(invalid="ignore", over="ignore"):
        # -grad V . pi = max(a, -grad V . f) exactly for the ReLU projection: where f already
        # descends faster than a, pi = f and the step gains that much more.
        descent = np.maximum(a_lo, -(grad * f).sum(-1).hi)
        gain = step * descent * (1 - 4 * ia.UNIT)
        loss = ia.up(step * eta * grad_hi * speed + 0.5 * step**2 * quadratic, 8)
        decrease = np.where(np.isfinite(loss), gain - loss, -np.inf)
        # The bounds hold over the segments of every step up to h, and the condition
        # h a_lo > h eta G P + h^2 Q / 2 only gets easier as h shrinks.
        spare = descent * (1 - 4 * ia.UNIT) - ia.up(eta * grad_hi * speed, 3)
        largest = np.where(
            (spare > 0) & np.isfinite(quadratic),
            np.minimum(step, 2.0 * spare / quadratic * (1 - 1e-12)),
            0.0,
        )
        largest = np.where(np.isfinite(largest) & (largest > 0), largest, 0.0)
    if not model.projected:
        # pi = f: grad V . pi <= -a does not hold, so nothing here proves a decrease.
        decrease = np.full(len(lo), -np.inf)
        largest = np.zeros(len(lo))
    return CellBounds(descent, speed, grad_hi, quadratic, decrease, largest)
