r"""Arb ball arithmetic (python-flint) for the re-check: a cell's proof, one cell at a time.

The last resort of :mod:`snds.certify.recheck` for the few cells that its NumPy Taylor models
(:mod:`snds.certify.reprove`) leave: interval jets of V and f in Arb's rigorous balls (its own
enclosures of exp, log, sin and cos), Taylor enclosures formed as ball polynomials, and splits.
Slow (milliseconds per cell in Python), loose on wide cells, independent of both other paths.
"""

from __future__ import annotations

import numpy as np

from snds.certify.model import PolicyModel
from snds.errors import CertificateError

__all__ = ["ArbModel", "Balls", "cell_box", "flint_module", "meet", "prove_cell", "prove_split"]


def flint_module():
    try:
        import flint
    except ImportError:  # pragma: no cover - the verify extra installs it
        raise CertificateError(
            "the re-check needs python-flint: pip install 'snds[verify]'"
        ) from None
    return flint


class Balls:
    """Jets of Arb balls: rows (1 x k arb_mat) of values, gradients and Hessians."""

    def __init__(self, flint, n: int) -> None:
        self.arb, self.mat, self.n = flint.arb, flint.arb_mat, n

    def matrix(self, array: np.ndarray):
        rows, cols = array.shape
        return self.mat(rows, cols, [float(v) for v in array.ravel()])

    def span(self, lo, hi):
        """The ball [lo, hi] of two arb numbers."""
        return lo + (hi - lo) * self.arb(0.5, 0.5)

    def variable(self, box: list, order: int) -> dict:
        n = self.n
        zero = self.mat(1, n)
        grads = []
        for i in range(n):
            row = self.mat(1, n)
            row[0, i] = 1
            grads.append(row)
        hess = [[self.mat(1, n) for _ in range(n)] for _ in range(n)] if order == 2 else None
        value = self.mat(1, n, list(box))
        del zero
        return {"v": value, "g": grads, "h": hess}

    def linear(self, jet: dict, weight, bias=None) -> dict:
        value = jet["v"] * weight
        if bias is not None:
            value = value + bias
        hess = None
        if jet["h"] is not None:
            hess = [[h * weight for h in row] for row in jet["h"]]
        return {"v": value, "g": [g * weight for g in jet["g"]], "h": hess}

    def add(self, a: dict, b: dict, sign: int = 1) -> dict:
        hess = None
        if a["h"] is not None and b["h"] is not None:
            hess = [[x + sign * y for x, y in zip(ra, rb)] for ra, rb in zip(a["h"], b["h"])]
        return {
            "v": a["v"] + sign * b["v"],
            "g": [x + sign * y for x, y in zip(a["g"], b["g"])],
            "h": hess,
        }

    def apply(self, jet: dict, fn) -> dict:  # noqa: ANN001
        k = jet["v"].ncols()
        n = self.n
        value = self.mat(1, k)
        grads = [self.mat(1, k) for _ in range(n)]
        hess = None if jet["h"] is None else [[self.mat(1, k) for _ in range(n)] for _ in range(n)]
        for t in range(k):
            s0, s1, s2 = fn(jet["v"][0, t])
            value[0, t] = s0
            g = [jet["g"][i][0, t] for i in range(n)]
            for i in range(n):
                grads[i][0, t] = s1 * g[i]
            if hess is not None:
                for i in range(n):
                    for j in range(n):
                        hess[i][j][0, t] = s1 * jet["h"][i][j][0, t] + s2 * g[i] * g[j]
        return {"v": value, "g": grads, "h": hess}

    def concat(self, jets: list[dict]) -> dict:
        def cat(rows: list):
            values = [row[0, t] for row in rows for t in range(row.ncols())]
            return self.mat(1, len(values), values)

        n = self.n
        hess = None
        if all(j["h"] is not None for j in jets):
            hess = [[cat([j["h"][a][b] for j in jets]) for b in range(n)] for a in range(n)]
        return {
            "v": cat([j["v"] for j in jets]),
            "g": [cat([j["g"][i] for j in jets]) for i in range(n)],
            "h": hess,
        }


class ArbModel:
    """The policy's networks in Arb (weights read once as exact balls)."""

    def __init__(self, flint, weights: PolicyModel) -> None:
        b = Balls(flint, weights.dim)
        self.b, self.w, self.arb = b, weights, flint.arb
        self.fourier = b.matrix(weights.fourier)
        self.layers = [(b.matrix(w), b.matrix(bias[None])) for w, bias in weights.layers]
        self.warp = [
            (b.matrix(o), b.matrix(p[None]), b.matrix(w), b.matrix(c[None]))
            for o, p, w, c in weights.warp
        ]
        self.skips = [(b.matrix(a), b.matrix(c[None])) for a, c in weights.icnn_skips]
        self.prev = [b.matrix(w) for w in weights.icnn_prev]
        self.out = (b.matrix(weights.icnn_out[0]), b.matrix(weights.icnn_out[1]))
        slope = weights.icnn_slope
        arb = flint.arb
        span = b.span

        def sig(u):
            return 1 / (1 + (-u).exp())

        def hull(fn, u, turns=()):
            # fn over the ball u from its values at u's ends and, where u meets a ball known
            # to hold a turning point of fn, fn over that ball.
            lo, hi = u.lower(), u.upper()
            parts = [fn(lo), fn(hi)] + [fn(t) for t in turns if t.upper() >= lo and t.lower() <= hi]
            return span(min(p.lower() for p in parts), max(p.upper() for p in parts))

        def leaky(u):
            value = hull(lambda v: slope * v + (1 - slope) * (1 + v.exp()).log(), u)
            first = hull(lambda v: slope + (1 - slope) * sig(v), u)
            second = hull(lambda v: (1 - slope) * sig(v) * (1 - sig(v)), u, (arb(0),))
            return value, first, second

        def silu_value(v):
            return v * sig(v)

        def silu_slope(v):
            return sig(v) * (1 + v * (1 - sig(v)))

        def silu_curve(v):
            return sig(v) * (1 - sig(v)) * (2 + v * (1 - 2 * sig(v)))

        # Balls that hold silu's minimum and silu''s extremes: the derivative changes sign
        # across each (checked here in balls), so a turning point lies inside.
        turn = arb(-1.2784645427610738, 1e-6)
        bends = (arb(2.3993572805154676, 1e-6), arb(-2.3993572805154676, 1e-6))
        assert silu_slope(turn.lower()) < 0 < silu_slope(turn.upper())
        assert all(silu_curve(t.lower()) * silu_curve(t.upper()) < 0 for t in bends)

        def silu(u):
            return hull(silu_value, u, (turn,)), hull(silu_slope, u, bends), arb(0)

        self.leaky, self.silu = leaky, silu
        zero = [arb(0)] * weights.dim
        self.net0 = self._net(zero)["v"]
        self.phi0 = self._flow(b.variable(zero, 1))["v"]
        at0 = self._icnn(b.variable(zero, 1))
        self.g0 = at0["v"]
        self.grad_g0 = b.mat(weights.dim, 1, [at0["g"][i][0, 0] for i in range(weights.dim)])

    def _net(self, box: list) -> dict:
        b = self.b
        x = b.variable(box, 1)
        angles = b.linear(x, self.fourier)
        sines = b.apply(angles, lambda u: (u.sin(), u.cos(), -u.sin()))
        cosines = b.apply(angles, lambda u: (u.cos(), -u.sin(), -u.cos()))
        h = b.concat([x, sines, cosines])
        for k, (weight, bias) in enumerate(self.layers):
            h = b.linear(h, weight, bias)
            if k + 1 < len(self.layers):
                h = b.apply(h, self.silu)
        return h

    def nominal(self, box: list) -> dict:
        net = self._net(box)
        return {"v": net["v"] - self.net0, "g": net["g"], "h": None}

    def _flow(self, x: dict) -> dict:
        b = self.b
        for omega, phases, weight, bias in self.warp:
            angles = b.linear(x, omega, phases)
            feats = b.apply(angles, lambda u: (u.cos(), -u.sin(), -u.cos()))
            x = b.add(x, b.linear(feats, weight, bias))
        return x

    def _icnn(self, z: dict) -> dict:
        b = self.b
        h = None
        for k, (skip, bias) in enumerate(self.skips):
            u = b.linear(z, skip, bias)
            if h is not None:
                u = b.add(u, b.linear(h, self.prev[k - 1]))
            h = b.apply(u, self.leaky)
        return b.add(b.linear(h, self.out[0]), b.linear(z, self.out[1]))

    def lyapunov(self, box: list, order: int) -> dict:
        """V's jet (values 1 x 1) over a box of balls."""
        b, n, d = self.b, self.w.dim, self.w.quadratic
        z = self._flow(b.variable(box, order))
        z = {"v": z["v"] - self.phi0, "g": z["g"], "h": z["h"]}
        g = self._icnn(z)
        tangent = b.linear(z, self.grad_g0)
        out = b.add(g, tangent, -1)
        out["v"] = out["v"] - self.g0
        zs = [z["v"][0, i] for i in range(n)]
        gz = [[z["g"][a][0, i] for i in range(n)] for a in range(n)]
        value = out["v"][0, 0] + d * sum(v * v for v in zs)
        grad = [
            out["g"][a][0, 0] + 2 * d * sum(zs[i] * gz[a][i] for i in range(n)) for a in range(n)
        ]
        hess = None
        if order == 2:
            hess = [
                [
                    out["h"][a][c][0, 0]
                    + 2
                    * d
                    * sum(gz[a][i] * gz[c][i] + zs[i] * z["h"][a][c][0, i] for i in range(n))
                    for c in range(n)
                ]
                for a in range(n)
            ]
        return {"v": value, "g": grad, "h": hess}

    def rate(self, box: list):
        """The decay rate a / V over a box of balls (a ball)."""
        w, arb = self.w, self.arb
        radius = sum(x * x for x in box).sqrt()

        def pos(v):
            lo, hi = v.lower(), v.upper()
            if lo >= 0:
                return v
            if hi <= 0:
                return arb(0)
            return self.b.span(arb(0), hi)

        rate = w.rho + w.rho_far * pos(radius - 1) + w.rho_near * pos(1 - radius / w.near_radius)
        if len(w.anchors) and w.drop > 0:
            distances = [
                sum((x - float(a)) ** 2 for x, a in zip(box, anchor)) for anchor in w.anchors
            ]
            low = min(d.lower() for d in distances)
            high = min(d.upper() for d in distances)
            span = self.b.span(low, high)
            rate = rate - w.drop * (-span / (2 * arb(w.data_radius) ** 2)).exp()
        return rate


def cell_box(b: Balls, cell: list[int], half: float) -> tuple[list, list, list]:
    arb = b.arb
    size = arb(2 * half) / arb(2) ** int(cell[0])
    lows = [-arb(half) + int(i) * size for i in cell[1:]]
    highs = [lo + size for lo in lows]
    return [b.span(lo, hi) for lo, hi in zip(lows, highs)], lows, highs


def meet(b: Balls, x, y):
    """A ball holding the intersection of two balls that both hold the true value."""
    return b.span(max(x.lower(), y.lower()), min(x.upper(), y.upper()))


def prove_cell(model: ArbModel, cell: list[int], half: float, step: float, eta: float) -> tuple:
    """(proven, a at the centre, |pi| at the centre) for one cell, in balls."""
    b, arb, n = model.b, model.arb, model.w.dim
    box, lows, highs = cell_box(b, cell, half)
    center = [(lo + hi) / 2 for lo, hi in zip(lows, highs)]
    offsets = [x - c for x, c in zip(box, center)]
    at_c = model.lyapunov(center, 1)
    over = model.lyapunov(box, 2)
    h = over["h"]
    value = at_c["v"] + sum(g * u for g, u in zip(at_c["g"], offsets))
    value = value + sum(h[i][j] * offsets[i] * offsets[j] for i in range(n) for j in range(n)) / 2
    v_lo = max(value.lower(), arb(0))
    v_hi = value.upper()
    grad = [
        meet(b, at_c["g"][j] + sum(h[i][j] * offsets[i] for i in range(n)), over["g"][j])
        for j in range(n)
    ]
    grad_lo = sum(g.abs_lower() ** 2 for g in grad).sqrt().lower()
    grad_hi = sum(g.abs_upper() ** 2 for g in grad).sqrt().upper()
    rate = model.rate(box)
    a_lo = v_lo * max(rate.lower(), arb(0))
    a_hi = v_hi * rate.upper()
    f_c = model.nominal(center)
    f_x = model.nominal(box)
    f = [
        meet(
            b,
            f_c["v"][0, k] + sum(f_x["g"][i][0, k] * offsets[i] for i in range(n)),
            f_x["v"][0, k],
        )
        for k in range(n)
    ]
    # At the centre: a and pi themselves, to test the numbers the certificate records.
    rate_c = model.rate(center)
    a_c = at_c["v"] * rate_c
    g_c = at_c["g"]
    fc = [f_c["v"][0, k] for k in range(n)]
    norm2 = sum(g * g for g in g_c)
    excess = sum(g * x for g, x in zip(g_c, fc)) + a_c
    pi_c = [x - g * (excess if excess.lower() > 0 else arb(0)) / norm2 for x, g in zip(fc, g_c)]
    speed_c = sum(p * p for p in pi_c).sqrt()
    if not grad_lo > 0:
        return False, a_c, speed_c
    speed = (sum(x.abs_upper() ** 2 for x in f) + (a_hi / grad_lo) ** 2).sqrt().upper()
    reach = ((1 + arb(eta)) * step * speed).upper()
    grown = [b.span(lo - reach, hi + reach) for lo, hi in zip(lows, highs)]
    hess = model.lyapunov(grown, 2)["h"]
    top = max(
        (hess[i][i] + sum(hess[i][j].abs_upper() for j in range(n) if j != i)).upper()
        for i in range(n)
    )
    curvature = max(top, arb(0))
    decrease = (
        step * a_lo
        - step * eta * grad_hi * speed
        - curvature * (1 + arb(eta)) ** 2 * arb(step) ** 2 * speed**2 / 2
    )
    return bool(decrease > 0), a_c, speed_c


def prove_split(
    model: ArbModel, cell: list[int], half: float, step: float, eta: float, *, depth: int
) -> bool:
    """Whether the re-check proves every child of a cell, splitting ``depth`` times more
    where its own bounds are looser than the search's (a proof of the parts is one of the
    whole)."""
    n = model.w.dim
    for corner in range(2**n):
        child = [cell[0] + 1] + [2 * i + ((corner >> k) & 1) for k, i in enumerate(cell[1:])]
        if prove_cell(model, child, half, step, eta)[0]:
            continue
        if depth <= 1 or not prove_split(model, child, half, step, eta, depth=depth - 1):
            return False
    return True
