# ruff: noqa: E501  (the C templates keep one C statement per line)
r"""The C99 source of a policy (:mod:`snds.c_export` writes it): one generator per model.

Every function is written once with placeholders (``REAL``, ``MATH(name)``, ``LIT(number)``,
``SFX``) and filled in for each :class:`CVariant` (double, float). The arithmetic follows the
library's operation by operation (the same sums in the same order where the library's order
is fixed, its constants computed as it computes them), so the double version agrees with the
library in float64 to rounding: :mod:`snds.c_check` measures it.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

import numpy as np
import torch

from snds.errors import SNDSError
from snds.nn.lyapunov import WarpedLyapunov
from snds.nn.mlp import FourierFeatures
from snds.policy import StablePolicy
from snds.se3 import PosePolicy

__all__ = ["VARIANTS", "CExportError", "CVariant", "Generator"]

# Activations of the nominal network, as C expressions of u (REAL, MATH and LIT filled in).
_ACTIVATIONS = {
    "relu": "(u > LIT(0.0) ? u : LIT(0.0))",
    "leaky_relu": "(u > LIT(0.0) ? u : LIT(0.01) * u)",
    "tanh": "MATH(tanh)(u)",
    "silu": "u / (LIT(1.0) + MATH(exp)(-u))",
    "softplus": "(u > LIT(20.0) ? u : MATH(log1p)(MATH(exp)(u)))",
    "gelu": "LIT(0.5) * u * (LIT(1.0) + MATH(erf)(u * LIT(0.7071067811865476)))",
}
# Below this angle roma's sinc and inv_sinc take their Taylor series: 2 eps^(1/6).
_SINC_THRESHOLD = {
    np.float64: 2.0 * np.finfo(np.float64).eps ** (1 / 6),
    np.float32: 2.0 * float(np.finfo(np.float32).eps) ** (1 / 6),
}


class CExportError(SNDSError):
    """A policy the C export cannot write (a method or a layer it does not have, a bad
    option)."""


@dataclass(frozen=True)
class CVariant:
    """One precision of the generated code.

    Attributes:
        real: The C type.
        suffix: Appended to the public functions' names ("" for double).
        math: Appended to the <math.h> functions' names.
        literal: Appended to number literals.
        numpy: The NumPy type of its numbers.
    """

    real: str
    suffix: str
    math: str
    literal: str
    numpy: type

    def number(self, value: float) -> str:
        """A C literal that is ``value`` rounded once to this precision."""
        value = self.numpy(value)
        if not np.isfinite(value):
            raise CExportError(f"the policy holds a non-finite number ({value})")
        # repr of a NumPy scalar is the shortest string that reads back to it.
        text = repr(float(value)) if self.numpy is np.float64 else str(value)
        if "e" not in text and "." not in text:
            text += ".0"
        return text + self.literal

    def fill(self, code: str) -> str:
        """``code`` with REAL, MATH(name), LIT(number) and SFX resolved."""
        code = re.sub(r"MATH\((\w+)\)", lambda m: m.group(1) + self.math, code)
        code = re.sub(r"LIT\(([^()]*)\)", lambda m: self.number(float(m.group(1))), code)
        return code.replace("REAL", self.real).replace("SFX", self.suffix[1:] or "d")


#: The two precisions: ``double`` (no suffix) and ``float`` (``_f``).
VARIANTS = (
    CVariant("double", "", "", "", np.float64),
    CVariant("float", "_f", "f", "f", np.float32),
)


def _dense(x: str, n_in: int, weights: str, bias: str | None, n_out: int, y: str) -> str:
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


class Generator:
    """The C files of one policy (float64, eval mode; see :func:`snds.c_export.export_c`).

    Arguments:
        policy: A float64 copy of an SNDS policy (positions, poses or a phase).
        prefix: Prefix of the public names.
    """

    def __init__(
        self, policy: StablePolicy, *, prefix: str, starts: np.ndarray | None = None
    ) -> None:
        self.policy = policy
        self.starts = None if starts is None else np.asarray(starts, dtype=np.float64)
        self.prefix = prefix
        self.pose = isinstance(policy, PosePolicy)
        space = policy.space
        self.n, self.states, self.velocities = policy.dim, space.dim, space.tangent_dim
        self.position_dim = space.position_dim
        self.arrays: dict[str, np.ndarray] = {}
        self.width = self.n
        with torch.no_grad():
            self._collect()

    def add(self, name: str, value) -> str:
        """Registers a constant array (any shape, stored flat in C order)."""
        if isinstance(value, torch.Tensor):
            value = value.detach().double().numpy()
        self.arrays[name] = np.ascontiguousarray(np.asarray(value, dtype=np.float64)).ravel()
        return name

    def _collect(self) -> None:
        p, n = self.policy, self.n
        zero = torch.zeros(1, n, dtype=torch.float64)
        self.add("CENTER", p.center)
        if self.starts is not None:
            self.add("START_STATES", self.starts)
        if self.pose:
            self.add("TARGET_POSITION", p.target_position)
            self.add("TARGET_ORIENTATION", p.target_orientation)
            self.add("SCALES", p.scales)
        # The nominal network, f(0) stored.
        layers = list(p.nominal_net)
        self.fourier = 0
        if isinstance(layers[0], FourierFeatures):
            self.fourier = layers[0].frequencies.shape[1]
            self.add("FOURIER", layers[0].frequencies)
            layers = layers[1:]
        self.linears = []
        for index, layer in enumerate(layers):
            if isinstance(layer, torch.nn.Linear):
                self.add(f"NOMINAL_W{index}", layer.weight.T)
                self.add(f"NOMINAL_B{index}", layer.bias)
                self.linears.append(
                    (
                        f"NOMINAL_W{index}",
                        f"NOMINAL_B{index}",
                        layer.in_features,
                        layer.out_features,
                    )
                )
                self.width = max(self.width, layer.in_features, layer.out_features)
        self.add("NOMINAL_AT_TARGET", p.nominal_net(zero)[0])
        # V: the warp, phi(0) stored; the ICNN, g(0) and grad g(0) stored.
        lyapunov = p.lyapunov
        convex, warp = (
            (lyapunov.convex, lyapunov.warp)
            if isinstance(lyapunov, WarpedLyapunov)
            else (lyapunov, None)
        )
        self.warp = []
        if warp is not None:
            for index, layer in enumerate(warp.layers):
                weight = layer.weight * layer.scaled_columns
                self.add(f"WARP_F{index}", layer.frequencies)  # (n, m)
                self.add(f"WARP_FT{index}", layer.frequencies.T)
                self.add(f"WARP_P{index}", layer.phases)
                self.add(f"WARP_W{index}", weight)  # (m, n)
                self.add(f"WARP_WT{index}", weight.T)
                self.add(f"WARP_B{index}", layer.bias * layer.columns)
                self.warp.append(layer.frequencies.shape[1])
            self.add("WARP_AT_TARGET", warp(zero)[0])
        icnn = convex.icnn
        weights = icnn.weights()
        self.hidden = []
        for k, skip in enumerate(icnn.skips):
            self.add(f"SKIP_T{k}", skip.weight.T)  # (n, h)
            self.add(f"SKIP{k}", skip.weight)  # (h, n)
            self.add(f"SKIP_B{k}", skip.bias)
            if k > 0:
                self.add(f"PREV_T{k}", weights[k - 1].T)  # (h_{k-1}, h_k)
                self.add(f"PREV{k}", weights[k - 1])  # (h_k, h_{k-1})
            self.hidden.append(skip.out_features)
            self.width = max(self.width, skip.out_features)
        self.add("ICNN_OUT", torch.nn.functional.softplus(icnn.raw_out))
        self.add("ICNN_LINEAR", icnn.linear_out)
        g0, grad0 = icnn.value_and_grad(zero)
        self.add("G_AT_TARGET", g0)
        self.add("GRAD_G_AT_TARGET", grad0[0])
        self.icnn_slope = 0.1 if icnn.activation == "smooth_leaky" else None
        self.quadratic = float(convex.quadratic)
        self.anchors = 0 if p.anchors is None else len(p.anchors)
        if self.anchors:
            self.add("ANCHORS", p.anchors)
            self.add("ANCHORS_SQ", (p.anchors * p.anchors).sum(-1))

    # --- the code -------------------------------------------------------------------------

    def _constants(self, variant: CVariant) -> str:
        lines = []
        for name, values in self.arrays.items():
            numbers = [variant.number(v) for v in values]
            rows = [", ".join(numbers[i : i + 6]) for i in range(0, len(numbers), 6)]
            lines.append(
                f"static const {variant.real} {name}_{variant.suffix[1:] or 'd'}"
                f"[{len(numbers)}] = {{\n    " + ",\n    ".join(rows) + "\n};"
            )
        return "\n".join(lines)

    def _chart(self) -> str:
        n = self.n
        if not self.pose:
            return (
                "static void chart_SFX(const REAL *x, REAL *z) {\n    int i;\n"
                f"    for (i = 0; i < {n}; ++i) z[i] = (x[i] - CENTER_SFX[i]) / LIT({self.policy.length});\n"
                "}\n"
            )
        return f"""static void chart_SFX(const REAL *x, REAL *z) {{
    /* The rotation vector log(q conj(q*)) (roma's quat_product and unitquat_to_rotvec). */
    const REAL *q = x + 3;
    const REAL c[4] = {{-TARGET_ORIENTATION_SFX[0], -TARGET_ORIENTATION_SFX[1],
                        -TARGET_ORIENTATION_SFX[2], TARGET_ORIENTATION_SFX[3]}};
    REAL r[4], y[6], sign, norm, half, scale;
    int i;
    r[0] = q[3] * c[0] + c[3] * q[0] + (q[1] * c[2] - q[2] * c[1]);
    r[1] = q[3] * c[1] + c[3] * q[1] + (q[2] * c[0] - q[0] * c[2]);
    r[2] = q[3] * c[2] + c[3] * q[2] + (q[0] * c[1] - q[1] * c[0]);
    r[3] = q[3] * c[3] - (q[0] * c[0] + q[1] * c[1] + q[2] * c[2]);
    sign = r[3] > LIT(0.0) ? LIT(1.0) : LIT(-1.0);
    for (i = 0; i < 4; ++i) r[i] = r[i] * sign;
    norm = MATH(sqrt)(r[0] * r[0] + r[1] * r[1] + r[2] * r[2]);
    half = MATH(atan2)(norm, r[3]);
    scale = LIT(2.0) * inv_sinc_SFX(half);
    for (i = 0; i < 3; ++i) {{
        y[i] = (x[i] - TARGET_POSITION_SFX[i]) / SCALES_SFX[i];
        y[3 + i] = (scale * r[i]) / SCALES_SFX[3 + i];
    }}
    for (i = 0; i < 6; ++i) z[i] = (y[i] - CENTER_SFX[i]) / LIT({self.policy.length});
}}
"""

    def _so3(self) -> str:
        return """static REAL inv_sinc_SFX(REAL x) {
    return MATH(fabs)(x) < SINC_THRESHOLD
        ? LIT(1.0) + x * x / LIT(6.0) + LIT(7.0) * (x * x * x * x) / LIT(360.0)
        : x / MATH(sin)(x);
}
static REAL sinc_SFX(REAL x) {
    return MATH(fabs)(x) < SINC_THRESHOLD
        ? LIT(1.0) - x * x / LIT(6.0) + (x * x * x * x) / LIT(120.0)
        : MATH(sin)(x) / x;
}
"""

    def _nominal(self) -> str:
        n, m = self.n, self.fourier
        act = _ACTIVATIONS[self.policy.config.activation]
        code = [
            f"static void nominal_SFX(const REAL *z, REAL *f) {{\n    REAL a[{self.width}], b[{self.width}];\n    int i, j;\n"
        ]
        if m:
            code.append(
                f"    REAL scaled[{n}];\n"
                f"    for (i = 0; i < {n}; ++i) {{ a[i] = z[i]; scaled[i] = LIT({2 * math.pi}) * z[i]; }}\n"
                f"    for (j = 0; j < {m}; ++j) {{\n        REAL angle = LIT(0.0);\n"
                f"        for (i = 0; i < {n}; ++i) angle += scaled[i] * FOURIER_SFX[i * {m} + j];\n"
                f"        a[{n} + j] = MATH(sin)(angle);\n        a[{n + m} + j] = MATH(cos)(angle);\n    }}\n"
            )
        else:
            code.append(f"    for (i = 0; i < {n}; ++i) a[i] = z[i];\n")
        source, target = "a", "b"
        for index, (weights, bias, n_in, n_out) in enumerate(self.linears):
            code.append(_dense(source, n_in, weights, bias, n_out, target))
            if index + 1 < len(self.linears):
                code.append(
                    f"    for (j = 0; j < {n_out}; ++j) {{ const REAL u = {target}[j]; {target}[j] = {act}; }}\n"
                )
            source, target = target, source
        code.append(
            f"    for (i = 0; i < {n}; ++i) f[i] = {source}[i] - NOMINAL_AT_TARGET_SFX[i];\n}}\n"
        )
        return "".join(code)

    def _warp(self) -> str:
        n = self.n
        sines = max(1, sum(self.warp))
        self.sines = sines
        temporary = f", t[{n}]" if self.warp else ""
        code = [
            f"static void warp_SFX(const REAL *z, REAL *e, REAL *sines) {{\n"
            f"    REAL y[{n}]{temporary};\n    int i, at_target = 1;\n"
            + ("    int j;\n" if self.warp else "    (void)sines;\n")
            + f"    for (i = 0; i < {n}; ++i) {{ y[i] = z[i]; if (z[i] != LIT(0.0)) at_target = 0; }}\n"
        ]
        offset = 0
        for index, m in enumerate(self.warp):
            code.append(
                f"    {{\n        REAL cosines[{m}];\n"
                f"        for (j = 0; j < {m}; ++j) {{\n            REAL angle = LIT(0.0);\n"
                f"            for (i = 0; i < {n}; ++i) angle += y[i] * WARP_F{index}_SFX[i * {m} + j];\n"
                f"            angle += WARP_P{index}_SFX[j];\n"
                f"            cosines[j] = MATH(cos)(angle);\n            sines[{offset} + j] = MATH(sin)(angle);\n        }}\n"
                + _dense("cosines", m, f"WARP_W{index}", None, n, "t")
                + f"        for (i = 0; i < {n}; ++i) y[i] = y[i] + (WARP_B{index}_SFX[i] + t[i]);\n    }}\n"
            )
            offset += m
        at = "WARP_AT_TARGET_SFX[i]" if self.warp else "LIT(0.0)"
        code.append(
            f"    for (i = 0; i < {n}; ++i) e[i] = at_target ? LIT(0.0) : y[i] - {at};\n}}\n"
        )
        vjp = [
            "static void warp_vjp_SFX(const REAL *sines, REAL *g) {\n    int i, j;\n"
            "    (void)sines; (void)g; (void)i; (void)j;\n"
        ]
        offset = sum(self.warp)
        for index in range(len(self.warp) - 1, -1, -1):
            m = self.warp[index]
            offset -= m
            vjp.append(
                f"    {{\n        REAL d[{m}], back[{n}];\n"
                + _dense("g", n, f"WARP_WT{index}", None, m, "d")
                + f"        for (j = 0; j < {m}; ++j) d[j] = sines[{offset} + j] * d[j];\n"
                + _dense("d", m, f"WARP_FT{index}", None, n, "back")
                + f"        for (i = 0; i < {n}; ++i) g[i] = g[i] - back[i];\n    }}\n"
            )
        vjp.append("}\n")
        return "".join(code) + "".join(vjp)

    def _convex(self) -> str:
        n, hidden = self.n, self.hidden
        depth = len(hidden)
        if self.icnn_slope is None:
            act = (
                "s[j] = (u > LIT(20.0) ? u : MATH(log1p)(MATH(exp)(u))); "
                "ds[j] = LIT(1.0) / (LIT(1.0) + MATH(exp)(-u));"
            )
        else:
            a = self.icnn_slope
            act = (
                f"s[j] = LIT({a}) * u + LIT({1 - a}) * (u > LIT(20.0) ? u : MATH(log1p)(MATH(exp)(u))); "
                f"ds[j] = LIT({a}) + LIT({1 - a}) * (LIT(1.0) / (LIT(1.0) + MATH(exp)(-u)));"
            )
        code = [
            f"static void convex_SFX(const REAL *x, REAL *value, REAL *grad) {{\n"
            f"    REAL slopes[{sum(hidden)}], z[{self.width}], u_[{self.width}], e_[{self.width}], d_[{self.width}], g[{n}];\n"
            f"    REAL bregman, inner, v, quad;\n    int i, j;\n"
        ]
        offset = 0
        for k, h in enumerate(hidden):
            code.append("    {\n" + _dense("x", n, f"SKIP_T{k}", f"SKIP_B{k}", h, "u_"))
            if k > 0:
                code.append(_dense("z", hidden[k - 1], f"PREV_T{k}", None, h, "d_"))
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
                + _dense("d_", h, f"SKIP{k}", None, n, "back")
                + f"        for (i = 0; i < {n}; ++i) g[i] = back[i] + g[i];\n"
            )
            if k > 0:
                code.append(_dense("d_", h, f"PREV{k}", None, hidden[k - 1], "e_"))
            code.append("    }\n")
        d = self.quadratic
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

    def _rate(self) -> str:
        config = self.policy.config
        n = self.n
        code = [
            f"static REAL rate_SFX(const REAL *z) {{\n    REAL radius = LIT(0.0), rate, excess;\n    int i;\n"
            f"    for (i = 0; i < {n}; ++i) radius += z[i] * z[i];\n    radius = MATH(sqrt)(radius);\n"
            f"    excess = radius - LIT(1.0);\n"
            f"    rate = LIT({config.decay_rate}) + LIT({config.decay_far}) * (excess > LIT(0.0) ? excess : LIT(0.0));\n"
        ]
        if self.anchors:
            code.append(
                f"    {{\n        REAL closest = LIT(0.0), square = LIT(0.0), nearest;\n        int a;\n"
                f"        for (a = 0; a < {self.anchors}; ++a) {{\n            REAL dot = LIT(0.0), d;\n"
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

    def _field(self) -> str:
        n = self.n
        if self.policy.config.rectifier == "relu":
            rectify = "excess = excess > LIT(0.0) ? excess : LIT(0.0);"
        else:  # softplus with beta 50, torch's threshold 20
            rectify = (
                "excess = LIT(50.0) * excess > LIT(20.0) ? excess "
                ": MATH(log1p)(MATH(exp)(LIT(50.0) * excess)) / LIT(50.0);"
            )
        return f"""static REAL value_SFX(const REAL *z) {{
    REAL e[{n}], grad[{n}], sines[SINES], v;
    warp_SFX(z, e, sines);
    convex_SFX(e, &v, grad);
    return v;
}}
static void field_SFX(const REAL *z, REAL *pi, REAL *value, REAL *rate) {{
    REAL f[{n}], e[{n}], g[{n}], sines[SINES], norm2 = LIT(0.0), excess = LIT(0.0), safe;
    int i;
    nominal_SFX(z, f);
    warp_SFX(z, e, sines);
    convex_SFX(e, value, g);
    warp_vjp_SFX(sines, g);
    *rate = rate_SFX(z);
    for (i = 0; i < {n}; ++i) norm2 += g[i] * g[i];
    for (i = 0; i < {n}; ++i) excess += g[i] * f[i];
    excess = excess + *value * *rate;
    {rectify}
    safe = norm2 > LIT(0.0) ? norm2 : LIT(1.0);
    for (i = 0; i < {n}; ++i) pi[i] = f[i] - g[i] * (excess / safe);
}}
"""

    def _to_user(self) -> str:
        p, n = self.policy, self.n
        speed = p.length / p.time
        if not self.pose:
            return (
                f"static void to_user_SFX(const REAL *z, const REAL *pi, REAL *v) {{\n    int i;\n    (void)z;\n"
                f"    for (i = 0; i < {n}; ++i) v[i] = pi[i] * LIT({speed});\n}}\n"
            )
        return f"""static void to_user_SFX(const REAL *z, const REAL *pi, REAL *v) {{
    /* (v, J_l(r) r'), r read back from z as the library does (snds.so3.left_jacobian). */
    REAL rates[6], r[3], hat[9], hat2[9], jac[9], theta2, theta, a, b;
    int i, j, k;
    for (i = 0; i < 6; ++i) rates[i] = (pi[i] * LIT({speed})) * SCALES_SFX[i];
    for (i = 0; i < 3; ++i) r[i] = (z[3 + i] * LIT({p.length}) + CENTER_SFX[3 + i]) * SCALES_SFX[3 + i];
    theta2 = r[0] * r[0] + r[1] * r[1] + r[2] * r[2];
    theta = MATH(sqrt)(theta2);
    if (theta < LIT(1e-3)) {{
        a = LIT(0.5) - theta2 / LIT(24.0);
        b = LIT(0.16666666666666666) - theta2 / LIT(120.0);
    }} else {{
        a = (LIT(1.0) - MATH(cos)(theta)) / (theta * theta);
        b = (theta - MATH(sin)(theta)) / (theta * theta * theta);
    }}
    hat[0] = LIT(0.0); hat[1] = -r[2]; hat[2] = r[1];
    hat[3] = r[2]; hat[4] = LIT(0.0); hat[5] = -r[0];
    hat[6] = -r[1]; hat[7] = r[0]; hat[8] = LIT(0.0);
    for (i = 0; i < 3; ++i)
        for (j = 0; j < 3; ++j) {{
            REAL sum = LIT(0.0);
            for (k = 0; k < 3; ++k) sum += hat[3 * i + k] * hat[3 * k + j];
            hat2[3 * i + j] = sum;
        }}
    for (i = 0; i < 9; ++i) jac[i] = ((i % 4 == 0) ? LIT(1.0) : LIT(0.0)) + a * hat[i] + b * hat2[i];
    for (i = 0; i < 3; ++i) {{
        v[i] = rates[i];
        v[3 + i] = jac[3 * i] * rates[3] + jac[3 * i + 1] * rates[4] + jac[3 * i + 2] * rates[5];
    }}
}}
"""

    def _advance(self) -> str:
        s, t = self.states, self.velocities
        if not self.pose:
            return (
                f"static void advance_SFX(const REAL *x, REAL h, const REAL *v, REAL *out) {{\n    int i;\n"
                f"    for (i = 0; i < {s}; ++i) out[i] = x[i] + h * v[i];\n}}\n"
            )
        del t
        return """static void advance_SFX(const REAL *x, REAL h, const REAL *v, REAL *out) {
    /* p + h v and exp(h w) q, renormalised (snds.spaces.SE3.advance). */
    REAL rv[3], e[4], norm, scale, length;
    const REAL *q = x + 3;
    int i;
    for (i = 0; i < 3; ++i) { out[i] = x[i] + h * v[i]; rv[i] = h * v[3 + i]; }
    norm = MATH(sqrt)(rv[0] * rv[0] + rv[1] * rv[1] + rv[2] * rv[2]);
    scale = sinc_SFX(norm / LIT(2.0)) / LIT(2.0);
    for (i = 0; i < 3; ++i) e[i] = scale * rv[i];
    e[3] = MATH(cos)(norm / LIT(2.0));
    out[3] = e[3] * q[0] + q[3] * e[0] + (e[1] * q[2] - e[2] * q[1]);
    out[4] = e[3] * q[1] + q[3] * e[1] + (e[2] * q[0] - e[0] * q[2]);
    out[5] = e[3] * q[2] + q[3] * e[2] + (e[0] * q[1] - e[1] * q[0]);
    out[6] = e[3] * q[3] - (e[0] * q[0] + e[1] * q[1] + e[2] * q[2]);
    length = MATH(sqrt)(out[3] * out[3] + out[4] * out[4] + out[5] * out[5] + out[6] * out[6]);
    for (i = 3; i < 7; ++i) out[i] = out[i] / length;
}
"""

    def _public(self) -> str:
        p, n, s, t = self.policy, self.n, self.states, self.velocities
        prefix = self.prefix
        return f"""static int at_target_SFX(const REAL *z) {{
    int i;
    for (i = 0; i < {n}; ++i) if (z[i] != LIT(0.0)) return 0;
    return 1;
}}
int {prefix}_policySUFFIX(const REAL *state, REAL *velocity) {{
    REAL z[{n}], pi[{n}], value, rate;
    int i, finite = 1;
    chart_SFX(state, z);
    if (at_target_SFX(z)) {{
        for (i = 0; i < {t}; ++i) velocity[i] = LIT(0.0);
        return 0;
    }}
    field_SFX(z, pi, &value, &rate);
    to_user_SFX(z, pi, velocity);
    for (i = 0; i < {t}; ++i) finite = finite && velocity[i] - velocity[i] == LIT(0.0);
    return finite ? 0 : -1;
}}
REAL {prefix}_lyapunovSUFFIX(const REAL *state) {{
    REAL z[{n}];
    chart_SFX(state, z);
    return value_SFX(z);
}}
REAL {prefix}_stepSUFFIX(const REAL *state, REAL dt, REAL max_speed, REAL *command, REAL *next) {{
    REAL z[{n}], pi[{n}], v[{t}], value, rate, speed = LIT(0.0), scale = LIT(1.0), required, h = dt, reached;
    int i, halvings;
    chart_SFX(state, z);
    if (at_target_SFX(z)) {{
        for (i = 0; i < {t}; ++i) command[i] = LIT(0.0);
        for (i = 0; i < {s}; ++i) next[i] = state[i];
        return dt;
    }}
    field_SFX(z, pi, &value, &rate);
    to_user_SFX(z, pi, v);
    for (i = 0; i < {self.position_dim}; ++i) speed += v[i] * v[i];
    speed = MATH(sqrt)(speed);
    if (max_speed > LIT(0.0) && speed > max_speed) scale = max_speed / speed;
    for (i = 0; i < {t}; ++i) v[i] = v[i] * scale;
    /* The scaled velocity promises the decrease rate scale a(x) (per user second). */
    required = LIT(0.5) * (scale * ((value * rate) / LIT({p.time})));
    advance_SFX(state, h, v, next);
    chart_SFX(next, z);
    reached = value_SFX(z);
    if (value > LIT(0.0)) {{
        for (halvings = 0; halvings < {MAX_HALVINGS}; ++halvings) {{
            if (reached <= value - h * required && reached < value) break;
            h = LIT(0.5) * h;
            advance_SFX(state, h, v, next);
            chart_SFX(next, z);
            reached = value_SFX(z);
        }}
    }}
    for (i = 0; i < {t}; ++i) command[i] = v[i] * (h / dt);
    return h;
}}
"""

    def _start(self) -> str:
        if self.starts is None:
            return ""
        s, p = self.states, self.position_dim
        return f"""void {self.prefix}_start_stateSUFFIX(const REAL *position, REAL *state) {{
    int d, i, nearest = 0;
    REAL best = LIT(0.0);
    for (d = 0; d < {len(self.starts)}; ++d) {{
        REAL distance = LIT(0.0);
        for (i = 0; i < {p}; ++i) {{
            const REAL offset = START_STATES_SFX[d * {s} + i] - position[i];
            distance += offset * offset;
        }}
        if (d == 0 || distance < best) {{ best = distance; nearest = d; }}
    }}
    for (i = 0; i < {p}; ++i) state[i] = position[i];
    for (i = {p}; i < {s}; ++i) state[i] = START_STATES_SFX[nearest * {s} + i];
}}
"""

    def source(self) -> str:
        """The ``.c`` file (its ``#include`` names the header as ``HEADER``)."""
        parts = [
            "/* Generated by snds (snds export --format c); do not edit. See the header. */\n"
            '#include <math.h>\n#include <stddef.h>\n#include "HEADER"\n'
        ]
        body = "".join(
            [
                self._so3() if self.pose else "",
                self._chart(),
                self._nominal(),
                self._warp(),
                self._convex(),
                self._rate(),
                self._field(),
                self._to_user(),
                self._advance(),
                self._public(),
                self._start(),
            ]
        )
        for variant in VARIANTS:
            parts.append(f"\n/* ---- {variant.real} ---- */\n")
            parts.append(self._constants(variant) + "\n")
            code = body.replace("SUFFIX", variant.suffix).replace("SINES", str(self.sines))
            threshold = _SINC_THRESHOLD[variant.numpy]
            parts.append(variant.fill(code).replace("SINC_THRESHOLD", variant.number(threshold)))
        return "".join(parts)

    def header(self, *, rate: float, max_speed: float) -> str:
        """The ``.h`` file: the public functions, dimensions, target, period and limit."""
        p, space, prefix = self.policy, self.policy.space, self.prefix
        macro = prefix.upper()
        target = ", ".join(repr(float(v)) for v in p.target)
        lines = [
            f"/* Generated by snds (snds export --format c): {p.method} policy. Do not edit.",
            f" * state in:  {space.state_text}",
            f" * out:       {space.velocity_text}",
            " * C99, <math.h> only; no allocation, no global mutable state; reentrant. */",
            f"#ifndef {macro}_POLICY_H",
            f"#define {macro}_POLICY_H",
            f"#define {macro}_STATE_DIM {self.states}",
            f"#define {macro}_VELOCITY_DIM {self.velocities}",
            f"#define {macro}_POSITION_DIM {self.position_dim}",
            f"/* The control period the model was exported for (s), 1 / {rate:g} Hz. */",
            f"#define {macro}_DT {1.0 / rate!r}",
            "/* The speed limit of the positions (user units/s; 0: none). */",
            f"#define {macro}_MAX_SPEED {float(max_speed)!r}",
            f"#define {macro}_TARGET {{{target}}}",
            "/* The demonstrations' extent (user units) and top speed (user units/s). */",
            f"#define {macro}_EXTENT {float(p.extents()[0])!r}",
            f"#define {macro}_TOP_SPEED {float(p.length / p.time * p.chart_scales()[0])!r}",
            '#ifdef __cplusplus\nextern "C" {\n#endif',
        ]
        for variant in VARIANTS:
            real, sfx = variant.real, variant.suffix
            lines += [
                f"/* pi(state) -> velocity, user units ({real}); 0, or -1 if not finite. */",
                f"int {prefix}_policy{sfx}(const {real} *state, {real} *velocity);",
                f"/* V(state) in model coordinates ({real}): 0 at the target, > 0 elsewhere. */",
                f"{real} {prefix}_lyapunov{sfx}(const {real} *state);",
                "/* The guarded step: velocity limited to max_speed (<= 0: none), step h <= dt",
                " * halved until V decreases enough; command = velocity h / dt (to hold for",
                " * dt), next = the state reached after h; returns h. */",
                f"{real} {prefix}_step{sfx}(const {real} *state, {real} dt, {real} max_speed,",
                f"    {real} *command, {real} *next);",
            ]
        if self.starts is not None:
            lines.append(f"#define {macro}_START_COUNT {len(self.starts)}")
            for variant in VARIANTS:
                real, sfx = variant.real, variant.suffix
                lines += [
                    "/* A start state at a position: the position, then the phase of the",
                    " * demonstration whose start is nearest (snds.phase.start_state). */",
                    f"void {prefix}_start_state{sfx}(const {real} *position, {real} *state);",
                ]
        lines += ["#ifdef __cplusplus\n}\n#endif", f"#endif /* {macro}_POLICY_H */", ""]
        return "\n".join(lines)


#: Halvings of the guarded step before it is taken as it is (snds.rollout.guarded_step).
MAX_HALVINGS = 30
