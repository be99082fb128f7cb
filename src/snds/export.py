r"""Export of a policy for a real-time controller, and the check that it computes the same.

The exported graph is the policy's own ``forward``: user positions in, user velocities out,
with the Lyapunov gradient written analytically (:meth:`snds.nn.Lyapunov.value_and_grad`),
so no autograd is needed or traced. For an SE(3) :class:`~snds.se3.PosePolicy` (space
:class:`~snds.spaces.SE3`) a state is a pose (x, y, z, qx, qy, qz, qw; user units and a unit
quaternion), and the output the twist (linear velocity in user units per second, then
the world-frame angular velocity in rad/s) out, with the log map of the orientation and the
left Jacobian of SO(3) in the graph, so a controller needs no quaternion maths of its own.
What an export takes and returns, asked of the policy's space, and how its check samples
it, is its :class:`Signature`.
Two formats:

- ONNX (:func:`export_onnx`), run by onnxruntime from any language; the file carries the
  target, the state dimension, the speed scale and what its input and output are in its
  metadata.
- ``torch.export`` (:func:`export_pt2`), a ``.pt2`` archive: the graph as JSON and the
  weights as raw bytes (no pickle for plain tensors), loaded by :func:`torch.export.load`.

:func:`verify` runs an exported file on random states, from near the target to 1000x the
demonstrations' extent (for poses: with orientations uniform on SO(3)), and compares it with
the library evaluated in the same precision.
"""

from __future__ import annotations

import contextlib
import copy
import json
import logging
import math
import threading
import warnings
import zipfile
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from snds.errors import SNDSError
from snds.io import atomic_write
from snds.nn.lyapunov import Lyapunov, WarpedLyapunov
from snds.nn.mlp import FourierFeatures
from snds.phase import StartRule
from snds.policy import Policy, StablePolicy, project

#: Largest accepted difference from the library evaluated in the export's precision,
#: relative to max(|velocity|, top speed) of each state. float64 graphs agree to rounding
#: (about 1e-13). float32 cannot promise 1e-5: next to the target V and its gradient are small
#: differences of order-1 numbers and the projection divides by |grad V|, so rounding is
#: amplified there, and two float32 implementations that order the sums differently
#: (onnxruntime's kernels, torch's) differ by about as much as each differs from float64
#: (measured figures: docs/design.md, "Export accuracy").
TOLERANCE = {torch.float64: 1e-5, torch.float32: 3e-4}
#: A float32 export also passes when it is no farther from the exact (float64) policy than
#: this many times the float32 library itself: next to the target two float32
#: implementations may each be far from the exact policy and differ from each other by as
#: much (docs/design.md, "Export accuracy").
ROUNDING_SLACK = 2.0
#: The name of the ONNX input (a state per row) and of its batch dimension; the output is
#: :attr:`Signature.output_name`.
INPUT_NAME = "state"
BATCH_NAME = "batch"
#: Spread of the random states of :func:`random_states`, in units of the demonstrations'
#: extent: from near the data out to 1000x.
STATE_RADII = (1.0, 3.0, 10.0, 100.0, 1000.0)
_NUMPY = {torch.float32: np.float32, torch.float64: np.float64}
# The files of a .pt2 archive that say, per tensor, whether it is stored pickled.
_TENSOR_CONFIGS = ("weights_config.json", "constants_config.json")


class ExportError(SNDSError):
    """An export that failed, or whose outputs differ from the library's."""


class _Exported(torch.nn.Module):
    """The traced module: the policy's ``forward``, in a fixed precision and in eval mode.

    A policy that :class:`_FusedStable` computes (the default SNDS policy) is traced as that
    fused graph. For another SNDS policy, f(0), which the library evaluates with every batch,
    is computed once here; the rest is the library's own code. g(0) and grad g(0) are not
    folded: the Bregman difference g(x) - g(0) - grad g(0).x cancels O(1) numbers next to
    the target, and only evaluating g(0) with the same kernels as g(x) (the target row in the
    ICNN's batch, as the library does) keeps the rounding errors of the two correlated there.
    Folded, a float32 export differed from the float32 library by 2.4e-4 of the top speed
    next to the target; in the graph, 8e-5. :func:`verify` compares the export with the
    library's ``forward``, so a change to :meth:`StablePolicy.field` that this misses fails
    every export.
    """

    def __init__(self, policy: Policy, dtype: torch.dtype) -> None:
        super().__init__()
        self.fused = _FusedStable(policy, dtype) if _fusable(policy) else None
        if self.fused is not None:
            return
        self.policy = _copy(policy, dtype)
        self.folded = type(self.policy) is StablePolicy
        if self.folded:
            with torch.no_grad():
                self.nominal = _fused_nominal(self.policy)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if self.fused is not None:
            return self.fused(x)
        policy = self.policy
        if not self.folded:
            return policy(x)
        z = policy.to_model(x)
        field = self.nominal(z)
        if policy.stable:
            v, grad_v = policy.lyapunov.value_and_grad(z)
            field = project(field, grad_v, policy.decay(v, z), policy.config.rectifier)
        return field * (policy.length / policy.time)


class _FourierInput(torch.nn.Module):
    r"""Random Fourier features and the first linear layer as one map, with fewer nodes.

    :math:`W [x; \sin 2\pi B x; \cos 2\pi B x] + b = W_x x + b + W_{sc} \sin(x P + c)`
    with :math:`P = 2\pi [B, B]` and phases :math:`c = [0, \pi/2]`: one sine of twice the
    width instead of a sine, a cosine and a concatenation (which alone took 1 ms of a batch of
    10,000 states). The same function; its rounding differs from the library's by about an
    ulp of the angles, which :func:`verify` bounds.
    """

    def __init__(self, features: FourierFeatures, linear: torch.nn.Linear) -> None:
        super().__init__()
        frequencies = (2 * math.pi) * features.frequencies.double()
        n, m = frequencies.shape
        dtype = linear.weight.dtype
        self.register_buffer("angles", torch.cat([frequencies, frequencies], 1).to(dtype))
        half_pi = torch.full((m,), math.pi / 2, dtype=torch.float64)
        phases = torch.cat([torch.zeros_like(half_pi), half_pi]).to(dtype)
        self.register_buffer("phases", phases)
        self.register_buffer("w_x", linear.weight[:, :n].T.contiguous())
        self.register_buffer("w_sc", linear.weight[:, n:].T.contiguous())
        self.register_buffer("bias", linear.bias.clone())

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        features = torch.sin(torch.addmm(self.phases, x, self.angles))
        return torch.addmm(torch.addmm(self.bias, x, self.w_x), features, self.w_sc)


def _fused_nominal(policy: StablePolicy) -> torch.nn.Sequential:
    """f(x) - f(0) as one network: f(0) is folded into the last layer's bias, and Fourier
    features into the first layer (:class:`_FourierInput`)."""
    layers = [copy.deepcopy(layer) for layer in policy.nominal_net]
    zero = torch.zeros(1, policy.dim, dtype=policy.center.dtype)
    layers[-1].bias -= policy.nominal_net(zero)[0]
    if isinstance(layers[0], FourierFeatures):
        layers[:2] = [_FourierInput(layers[0], layers[1])]
    return torch.nn.Sequential(*layers)


class _FusedStable(torch.nn.Module):
    r"""The default SNDS policy's ``forward`` as one fused graph: the library's arithmetic with
    its constants folded, in fewer and larger operations.

    It computes what :meth:`StablePolicy.forward` computes, for a stable policy whose V is a
    :class:`~snds.nn.Lyapunov` or a :class:`~snds.nn.WarpedLyapunov` of additive coupling
    layers, with the ReLU rectifier (other policies export through the library's own code).
    Folded in float64 and rounded once to the export's precision:

    - f(0) and the unit of speed L/T into the nominal network's last layer, and L/T into the
      decay rates: ReLU is positively homogeneous, so the projection of the scaled field is
      the scaled projection.
    - Per coupling layer, the amplitude and mask of the weights; its cosine and sine features
      as one sine of twice the width, :math:`\sin(y [\Omega, \Omega] + [\beta + \pi/2,
      \beta])`; and its shift :math:`t` and the non-zero entries :math:`c` of its Jacobian
      :math:`C` (transformed rows, conditioning columns) as one product of those features,
      which gives the block :math:`[y + t, c]`. The backward pass is then :math:`g \leftarrow
      g + ((g E) \odot [y, c]) R` with fixed 0/1 matrices E and R.
    - The ICNN's output weights into its backward products, and the affine part of the
      activation's slope into their biases.

    Not folded, as in the library: :math:`\phi(0)`, g(0) and :math:`\nabla g(0)`. The target
    is the last row of the batch, so that the cancellations :math:`\phi(x) - \phi(0)` and
    :math:`g(e) - g(0) - \nabla g(0)^\top e` next to the target subtract values computed by
    the same kernels (see :class:`_Exported`). A state exactly at the target gets velocity 0
    exactly.

    Arguments:
        policy: The policy (see :func:`_fusable`).
        dtype: Precision of the graph.
    """

    def __init__(self, policy: StablePolicy, dtype: torch.dtype) -> None:
        super().__init__()
        exact = _copy(policy, torch.float64)
        config = exact.config
        n = exact.dim
        speed = exact.length / exact.time
        self.length = float(exact.length)

        def buffer(name: str, value: torch.Tensor) -> None:
            self.register_buffer(name, value.detach().to(torch.float64).to(dtype).contiguous())

        buffer("center", exact.center)
        buffer("zero_row", torch.zeros(1, n))
        # The nominal f(x) - f(0), times L/T.
        with torch.no_grad():
            nominal = _fused_nominal(exact)
            nominal[-1].weight *= speed
            nominal[-1].bias *= speed
        self.nominal = nominal.to(dtype)
        lyapunov = exact.lyapunov
        if isinstance(lyapunov, WarpedLyapunov):
            convex, layers = lyapunov.convex, list(lyapunov.warp.layers)
        else:
            convex, layers = lyapunov, []
        # Coupling layers. Row block Y_l = [y_l, c_l]: the state after layer l and the q
        # non-zero entries c_l of that layer's Jacobian C_l (q = |x_a| |x_b|).
        self.layers = len(layers)
        # float64: cos and sin of the angles themselves. Adding pi/2 to an angle of 1e5 rad
        # (1000 extents out) rounds it by 1e-11, which a trained warp amplifies to 1e-8 of
        # the velocity; float32's own rounding is far larger.
        self.split = dtype == torch.float64
        width = n
        for index, layer in enumerate(layers):
            frequencies = layer.frequencies  # (n, m), zero rows on x_b
            m = frequencies.shape[1]
            weight = layer.weight * layer.scaled_columns  # (m, n), zero columns on x_a
            pairs = [
                (k, i)
                for k in range(n)
                if layer.transformed[k] > 0
                for i in range(n)
                if layer.transformed[i] == 0
            ]
            q = len(pairs)
            # Y_{l-1} [Omega, Omega] (+ phases): the angles, from y_{l-1} only.
            angles = torch.zeros(width, 2 * m, dtype=torch.float64)
            angles[:n] = torch.cat([frequencies, frequencies], 1)
            # [cos, sin] -> [t, c]: t = cos W + bias, c_p = C[k, i] = -sum_j sin_j Omega[i, j]
            # W[j, k] for the pair p = (k, i).
            product = torch.zeros(2 * m, n + q, dtype=torch.float64)
            product[:m, :n] = weight
            bias = torch.zeros(n + q, dtype=torch.float64)
            bias[:n] = layer.bias * layer.columns
            keep = torch.zeros(width, n + q, dtype=torch.float64)
            keep[:n, :n] = torch.eye(n, dtype=torch.float64)
            # Backward: C^T g = ((g E) * c) R with E[k, p] = 1 and R[p, i] = 1.
            select = torch.zeros(n, n + q, dtype=torch.float64)
            scatter = torch.zeros(n + q, n, dtype=torch.float64)
            for p, (k, i) in enumerate(pairs):
                product[m:, n + p] = -frequencies[i] * weight[:, k]
                select[k, n + p] = 1.0
                scatter[n + p, i] = 1.0
            if self.split:
                buffer(f"angles{index}", angles[:, :m])
                buffer(f"phases{index}", layer.phases)
            else:
                buffer(f"angles{index}", angles)
                buffer(f"phases{index}", torch.cat([layer.phases + math.pi / 2, layer.phases]))
            buffer(f"product{index}", product)
            buffer(f"product_bias{index}", bias)
            buffer(f"keep{index}", keep)
            buffer(f"select{index}", select)
            buffer(f"scatter{index}", scatter)
            width = n + q
        out_of_block = torch.zeros(width, n, dtype=torch.float64)
        out_of_block[:n] = torch.eye(n, dtype=torch.float64)
        buffer("state_of_block", out_of_block)
        # The ICNN: z_k = s(u_k), s(u) = a u + (1 - a) softplus(u), s'(u) = a + (1 - a) sigma(u).
        icnn = convex.icnn
        self.slope = 0.1 if icnn.activation == "smooth_leaky" else 0.0
        a = self.slope
        weights = icnn.weights()
        out = torch.nn.functional.softplus(icnn.raw_out)
        depth = len(icnn.skips)
        self.depth = depth
        for k, skip in enumerate(icnn.skips):
            buffer(f"skip{k}", skip.weight.T)
            buffer(f"bias{k}", skip.bias)
            if k > 0:
                buffer(f"prev{k}", weights[k - 1].T)
                buffer(f"prev_tail{k}", -(1 - a) * weights[k - 1].T)
        buffer("out", out[:, None])
        buffer("out_tail", -(1 - a) * out[:, None])
        buffer("linear", icnn.linear_out[:, None])
        # Backward: the last layer's delta is out * s'(u_K) = (1 - a) out sigma + a out.
        last = icnn.skips[-1].weight
        buffer("back_skip", (1 - a) * out[:, None] * last)
        gradient_bias = icnn.linear_out + a * (out[:, None] * last).sum(0)
        buffer("gradient_bias", gradient_bias[None])
        buffer("quadratic_eye", 2 * convex.quadratic * torch.eye(n, dtype=torch.float64))
        # d |e|^2 as the product of e * e with a column of d (one node less than a sum and a
        # product with d).
        buffer("quadratic_column", torch.full((n, 1), float(convex.quadratic), dtype=torch.float64))
        if depth > 1:
            buffer("back_prev", (1 - a) * out[:, None] * weights[-1])
            buffer("back_prev_bias", (a * (out[:, None] * weights[-1]).sum(0))[None])
        # Lower layers: delta_k = e_k (a + (1 - a) sigma_k) = (1 - a) e_k (sigma_k + a / (1 - a)).
        self.offset = a / (1 - a)
        for k in range(depth - 1):
            buffer(f"back_skip{k}", (1 - a) * icnn.skips[k].weight)
            if k > 0:
                buffer(f"back_prev{k}", (1 - a) * weights[k - 1])
        # The decay rate a(x) / V = rho + rho_far (|x| - 1)_+ + rho_near (1 - |x| / r)_+, times
        # L/T, as a two-layer network of |x| (and the data kernel below).
        rates = [(1.0, -1.0, config.decay_far)]
        if config.decay_near:
            rates.append((-1.0 / config.near_radius, 1.0, config.decay_near))
        rates = torch.tensor(rates, dtype=torch.float64)
        buffer("rate_in", rates[None, :, 0])
        buffer("rate_bias", rates[:, 1])
        buffer("rate_out", speed * rates[:, 2:])
        buffer("rate_base", torch.tensor([speed * config.decay_rate], dtype=torch.float64))
        # On the data, rho gives way to rho_data by the kernel exp(-d^2 / (2 r^2)) of the
        # distance to the nearest anchor (see PolicyConfig.data_rate), times L/T.
        self.anchored = exact.anchors is not None
        if self.anchored:
            anchors = exact.anchors.to(torch.float64)
            # With w = 1 / (2 r^2), the kernel's exponent -w min_j |z - a_j|^2 is
            # max_j (2 w z . a_j - w |a_j|^2) - w |z|^2: the bracket is one product with a bias,
            # and w |z|^2, a product of z * z with a column of w, is subtracted after the
            # maximum, from a column instead of from every (state, anchor) pair.
            width = 1.0 / (2.0 * config.data_radius**2)
            buffer("anchors_t", 2.0 * width * anchors.T)
            buffer("anchors_sq", -width * (anchors * anchors).sum(-1))
            buffer("width_column", torch.full((n, 1), width, dtype=torch.float64))
            # the kernel enters the rate through a product with -L/T rho_drop (a 1 x 1 matrix)
            buffer(
                "data_gain", torch.full((1, 1), -speed * config.data_rate_drop, dtype=torch.float64)
            )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        z = torch.cat([(x - self.center) / self.length, self.zero_row])  # the target last
        field = self.nominal(z)
        # The warp: Y_l = [y_{l-1}, 0] + [t_l, c_l]. Every output of the products with keep and
        # scatter has one non-zero term, so each is rounded once, whatever the kernel's order.
        block, blocks = z, []
        for index in range(self.layers):
            angles = torch.addmm(
                getattr(self, f"phases{index}"), block, getattr(self, f"angles{index}")
            )
            if self.split:
                features = torch.cat([torch.cos(angles), torch.sin(angles)], 1)
            else:
                features = torch.sin(angles)
            shift = torch.addmm(
                getattr(self, f"product_bias{index}"), features, getattr(self, f"product{index}")
            )
            block = torch.addmm(shift, block, getattr(self, f"keep{index}"))
            blocks.append(block)
        y = block @ self.state_of_block if self.layers else z
        e = y - y[-1:]
        # The ICNN g at e, forward.
        u = torch.addmm(self.bias0, e, self.skip0)
        sigmoids = []
        for k in range(self.depth):
            sigmoid = torch.sigmoid(u)
            sigmoids.append(sigmoid)
            # softplus(u) = relu(u) - log(sigma(|u|)), and sigma(|u|) = max(sigma, 1 - sigma)
            tail = torch.log(torch.maximum(sigmoid, 1.0 - sigmoid))
            if self.slope:
                activated = torch.nn.functional.leaky_relu(u, self.slope)
            else:
                activated = torch.relu(u)
            # z_k = activated - (1 - a) tail, each part multiplied by its consumer's weights.
            if k + 1 < self.depth:
                u = torch.addmm(getattr(self, f"bias{k + 1}"), e, getattr(self, f"skip{k + 1}"))
                u = torch.addmm(u, activated, getattr(self, f"prev{k + 1}"))
                u = torch.addmm(u, tail, getattr(self, f"prev_tail{k + 1}"))
        g = torch.addmm(torch.addmm(e @ self.linear, activated, self.out), tail, self.out_tail)
        # Backward: grad g(e) + 2 d e.
        grad = torch.addmm(
            torch.addmm(self.gradient_bias, e, self.quadratic_eye), sigmoids[-1], self.back_skip
        )
        if self.depth > 1:
            back = torch.addmm(self.back_prev_bias, sigmoids[-1], self.back_prev)
            for k in range(self.depth - 2, -1, -1):
                delta = back * (sigmoids[k] + self.offset)
                grad = torch.addmm(grad, delta, getattr(self, f"back_skip{k}"))
                if k > 0:
                    back = delta @ getattr(self, f"back_prev{k}")
        # V_c(e) = min(Bregman + d |e|^2, grad V_c . e), as in Lyapunov.value_and_grad.
        g0, grad0 = g[-1:], grad[-1:]
        bregman = torch.relu(g - g0 - e @ grad0.T)
        grad_v = grad - grad0
        value = bregman + (e * e) @ self.quadratic_column
        value = torch.relu(torch.minimum(value, (grad_v * e).sum(-1, keepdim=True)))
        # The warp, backward: J_l^T g = g + C_l^T g.
        for index in range(self.layers - 1, -1, -1):
            picked = (grad_v @ getattr(self, f"select{index}")) * blocks[index]
            grad_v = torch.addmm(grad_v, picked, getattr(self, f"scatter{index}"))
        # The decay a(x) and the projection.
        radius = torch.linalg.vector_norm(z, dim=-1, keepdim=True)
        rate = torch.addmm(
            self.rate_base,
            torch.relu(torch.addmm(self.rate_bias, radius, self.rate_in)),
            self.rate_out,
        )
        if self.anchored:
            closest = torch.amax(
                torch.addmm(self.anchors_sq, z, self.anchors_t), dim=-1, keepdim=True
            )
            exponent = torch.clamp_max(closest - (z * z) @ self.width_column, 0.0)
            rate = torch.addmm(rate, torch.exp(exponent), self.data_gain)
        norm2 = (grad_v * grad_v).sum(-1, keepdim=True)
        excess = torch.relu((grad_v * field).sum(-1, keepdim=True) + value * rate)
        safe = torch.where(norm2 > 0, norm2, 1.0)
        velocity = field - grad_v * (excess / safe)
        velocity = torch.where(radius == 0, 0.0, velocity)
        return velocity[:-1]


def _fusable(policy: Policy) -> bool:
    """Whether :class:`_FusedStable` computes this policy: a stable SNDS policy with the ReLU
    rectifier whose V is convex or warped by additive coupling layers."""
    if type(policy) is not StablePolicy or not policy.stable:
        return False
    if policy.config.rectifier != "relu":
        return False
    lyapunov = policy.lyapunov
    if isinstance(lyapunov, WarpedLyapunov):
        if any(layer.affine for layer in lyapunov.warp.layers):
            return False
        lyapunov = lyapunov.convex
    return isinstance(lyapunov, Lyapunov) and lyapunov.icnn.activation in (
        "smooth_leaky",
        "softplus",
    )


def _copy(policy: Policy, dtype: torch.dtype) -> Policy:
    return copy.deepcopy(policy).to(device="cpu", dtype=dtype).eval()


def _check_dtype(dtype: torch.dtype) -> None:
    if dtype not in _NUMPY:
        raise ExportError(f"export is float32 or float64, not {dtype}")


@contextlib.contextmanager
def _quiet_exporter() -> Iterator[None]:
    # The ONNX exporter logs a warning per missing optional library (torchvision), and torch
    # warns about its own deprecated internals: neither is the user's business.
    logger = logging.getLogger("torch.onnx")
    level = logger.level
    logger.setLevel(logging.ERROR)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", FutureWarning)
            yield
    finally:
        logger.setLevel(level)


class Signature:
    r"""What the exported graph of a policy computes, asked of its space: states
    (B, space.dim) to velocities (B, space.tangent_dim), user units (a pose policy: poses
    (B, 7) to twists (B, 6)); and the random states that check it.

    A velocity's components are compared in the units of the policy's chart (divided by
    :meth:`~snds.policy.Policy.chart_scales`, one per block: 1 for positions, :math:`L_p`
    and :math:`L_r` for a twist), where the top speed of the normalisation is the floor.

    Arguments:
        policy: The policy.
    """

    def __init__(self, policy: Policy) -> None:
        self.policy = policy
        self.space = policy.space
        #: Width of an input row.
        self.inputs = self.space.dim
        #: The name of the ONNX output: "twist" for a pose (linear and angular velocity),
        #: "velocity" otherwise (a phase model's velocity ends with the phase rate).
        self.output_name = (
            "twist" if "angular_velocity" in self.space.velocity_names else "velocity"
        )
        #: What the graph maps to what, in words.
        self.description = (
            f"(B, {self.space.dim}) {self.space.state_text} -> "
            f"(B, {self.space.tangent_dim}) {self.space.velocity_text}"
        )

    def module(self, dtype: torch.dtype) -> torch.nn.Module:
        """The module to trace, in ``dtype``."""
        return _Exported(self.policy, dtype)

    def library(self, x: torch.Tensor) -> torch.Tensor:
        """What the library computes at inputs (B, inputs), in their dtype."""
        return _copy(self.policy, x.dtype)(x)

    def random_inputs(self, count: int, rng: np.random.Generator) -> np.ndarray:
        """States (count, space.dim): equal shares with positions uniform in the boxes of
        :data:`STATE_RADII` extents around the target (half-widths), in the order of the
        radii over and over; orientations (poses) uniform on SO(3)."""
        states = np.empty((count, self.inputs))
        extent = float(self.policy.extents()[0])
        for i, radius in enumerate(STATE_RADII):
            rows = slice(i, None, len(STATE_RADII))
            share = len(range(count)[rows])
            states[rows] = self.space.uniform(self.policy.target, radius * extent, share, rng)
        return states

    def extents(self, x: np.ndarray) -> np.ndarray:
        """Each input's largest position offset from the target, in extents, shape (B,)."""
        space, policy = self.space, self.policy
        offset = np.abs(space.positions(x) - space.positions(policy.target)).max(axis=-1)
        return offset / float(policy.extents()[0])

    def output_scale(self) -> np.ndarray:
        """Divisors (outputs,) of the outputs before they are compared with the top speed."""
        blocks = self.policy.chart_scales()[list(self.space.velocity_units)]
        return np.repeat(blocks, self.space.velocity_sizes)

    def metadata(self) -> dict[str, str]:
        """The ONNX file's metadata: what goes in and out, the target, the extents and top
        speeds of each component."""
        space, policy = self.space, self.policy
        speeds = _top_speed(policy) * policy.chart_scales()[list(space.velocity_units)]
        return {
            "snds.dim": str(space.tangent_dim),
            "snds.input": space.state_text,
            "snds.output": space.velocity_text,
            "snds.target": json.dumps([float(c) for c in policy.target]),
            **{
                _EXTENT_KEYS[name]: repr(float(value))
                for name, value in zip(space.error_names, policy.extents(), strict=True)
            },
            **{
                _SPEED_KEYS[name]: repr(float(value))
                for name, value in zip(space.velocity_names, speeds, strict=True)
            },
        }


#: The metadata key of each error component's extent (:attr:`~snds.spaces.Space.error_names`).
_EXTENT_KEYS = {"distance": "snds.extent", "angle": "snds.angle_extent"}
#: The metadata key of each velocity block's top speed.
_SPEED_KEYS = {
    "velocity": "snds.top_speed",
    "angular_velocity": "snds.top_angular_speed",
    "phase_rate": "snds.top_phase_rate",
}


def signature(policy: Policy) -> Signature:
    """The :class:`Signature` of a policy's export."""
    return Signature(policy)


def _trace(policy: Policy, dtype: torch.dtype) -> torch.export.ExportedProgram:
    kind = signature(policy)
    module = kind.module(dtype)
    example = torch.as_tensor(kind.random_inputs(4, np.random.default_rng(0)), dtype=dtype)
    batch = torch.export.Dim("batch", min=1)
    with torch.no_grad():
        return torch.export.export(module, (example,), dynamic_shapes={"x": {0: batch}})


def export_pt2(policy: Policy, path: str | Path, *, dtype: torch.dtype = torch.float32) -> Path:
    """Exports a policy with ``torch.export`` to a ``.pt2`` archive.

    Arguments:
        policy: The policy; it is copied, not changed.
        path: The file to write.
        dtype: Precision of the graph, its input and its output.

    Returns:
        The path written. Its program maps positions (B, n) to velocities (B, n), user units
        (a pose policy: poses (B, 7) to twists (B, 6), see :class:`Signature`).
    """
    _check_dtype(dtype)
    program = _trace(policy, dtype)
    # Example inputs would be stored with torch.save, a pickle; the program needs none.
    program.example_inputs = None
    path = Path(path)

    def write(tmp: Path) -> None:
        # Through a file object: torch.export.save warns about a file name not ending in .pt2.
        with open(tmp, "wb") as handle:
            torch.export.save(program, handle)

    atomic_write(path, write)
    return path


def _softplus_onnx(self, beta: float = 1.0, threshold: float = 20.0):
    # torch's softplus: log(1 + exp(beta u)) / beta, and u itself where beta u > threshold,
    # as max(u, 0) + log(1 + exp(-|u|)), which is exact in any precision. onnxruntime's own
    # Softplus has no float64 kernel, and its float32 one is scalar code: this form, of
    # vectorised operations, runs a batch of 10,000 states 20% faster (benchmarks/README.md).
    from onnxscript import ir
    from onnxscript import opset18 as op

    scaled = self if beta == 1.0 else op.Mul(self, op.CastLike(beta, self))
    tail = op.Log(op.Add(op.CastLike(1.0, self), op.Exp(op.Neg(op.Abs(scaled)))))
    value = op.Add(op.Relu(scaled), tail)
    if beta != 1.0:
        value = op.Div(value, op.CastLike(beta, self))
    if self.dtype == ir.DataType.FLOAT:
        # Above the threshold the tail, below exp(-20), is under half an ulp of the result:
        # float32 rounds to u without the cut-off.
        return value
    return op.Where(op.Greater(scaled, op.CastLike(threshold, self)), self, value)


def _leaky_relu_onnx(self, negative_slope: float = 0.01):
    # onnxruntime's LeakyRelu has no float64 kernel: there, max(u, slope u), the same for a
    # slope below 1 (the ICNN's smooth leaky activation uses 0.1).
    from onnxscript import ir
    from onnxscript import opset18 as op

    if self.dtype == ir.DataType.FLOAT:
        return op.LeakyRelu(self, alpha=negative_slope)
    # A float64 constant: CastLike of a Python number would round the slope to float32.
    slope = op.Constant(value=ir.tensor(np.array(negative_slope, dtype=np.float64)))
    return op.Max(self, op.Mul(self, slope))


def export_onnx(
    policy: Policy,
    path: str | Path,
    *,
    dtype: torch.dtype = torch.float32,
    start_rule: StartRule | None = None,
) -> Path:
    """Exports a policy to ONNX (opset 18), with a dynamic batch dimension.

    Arguments:
        policy: The policy; it is copied, not changed.
        path: The file to write.
        dtype: Precision of the graph, its input and its output.
        start_rule: How a model with a phase gives a new start its phase
            (:func:`snds.phase.start_rule`), written as ``snds.start_references`` (a JSON list
            of reference states) and ``snds.start_reach`` (user units): a new start takes the
            phase of the reference nearest to its position if within the reach, else 0.

    Returns:
        The path written. The graph maps ``x`` (B, n) to velocities (B, n), user units (a
        pose policy: poses (B, 7) to twists (B, 6), see :class:`Signature`); its metadata
        holds ``snds.dim``, ``snds.input`` and ``snds.output`` (what they are, in words),
        ``snds.target`` (a JSON list; a pose policy: position then quaternion),
        ``snds.extent`` (the demonstrations' largest distance from the target),
        ``snds.top_speed`` (user units per second), ``snds.dtype`` and ``snds.method``; a pose
        policy's also ``snds.angle_extent`` (radians) and ``snds.top_angular_speed`` (rad/s).
    """
    _check_dtype(dtype)
    starts = {} if start_rule is None else _start_metadata(policy, start_rule)
    try:
        import onnx
    except ImportError as error:
        raise ExportError(
            "ONNX export needs onnx and onnxscript: pip install 'snds[export]'"
        ) from error
    program = _trace(policy, dtype)
    kind = signature(policy)
    with _quiet_exporter():
        onnx_program = torch.onnx.export(
            program,
            input_names=[INPUT_NAME],
            output_names=[kind.output_name],
            dynamo=True,
            optimize=True,
            verbose=False,
            custom_translation_table={
                torch.ops.aten.softplus.default: _softplus_onnx,
                torch.ops.aten.leaky_relu.default: _leaky_relu_onnx,
                torch.ops.aten.scalar_tensor.default: _scalar_tensor_onnx,
                torch.ops.aten.matmul.default: _matmul_onnx,
                torch.ops.aten.atan2.default: _atan2_onnx,
            },
        )
    model = onnx_program.model_proto
    # The exporter names the batch dimension after its symbol (s77): a controller reads it.
    for value in [*model.graph.input, *model.graph.output]:
        value.type.tensor_type.shape.dim[0].dim_param = BATCH_NAME
    metadata = {
        **signature(policy).metadata(),
        "snds.dtype": str(dtype).removeprefix("torch."),
        "snds.method": policy.method,
        # A modulated policy (snds.obstacles) records its fixed obstacles.
        **getattr(policy, "export_metadata", dict)(),
        **starts,
    }
    for key, value in metadata.items():
        entry = model.metadata_props.add()
        entry.key, entry.value = key, value
    path = Path(path)
    atomic_write(path, lambda tmp: onnx.save(model, str(tmp)))
    return path


def _start_metadata(policy: Policy, rule: StartRule) -> dict[str, str]:
    """A start rule as ONNX metadata, or an error naming the shape."""
    references = np.asarray(rule.references, dtype=np.float64)
    dim = policy.space.dim
    if references.ndim != 2 or references.shape[1] != dim or not np.isfinite(references).all():
        raise ExportError(
            f"start references must be finite, of shape (K, {dim}); got {references.shape}"
        )
    return {
        "snds.start_references": json.dumps(references.tolist()),
        "snds.start_reach": repr(float(rule.reach)),
    }


def _scalar_tensor_onnx(
    s: float, dtype: int = 1, layout: str = "", device: str = "", pin_memory: bool = False
):
    # The stock translation makes a float32 constant of the Python number and casts it: a
    # float64 graph would compute with 2 pi, the decay rates and the normalisation rounded to
    # float32. Here the constant is made in its own dtype.
    from onnxscript import ir
    from onnxscript import opset18 as op

    return op.Constant(value=ir.tensor(np.array(s, dtype=ir.DataType(dtype).numpy())))


def _matmul_onnx(self, other):
    # A product with a vector (the ICNN's output weights, its linear term) as a product with
    # a one-column matrix: onnxruntime's MatMul with a 1-D operand is a slow path
    # (docs/design.md, "Export graph and latency"); the same maths.
    from onnxscript import opset18 as op

    if len(other.shape) != 1 or len(self.shape) < 2:
        return op.MatMul(self, other)
    axis = op.Constant(value_ints=[-1])
    return op.Squeeze(op.MatMul(self, op.Unsqueeze(other, axis)), axis)


def _atan2_onnx(self, other):
    # atan2(y, x) (the log map of a pose policy's orientation) from operations onnxruntime
    # runs in both precisions: it has no float64 Atan kernel. Float64 takes the float32 angle
    # and one Newton step, theta0 + tan(theta - theta0) with tan(theta - theta0) =
    # (y cos theta0 - x sin theta0) / (x cos theta0 + y sin theta0): the float32 error of
    # about 1e-7 leaves an error of its cube, below float64 rounding.
    from onnxscript import ir
    from onnxscript import opset18 as op

    y, x = self, other
    if self.dtype != ir.DataType.DOUBLE:
        return _atan2_float32(y, x)
    # atan2 is blind to a positive common factor: dividing by max(|y|, |x|) keeps the float32
    # cast from overflowing or flushing to zero.
    largest = op.Max(op.Abs(y), op.Abs(x))
    zero = op.CastLike(0.0, y)
    safe = op.Where(op.Greater(largest, zero), largest, op.CastLike(1.0, y))
    y_unit, x_unit = op.Div(y, safe), op.Div(x, safe)
    first = _atan2_float32(
        op.Cast(y_unit, to=ir.DataType.FLOAT), op.Cast(x_unit, to=ir.DataType.FLOAT)
    )
    first = op.Cast(first, to=ir.DataType.DOUBLE)
    cos, sin = op.Cos(first), op.Sin(first)
    numerator = op.Sub(op.Mul(y_unit, cos), op.Mul(x_unit, sin))
    # r cos(theta - theta0) ~ r = 1 after the division; 0 only at y = x = 0, where atan2 is 0.
    denominator = op.Add(op.Mul(x_unit, cos), op.Mul(y_unit, sin))
    step = op.Where(op.Greater(denominator, zero), op.Div(numerator, denominator), zero)
    angle = op.Add(first, step)
    # A y below float32's range (|y| < 1e-45 |x|) is cast to 0, which on the negative x axis
    # gives +pi for a negative y, where atan2 is -pi: the sign of the float64 y decides.
    wrong_side = op.And(op.Less(y, zero), op.Greater(angle, zero))
    # A float64 constant: a Python number would be made a float32 one and cast.
    turn = op.Constant(value=ir.tensor(np.array(2 * math.pi, dtype=np.float64)))
    return op.Where(wrong_side, op.Sub(angle, turn), angle)


def _atan2_float32(y, x):
    # atan(y / x) moved into the quadrant of (x, y); on the y axis, +-pi/2 (0 at the origin).
    # A y of -0 counts as +0 (pi, not -pi, on the negative x axis): the log map's y is a norm.
    from onnxscript import opset18 as op

    zero = op.CastLike(0.0, y)
    pi = op.CastLike(math.pi, y)
    base = op.Atan(op.Div(y, op.Where(op.Equal(x, zero), op.CastLike(1.0, y), x)))
    turned = op.Where(op.GreaterOrEqual(y, zero), op.Add(base, pi), op.Sub(base, pi))
    angle = op.Where(op.Less(x, zero), turned, base)
    return op.Where(op.Equal(x, zero), op.Mul(op.Sign(y), op.CastLike(math.pi / 2, y)), angle)


#: ``snds export --format`` choices.
FORMATS: dict[str, Callable[..., Path]] = {"onnx": export_onnx, "pt2": export_pt2}


#: Rows per thread below which :class:`OnnxPolicy` runs a batch whole: handing a chunk to a
#: thread costs tens of microseconds.
MIN_ROWS_PER_THREAD = 1024


class OnnxPolicy:
    """An exported policy in onnxruntime, as a function of NumPy positions (B, n).

    Two paths, both with one-thread sessions:

    * **One state per call** (the control loop) runs on input and output buffers bound to
      the session once (onnxruntime's IO binding): the state is copied in, the velocity
      copied out, and nothing else is allocated or converted, which saves ``session.run``'s
      own conversions on every call (docs/design.md).
    * **Batches** of at least ``threads x`` :data:`MIN_ROWS_PER_THREAD` states are split into
      ``threads`` contiguous chunks that run at the same time on the one session
      (onnxruntime releases the GIL and lets several threads run a session). The graph is
      mostly small element-wise operations, which onnxruntime's own intra-op threads do not
      split: with them, two threads took 10.7 ms on 10,000 states of the compact network
      where one took 11.6.

    Arguments:
        path: The ``.onnx`` file.
        threads: Threads for large batches (1: every call on the caller's thread).

    Raises:
        ExportError: Without onnxruntime, or for a file it cannot load.
    """

    def __init__(self, path: str | Path, *, threads: int = 1) -> None:
        try:
            import onnxruntime as ort
        except ImportError as error:
            raise ExportError(
                "running ONNX needs onnxruntime: pip install 'snds[export]'"
            ) from error
        if threads < 1:
            raise ExportError(f"threads must be >= 1, got {threads}")
        options = ort.SessionOptions()
        options.intra_op_num_threads = 1
        options.inter_op_num_threads = 1
        options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
        try:
            self.session = ort.InferenceSession(
                str(path), options, providers=["CPUExecutionProvider"]
            )
        except Exception as error:  # onnxruntime raises its own exception types
            raise ExportError(f"{path}: not a loadable ONNX model ({error})") from error
        first = self.session.get_inputs()[0]
        self.input_name = first.name
        self.dtype = np.float64 if first.type == "tensor(double)" else np.float32
        self.threads = threads
        self._pool = None
        self._lock = threading.Lock()
        self._bound: tuple | None = None

    def _bind(self, width: int):
        """Binds a one-row input buffer and its output buffer to the session, once."""
        import onnxruntime as ort

        x = np.zeros((1, width), dtype=self.dtype)
        y = self._run(x)
        binding = self.session.io_binding()
        binding.bind_ortvalue_input(self.input_name, ort.OrtValue.ortvalue_from_numpy(x))
        output = self.session.get_outputs()[0].name
        binding.bind_ortvalue_output(output, ort.OrtValue.ortvalue_from_numpy(y))
        self._bound = (x, y, binding)
        return self._bound

    def _run(self, x: np.ndarray) -> np.ndarray:
        return self.session.run(None, {self.input_name: x})[0]

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """Velocities (B, m) at positions (B, n), in the file's precision."""
        x = np.asarray(x, dtype=self.dtype)
        if x.ndim == 2 and x.shape[0] == 1:
            with self._lock:
                bound = self._bound
                if bound is None or bound[0].shape != x.shape:
                    bound = self._bind(x.shape[1])
                buffer, out, binding = bound
                np.copyto(buffer, x)
                self.session.run_with_iobinding(binding)
                return out.copy()
        if self.threads == 1 or x.ndim != 2 or len(x) < self.threads * MIN_ROWS_PER_THREAD:
            return self._run(x)
        if self._pool is None:
            from concurrent.futures import ThreadPoolExecutor

            self._pool = ThreadPoolExecutor(self.threads, thread_name_prefix="snds-onnx")
        chunks = np.array_split(np.ascontiguousarray(x), self.threads)
        return np.concatenate(list(self._pool.map(self._run, chunks)))


def load_onnx(path: str | Path, *, threads: int = 1) -> OnnxPolicy:
    """An onnxruntime session of an exported policy, as a function of NumPy positions.

    Arguments:
        path: The ``.onnx`` file.
        threads: Threads for large batches (see :class:`OnnxPolicy`).

    Returns:
        A function from positions (B, n) to velocities (B, n) (a pose file: poses (B, 7) to
        twists (B, 6)), in the file's precision.
    """
    return OnnxPolicy(path, threads=threads)


def load_pt2(path: str | Path) -> Callable[[np.ndarray], np.ndarray]:
    """A ``.pt2`` export as a function of NumPy positions (B, n) -> velocities (B, n).

    :func:`torch.export.load` would unpickle a tensor subclass; an snds export has none
    (see :func:`pickled_entries`), and this refuses a file that does.
    """
    path = Path(path)
    pickled = pickled_entries(path)
    if pickled:
        raise ExportError(f"{path}: holds pickled data ({pickled[0]}); refused")
    module = torch.export.load(str(path)).module()
    dtype = next(iter(module.state_dict().values())).dtype

    @torch.no_grad()
    def run(x: np.ndarray) -> np.ndarray:
        # A copy: the caller's array may be read-only, which torch cannot wrap.
        return module(torch.tensor(np.asarray(x), dtype=dtype)).numpy()

    return run


def pickled_entries(path: str | Path) -> list[str]:
    """Entries of a ``.pt2`` archive that would be unpickled on load (an snds export: none).

    Raises:
        ExportError: If the file is not a ``.pt2`` (zip) archive.
    """
    try:
        with zipfile.ZipFile(path) as archive:
            names = archive.namelist()
            configs = [
                n for n in names if n.endswith(("weights_config.json", "constants_config.json"))
            ]
            pickled = []
            for name in configs:
                config = json.loads(archive.read(name))
                for key, entry in config.get("config", {}).items():
                    if entry.get("use_pickle"):
                        pickled.append(f"{name}:{key}")
    except (zipfile.BadZipFile, OSError, json.JSONDecodeError) as error:
        raise ExportError(f"{path}: not a .pt2 archive ({error})") from error
    with zipfile.ZipFile(path) as archive:
        stored = [i.filename for i in archive.infolist() if i.file_size > 0]
    # torch.save files (.pt: sample inputs, or any pickle) and raw .pkl entries.
    return pickled + [n for n in stored if n.endswith((".pkl", ".pt"))]


def random_states(policy: Policy, count: int, *, seed: int = 0) -> np.ndarray:
    """Random inputs of a policy's export, in boxes around the target of 1 to 1000x the extent.

    Equal shares of the positions are drawn uniformly from the boxes of :data:`STATE_RADII`
    (half-widths, in units of the demonstrations' extent), so a check sees the data region,
    the space around it and states far beyond it. A pose policy's inputs are poses: such
    positions with orientations uniform on SO(3).

    Arguments:
        policy: Gives the target and the extent.
        count: Number of states.
        seed: Seed of the draw.

    Returns:
        Positions, shape (count, n), or poses (position, quaternion), shape (count, 7);
        float64.
    """
    return signature(policy).random_inputs(count, np.random.default_rng(seed))


#: The box of the data, in extents around the target (half-width): :class:`Check` reports the
#: differences inside it and beyond it apart, since far states have far larger velocities.
DATA_BOX = 1.0


@dataclass(frozen=True)
class Check:
    """The comparison of an exported model with the library.

    Attributes:
        path: The exported file.
        dtype: Its precision.
        samples: Number of random states.
        seed: Their seed.
        max_error: Largest difference relative to max(|library velocity|, top speed), over
            the states, the library in the export's precision: the criterion.
        max_error_float64: The same against the library in float64 (equal to ``max_error``
            for a float64 export): how far the export is from the exact policy.
        library_error: The library in the export's precision against itself in float64, on
            the same scale: the rounding that precision costs the library itself.
        max_abs_diff: Largest absolute difference of a velocity component, user units (of a
            twist's component for a pose policy: user units/s or rad/s).
        max_error_near: ``max_error`` over the states in the data's box (:data:`DATA_BOX`
            extents around the target; a pose policy: whose position is).
        max_abs_diff_near: ``max_abs_diff`` over those states.
        max_error_far: ``max_error`` over the states beyond the data's box (out to
            1000 extents).
        max_abs_diff_far: ``max_abs_diff`` over those states.
        max_speed_far: The largest velocity component there (what ``max_abs_diff_far`` is a
            difference of).
        tolerance: The accepted ``max_error``.
        passed: Whether ``max_error <= tolerance``, or, for a float32 export, whether
            ``max_error_float64 <= max(tolerance, ROUNDING_SLACK * library_error)``: the
            export is as close to the exact policy as the library in float32 is.
    """

    path: str
    dtype: str
    samples: int
    seed: int
    max_error: float
    max_error_float64: float
    library_error: float
    max_abs_diff: float
    max_error_near: float
    max_abs_diff_near: float
    max_error_far: float
    max_abs_diff_far: float
    max_speed_far: float
    tolerance: float
    passed: bool

    def to_dict(self) -> dict:
        """JSON-ready form."""
        return asdict(self)

    def summary(self) -> str:
        """The differences in words, the data's box and far out apart."""
        return (
            f"largest difference from the library ({self.dtype}, {self.samples} random states): "
            f"in the data's box {self.max_error_near:.2e} relative, {self.max_abs_diff_near:.2e} "
            f"absolute; beyond it, out to 1000x the extent, {self.max_error_far:.2e} relative, "
            f"{self.max_abs_diff_far:.2e} absolute (of velocities up to {self.max_speed_far:.2e})"
        )


def verify(
    path: str | Path,
    policy: Policy,
    *,
    samples: int = 10_000,
    seed: int = 0,
    tolerance: float | None = None,
) -> Check:
    """Runs an exported model on random states and compares it with the library.

    The library is evaluated in the exported file's precision, on the same inputs: a pose
    policy's export on random poses (orientations uniform on SO(3)) against its
    :meth:`~snds.se3.PosePolicy.forward`.

    Arguments:
        path: An ``.onnx`` or ``.pt2`` file written by this module.
        policy: The policy it was exported from.
        samples: Number of states (see :func:`random_states`).
        seed: Seed of the states.
        tolerance: Accepted relative difference; :data:`TOLERANCE` of the dtype by default.

    Returns:
        The comparison.
    """
    path = Path(path)
    run = load_onnx(path) if path.suffix == ".onnx" else load_pt2(path)
    probe = np.asarray(run(random_states(policy, 1, seed=seed)))
    dtype = torch.float64 if probe.dtype == np.float64 else torch.float32
    return compare(
        run, policy, path=path, dtype=dtype, samples=samples, seed=seed, tolerance=tolerance
    )


def compare(
    run: Callable[[np.ndarray], np.ndarray],
    policy: Policy,
    *,
    path: str | Path,
    dtype: torch.dtype,
    samples: int = 10_000,
    seed: int = 0,
    tolerance: float | None = None,
) -> Check:
    """Compares a function of states (B, space.dim) -> velocities, in ``dtype``, with the
    library in the same precision on :func:`random_states` (see :func:`verify`).

    Arguments:
        run: The exported policy.
        policy: The policy it was exported from.
        path: The file it came from (recorded).
        dtype: Its precision.
        samples: Number of states.
        seed: Their seed.
        tolerance: Accepted relative difference; :data:`TOLERANCE` of the dtype by default.
    """
    kind = signature(policy)
    states = random_states(policy, samples, seed=seed).astype(_NUMPY[dtype])
    exported = np.asarray(run(states), dtype=np.float64)
    with torch.no_grad():
        reference = kind.library(torch.as_tensor(states)).double().numpy()
        exact = kind.library(torch.as_tensor(states).double()).numpy()
    difference = np.abs(exported - reference)
    near = kind.extents(states) <= DATA_BOX
    max_error = _relative_error(exported, reference, policy)
    if not np.all(np.isfinite(exported)):
        max_error = math.inf
    limit = TOLERANCE[dtype] if tolerance is None else tolerance
    max_error_float64 = _relative_error(exported, exact, policy)
    library_error = _relative_error(reference, exact, policy)
    passed = max_error <= limit or (
        dtype == torch.float32 and max_error_float64 <= max(limit, ROUNDING_SLACK * library_error)
    )

    def largest(values: np.ndarray) -> float:
        return float(values.max()) if values.size else 0.0

    return Check(
        path=str(path),
        dtype=str(dtype).removeprefix("torch."),
        samples=int(samples),
        seed=int(seed),
        max_error=max_error,
        max_error_float64=max_error_float64,
        library_error=library_error,
        max_abs_diff=largest(difference),
        max_error_near=_relative_error(exported[near], reference[near], policy),
        max_abs_diff_near=largest(difference[near]),
        max_error_far=_relative_error(exported[~near], reference[~near], policy),
        max_abs_diff_far=largest(difference[~near]),
        max_speed_far=largest(np.abs(reference[~near])),
        tolerance=float(limit),
        passed=bool(passed),
    )


def _relative_error(values: np.ndarray, reference: np.ndarray, policy: Policy) -> float:
    """Largest |values - reference| / max(|reference|, top speed) over states (B, m), the
    outputs divided by :meth:`Signature.output_scale` first."""
    if not values.size:
        return 0.0
    divisors = signature(policy).output_scale()
    values, reference = values / divisors, reference / divisors
    # The floor at the top speed: next to the target velocities vanish, and a difference of
    # rounding size relative to a vanishing velocity would say nothing about the model.
    scale = np.maximum(np.linalg.norm(reference, axis=-1), _top_speed(policy))
    return float(np.max(np.linalg.norm(values - reference, axis=-1) / scale))


def _top_speed(policy: Policy) -> float:
    """The normalisation's unit of speed (the demonstrations' top speed), user units/s (a
    pose policy: of its scaled state)."""
    return float(policy.normalization.length / policy.normalization.time)
