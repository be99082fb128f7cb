# ruff: noqa: E501  (the C templates keep one C statement per line)
r"""The C of a policy's V and decay rate, for :mod:`snds.export.c_source`: the warp's additive
coupling layers and their Jacobian-transpose product, the ICNN in its Bregman form with its
analytic gradient, and the decay rate a(x) / V with the data kernel on the anchors. Each
function takes the :class:`~snds.export.c_source.Generator` and returns C with its placeholders
(REAL, MATH, LIT, SFX); :func:`dense` is the matrix product all of them use.
"""

from __future__ import annotations

__all__ = ["convex", "decay_rate", "dense", "warp"]


def dense(x: str, n_in: int, weights: str, bias: str | None, n_out: int, y: str) -> str:
    """C for y = x W^T (+ b), W^T stored (in, out): the inner loop runs along a row, which
    the compiler vectorises, and each output sums its terms in input order."""
    bias_line = f"    for (j = 0; j < {n_out}; ++j) {y}[j] += {bias}_SFX[j];\n" if bias else ""
    return (
        f"    for (j = 0; j < {n_out}; ++j) {y}[j] = LIT(0.0);\n"
        f"    for (i = 0; i < {n_in}; ++i) {{\n"
        f"        const REAL xi = {x}[i];\n"
        f"        const REAL *row = {weights}_SFX + (size_t)i * {n_out};\n"
        f"        for (j = 0; j < {n_out}; ++j) {y}[j] += xi * row[j];\n"
        f"    }}\n{bias_line}"
    )


def warp(generator) -> str:
    """``warp_SFX`` (e = phi(z) - phi(0)) and ``warp_vjp_SFX`` (J^T g)."""
    n = generator.n
    temporary = f", t[{n}]" if generator.warp else ""
    code = [
        f"static void warp_SFX(const REAL *z, REAL *e, REAL *sines) {{\n"
        f"    REAL y[{n}]{temporary};\n    int i, at_target = 1;\n"
        + ("    int j;\n" if generator.warp else "    (void)sines;\n")
        + f"    for (i = 0; i < {n}; ++i) {{ y[i] = z[i]; if (z[i] != LIT(0.0)) at_target = 0; }}\n"
    ]
    offset = 0
    for index, m in enumerate(generator.warp):
        code.append(
            f"    {{\n        REAL cosines[{m}];\n"
            f"        for (j = 0; j < {m}; ++j) {{\n            REAL angle = LIT(0.0);\n"
            f"            for (i = 0; i < {n}; ++i) angle += y[i] * WARP_F{index}_SFX[i * {m} + j];\n"
            f"            angle += WARP_P{index}_SFX[j];\n"
            f"            cosines[j] = MATH(cos)(angle);\n            sines[{offset} + j] = MATH(sin)(angle);\n        }}\n"
            + dense("cosines", m, f"WARP_W{index}", None, n, "t")
            + f"        for (i = 0; i < {n}; ++i) y[i] = y[i] + (WARP_B{index}_SFX[i] + t[i]);\n    }}\n"
        )
        offset += m
    at = "WARP_AT_TARGET_SFX[i]" if generator.warp else "LIT(0.0)"
    code.append(f"    for (i = 0; i < {n}; ++i) e[i] = at_target ? LIT(0.0) : y[i] - {at};\n}}\n")
    vjp = [
        "static void warp_vjp_SFX(const REAL *sines, REAL *g) {\n    int i, j;\n"
        "    (void)sines; (void)g; (void)i; (void)j;\n"
    ]
    offset = sum(generator.warp)
    for index in range(len(generator.warp) - 1, -1, -1):
        m = generator.warp[index]
        offset -= m
        vjp.append(
            f"    {{\n        REAL d[{m}], back[{n}];\n"
            + dense("g", n, f"WARP_WT{index}", None, m, "d")
            + f"        for (j = 0; j < {m}; ++j) d[j] = sines[{offset} + j] * d[j];\n"
            + dense("d", m, f"WARP_FT{index}", None, n, "back")
            + f"        for (i = 0; i < {n}; ++i) g[i] = g[i] - back[i];\n    }}\n"
        )
    vjp.append("}\n")
    return "".join(code) + "".join(vjp)


def convex(generator) -> str:
    """``convex_SFX``: V_c and its gradient at e."""
    n, hidden = generator.n, generator.hidden
    depth = len(hidden)
    if generator.icnn_slope is None:
        act = (
            "s[j] = (u > LIT(20.0) ? u : MATH(log1p)(MATH(exp)(u))); "
            "ds[j] = LIT(1.0) / (LIT(1.0) + MATH(exp)(-u));"
        )
    else:
        a = generator.icnn_slope
        act = (
            f"s[j] = LIT({a}) * u + LIT({1 - a}) * (u > LIT(20.0) ? u : MATH(log1p)(MATH(exp)(u))); "
            f"ds[j] = LIT({a}) + LIT({1 - a}) * (LIT(1.0) / (LIT(1.0) + MATH(exp)(-u)));"
        )
    code = [
        f"static void convex_SFX(const REAL *x, REAL *value, REAL *grad) {{\n"
        f"    REAL slopes[{sum(hidden)}], z[{generator.width}], u_[{generator.width}], e_[{generator.width}], d_[{generator.width}], g[{n}];\n"
        f"    REAL bregman, inner, v, quad;\n    int i, j;\n"
    ]
    offset = 0
    for k, h in enumerate(hidden):
        code.append("    {\n" + dense("x", n, f"SKIP_T{k}", f"SKIP_B{k}", h, "u_"))
        if k > 0:
            code.append(dense("z", hidden[k - 1], f"PREV_T{k}", None, h, "d_"))
            code.append(f"    for (j = 0; j < {h}; ++j) u_[j] = u_[j] + d_[j];\n")
        code.append(
            f"    {{ REAL *s = z, *ds = slopes + {offset};\n"
            f"      for (j = 0; j < {h}; ++j) {{ const REAL u = u_[j]; {act} }} }}\n    }}\n"
        )
        offset += h
    last = hidden[-1]
    code.append(
        f"    v = LIT(0.0);\n    for (j = 0; j < {last}; ++j) v += z[j] * ICNN_OUT_SFX[j];\n"
        f"    inner = LIT(0.0);\n    for (i = 0; i < {n}; ++i) inner += x[i] * ICNN_LINEAR_SFX[i];\n"
        f"    v = v + inner;\n"
        f"    for (i = 0; i < {n}; ++i) g[i] = ICNN_LINEAR_SFX[i];\n"
        f"    for (j = 0; j < {last}; ++j) e_[j] = ICNN_OUT_SFX[j];\n"
    )
    for k in range(depth - 1, -1, -1):
        h = hidden[k]
        offset -= h
        code.append(
            f"    {{\n        REAL back[{n}];\n"
            f"        for (j = 0; j < {h}; ++j) d_[j] = e_[j] * slopes[{offset} + j];\n"
            + dense("d_", h, f"SKIP{k}", None, n, "back")
            + f"        for (i = 0; i < {n}; ++i) g[i] = back[i] + g[i];\n"
        )
        if k > 0:
            code.append(dense("d_", h, f"PREV{k}", None, hidden[k - 1], "e_"))
        code.append("    }\n")
    d = generator.quadratic
    code.append(
        f"    inner = LIT(0.0);\n    for (i = 0; i < {n}; ++i) inner += x[i] * GRAD_G_AT_TARGET_SFX[i];\n"
        f"    bregman = v - G_AT_TARGET_SFX[0] - inner;\n"
        f"    if (bregman < LIT(0.0)) bregman = LIT(0.0);\n"
        f"    quad = LIT(0.0);\n    for (i = 0; i < {n}; ++i) quad += x[i] * x[i];\n"
        f"    v = bregman + LIT({d}) * quad;\n"
        f"    for (i = 0; i < {n}; ++i) grad[i] = (g[i] - GRAD_G_AT_TARGET_SFX[i]) + LIT({2 * d}) * x[i];\n"
        f"    inner = LIT(0.0);\n    for (i = 0; i < {n}; ++i) inner += grad[i] * x[i];\n"
        f"    if (inner < v) v = inner;\n    *value = v > LIT(0.0) ? v : LIT(0.0);\n}}\n"
    )
    return "".join(code)


def decay_rate(generator) -> str:
    """``rate_SFX``: a(x) / V per unit of model time."""
    config = generator.policy.config
    n = generator.n
    code = [
        f"static REAL rate_SFX(const REAL *z) {{\n    REAL radius = LIT(0.0), rate, excess;\n    int i;\n"
        f"    for (i = 0; i < {n}; ++i) radius += z[i] * z[i];\n    radius = MATH(sqrt)(radius);\n"
        f"    excess = radius - LIT(1.0);\n"
        f"    rate = LIT({config.decay_rate}) + LIT({config.decay_far}) * (excess > LIT(0.0) ? excess : LIT(0.0));\n"
    ]
    if generator.anchors:
        code.append(
            f"    {{\n        REAL closest = LIT(0.0), square = LIT(0.0), nearest;\n        int a;\n"
            f"        for (a = 0; a < {generator.anchors}; ++a) {{\n            REAL dot = LIT(0.0), d;\n"
            f"            for (i = 0; i < {n}; ++i) dot += z[i] * ANCHORS_SFX[a * {n} + i];\n"
            f"            d = ANCHORS_SQ_SFX[a] + LIT(-2.0) * dot;\n"
            f"            if (a == 0 || d < closest) closest = d;\n        }}\n"
            f"        for (i = 0; i < {n}; ++i) square += z[i] * z[i];\n"
            f"        nearest = closest + square;\n        if (nearest < LIT(0.0)) nearest = LIT(0.0);\n"
            f"        rate = rate - LIT({config.data_rate_drop}) * MATH(exp)(-nearest / LIT({2.0 * config.data_radius**2}));\n    }}\n"
        )
    if config.decay_near:
        code.append(
            f"    excess = LIT(1.0) - radius / LIT({config.near_radius});\n"
            f"    rate = rate + LIT({config.decay_near}) * (excess > LIT(0.0) ? excess : LIT(0.0));\n"
        )
    code.append("    return rate;\n}\n")
    return "".join(code)
