r"""The default SNDS policy's ``forward`` as one fused graph, for a fast exported controller.

:class:`FusedStable` computes what :meth:`snds.policy.StablePolicy.forward` computes, with
the policy's constants folded (in float64, rounded once to the export's precision) and its
operations merged into fewer, larger ones: 116 ONNX nodes instead of the 168 that tracing the
library's ``forward`` gives for the default model (docs/robots-and-export.md), and a
one-state call's cost in onnxruntime follows the node count (docs/design.md, "Export graph
and latency"). It is a second statement of the policy's maths, kept for that latency, not
because tracing needs it: a policy it does not cover exports through the library's own
``forward`` (:class:`snds.export.graph.Exported`). Every export is compared with the
library's ``forward`` (:func:`snds.export.verify`, 10,000 states out to 1000x the data's
extent), so a change to the policy that this misses fails every export.
"""

from __future__ import annotations

import copy
import math

import torch

from snds.nn.lyapunov import Lyapunov, WarpedLyapunov
from snds.nn.mlp import FourierFeatures
from snds.policy import Policy, StablePolicy

__all__ = ["FourierInput", "FusedStable", "fusable", "fused_nominal"]


class FourierInput(torch.nn.Module):
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


def fused_nominal(policy: StablePolicy) -> torch.nn.Sequential:
    """f(x) - f(0) as one network: f(0) is folded into the last layer's bias, and Fourier
    features into the first layer (:class:`FourierInput`)."""
    layers = [copy.deepcopy(layer) for layer in policy.nominal_net]
    zero = torch.zeros(1, policy.dim, dtype=policy.center.dtype)
    layers[-1].bias -= policy.nominal_net(zero)[0]
    if isinstance(layers[0], FourierFeatures):
        layers[:2] = [FourierInput(layers[0], layers[1])]
    return torch.nn.Sequential(*layers)


class FusedStable(torch.nn.Module):
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
    the same kernels (see :class:`~snds.export.graph.Exported`). A state exactly at the
    target gets velocity 0 exactly.

    Arguments:
        exact: The policy (see :func:`fusable`), a float64 copy in eval mode on the CPU
            (:func:`snds.export.graph.policy_copy`); it is read, not kept.
        dtype: Precision of the graph.
    """

    def __init__(self, exact: StablePolicy, dtype: torch.dtype) -> None:
        super().__init__()
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
            nominal = fused_nominal(exact)
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


def fusable(policy: Policy) -> bool:
    """Whether :class:`FusedStable` computes this policy: a stable SNDS policy with the ReLU
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
