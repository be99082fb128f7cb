# ruff: noqa: E501  (the C templates keep one C statement per line)
r"""The C99 source of a policy (:mod:`snds.export.c` writes it): one generator per model.

Every function is written once with placeholders (``REAL``, ``MATH(name)``, ``LIT(number)``,
``SFX``) and filled in for each :class:`CVariant` (double, float). The arithmetic follows the
library's operation by operation (the same sums in the same order where the library's order
is fixed, its constants computed as it computes them), so the double version agrees with the
library in float64 to rounding: :mod:`snds.export.c_check` measures it. V and its decay rate are
written by :mod:`snds.export.c_lyapunov`, the space's maps (a pose's log and exponential maps and
twist) by :mod:`snds.export.c_space`; this module writes the nominal network, the projection, the
public functions and the files.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

import numpy as np
import torch

from snds.errors import CExportError
from snds.export import c_lyapunov
from snds.export.c_lyapunov import dense
from snds.export.c_space import SINC_THRESHOLD, advance, chart, so3, to_user
from snds.nn.lyapunov import WarpedLyapunov
from snds.nn.mlp import FourierFeatures
from snds.phase import StartRule
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


class Generator:
    """The C files of one policy (float64, eval mode; see :func:`snds.export.c.export_c`).

    Arguments:
        policy: A float64 copy of an SNDS policy (positions, poses or a phase).
        prefix: Prefix of the public names.
    """

    def __init__(
        self, policy: StablePolicy, *, prefix: str, start_rule: StartRule | None = None
    ) -> None:
        self.policy = policy
        self.start_rule = start_rule
        self.starts = None if start_rule is None else np.asarray(start_rule.references)
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
        #: Sines of the warp's Fourier angles that its Jacobian product keeps (1 without one).
        self.sines = max(1, sum(self.warp))
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
            code.append(dense(source, n_in, weights, bias, n_out, target))
            if index + 1 < len(self.linears):
                code.append(
                    f"    for (j = 0; j < {n_out}; ++j) {{ const REAL u = {target}[j]; {target}[j] = {act}; }}\n"
                )
            source, target = target, source
        code.append(
            f"    for (i = 0; i < {n}; ++i) f[i] = {source}[i] - NOMINAL_AT_TARGET_SFX[i];\n}}\n"
        )
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
        if self.start_rule is None:
            return ""
        s, p = self.states, self.position_dim
        b = s - self.policy.space.phase_dim
        reach = self.start_rule.reach
        return f"""void {self.prefix}_start_stateSUFFIX(const REAL *base, REAL *state) {{
    int d, i, nearest = 0;
    REAL best = LIT(0.0);
    for (d = 0; d < {len(self.starts)}; ++d) {{
        REAL distance = LIT(0.0);
        for (i = 0; i < {p}; ++i) {{
            const REAL offset = START_STATES_SFX[d * {s} + i] - base[i];
            distance += offset * offset;
        }}
        if (d == 0 || distance < best) {{ best = distance; nearest = d; }}
    }}
    for (i = 0; i < {b}; ++i) state[i] = base[i];
    for (i = {b}; i < {s}; ++i)
        state[i] = best <= LIT({reach * reach!r}) ? START_STATES_SFX[nearest * {s} + i] : LIT(0.0);
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
                so3(self) if self.pose else "",
                chart(self),
                self._nominal(),
                c_lyapunov.warp(self),
                c_lyapunov.convex(self),
                c_lyapunov.decay_rate(self),
                self._field(),
                to_user(self),
                advance(self),
                self._public(),
                self._start(),
            ]
        )
        for variant in VARIANTS:
            parts.append(f"\n/* ---- {variant.real} ---- */\n")
            parts.append(self._constants(variant) + "\n")
            code = body.replace("SUFFIX", variant.suffix).replace("SINES", str(self.sines))
            threshold = SINC_THRESHOLD[variant.numpy]
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
                    "/* A start state at a base state (a position, or a pose): the base, then",
                    " * the phase of the nearest demonstrated sample within the reach, else 0",
                    " * (snds.phase.start_state). */",
                    f"void {prefix}_start_state{sfx}(const {real} *base, {real} *state);",
                ]
        lines += ["#ifdef __cplusplus\n}\n#endif", f"#endif /* {macro}_POLICY_H */", ""]
        return "\n".join(lines)


#: Halvings of the guarded step before it is taken as it is (snds.rollout.guarded_step).
MAX_HALVINGS = 30
