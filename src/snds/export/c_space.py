# ruff: noqa: E501  (the C templates keep one C statement per line)
r"""The C of a policy's space, for :mod:`snds.export.c_source`: how a state becomes model coordinates
(a pose's log map, as roma computes it), how a model velocity becomes a user velocity (a
pose's twist through the left Jacobian of SO(3)), and how a state moves along a velocity (a
pose's exponential map). Each function takes the :class:`~snds.export.c_source.Generator` and returns
C with its placeholders (REAL, MATH, LIT, SFX).
"""

from __future__ import annotations

import numpy as np

__all__ = ["SINC_THRESHOLD", "advance", "chart", "so3", "to_user"]

#: Below this angle roma's sinc and inv_sinc take their Taylor series: 2 eps^(1/6).
SINC_THRESHOLD = {
    np.float64: 2.0 * np.finfo(np.float64).eps ** (1 / 6),
    np.float32: 2.0 * float(np.finfo(np.float32).eps) ** (1 / 6),
}


def so3(generator) -> str:
    """roma's inv_sinc and sinc (poses)."""
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


def chart(generator) -> str:
    """``chart_SFX``: user state -> model coordinates."""
    n = generator.n
    if not generator.pose:
        return (
            "static void chart_SFX(const REAL *x, REAL *z) {\n    int i;\n"
            f"    for (i = 0; i < {n}; ++i) z[i] = (x[i] - CENTER_SFX[i]) / LIT({generator.policy.length});\n"
            "}\n"
        )
    return f"""static void chart_SFX(const REAL *x, REAL *z) {{
/* The rotation vector log(q conj(q*)) (roma's quat_product and unitquat_to_rotvec). */
const REAL *q = x + 3;
const REAL c[4] = {{-TARGET_ORIENTATION_SFX[0], -TARGET_ORIENTATION_SFX[1],
                    -TARGET_ORIENTATION_SFX[2], TARGET_ORIENTATION_SFX[3]}};
REAL r[4], y[{n}], sign, norm, half, scale;
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
/* A phase after the pose is scaled as the positions are (snds.se3.PosePolicy.chart). */
for (i = 6; i < {n}; ++i) y[i] = x[i + 1] / SCALES_SFX[i];
for (i = 0; i < {n}; ++i) z[i] = (y[i] - CENTER_SFX[i]) / LIT({generator.policy.length});
}}
"""


def to_user(generator) -> str:
    """``to_user_SFX``: model velocity -> user velocity (a pose's twist)."""
    p, n = generator.policy, generator.n
    speed = p.length / p.time
    if not generator.pose:
        return (
            f"static void to_user_SFX(const REAL *z, const REAL *pi, REAL *v) {{\n    int i;\n    (void)z;\n"
            f"    for (i = 0; i < {n}; ++i) v[i] = pi[i] * LIT({speed});\n}}\n"
        )
    return f"""static void to_user_SFX(const REAL *z, const REAL *pi, REAL *v) {{
/* (v, J_l(r) r'), r read back from z as the library does (snds.so3.left_jacobian). */
REAL rates[{n}], r[3], hat[9], hat2[9], jac[9], theta2, theta, a, b;
int i, j, k;
for (i = 0; i < {n}; ++i) rates[i] = (pi[i] * LIT({speed})) * SCALES_SFX[i];
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
for (i = 6; i < {n}; ++i) v[i] = rates[i];
}}
"""


def advance(generator) -> str:
    """``advance_SFX``: a state moved along a velocity for h seconds."""
    s, t = generator.states, generator.velocities
    if not generator.pose:
        return (
            f"static void advance_SFX(const REAL *x, REAL h, const REAL *v, REAL *out) {{\n    int i;\n"
            f"    for (i = 0; i < {s}; ++i) out[i] = x[i] + h * v[i];\n}}\n"
        )
    del t
    return """static void advance_SFX(const REAL *x, REAL h, const REAL *v, REAL *out) {
/* p + h v and exp(h w) q, renormalised (snds.spaces.SE3.advance); a phase after the pose
   moves along its rate. */
REAL rv[3], e[4], norm, scale, length;
const REAL *q = x + 3;
int i;
for (i = 7; i < STATES; ++i) out[i] = x[i] + h * v[i - 1];
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
""".replace("STATES", str(s))
