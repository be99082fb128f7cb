"""Translations of torch operations to ONNX (onnxscript), where the stock ones lose
precision or speed in onnxruntime: each computes the same function as the torch operation,
in operations onnxruntime runs fast and in both precisions. :data:`TRANSLATIONS` is the
``custom_translation_table`` of :func:`snds.export.export_onnx`.

onnxscript is imported inside each function: it belongs to the ``export`` extra, and the
exporter calls these only while it writes a file.
"""

from __future__ import annotations

import math

import numpy as np
import torch

__all__ = [
    "TRANSLATIONS",
    "atan2",
    "atan2_float32",
    "leaky_relu",
    "matmul",
    "scalar_tensor",
    "softplus",
]


def softplus(self, beta: float = 1.0, threshold: float = 20.0):
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


def leaky_relu(self, negative_slope: float = 0.01):
    # onnxruntime's LeakyRelu has no float64 kernel: there, max(u, slope u), the same for a
    # slope below 1 (the ICNN's smooth leaky activation uses 0.1).
    from onnxscript import ir
    from onnxscript import opset18 as op

    if self.dtype == ir.DataType.FLOAT:
        return op.LeakyRelu(self, alpha=negative_slope)
    # A float64 constant: CastLike of a Python number would round the slope to float32.
    slope = op.Constant(value=ir.tensor(np.array(negative_slope, dtype=np.float64)))
    return op.Max(self, op.Mul(self, slope))


def scalar_tensor(
    s: float, dtype: int = 1, layout: str = "", device: str = "", pin_memory: bool = False
):
    # The stock translation makes a float32 constant of the Python number and casts it: a
    # float64 graph would compute with 2 pi, the decay rates and the normalisation rounded to
    # float32. Here the constant is made in its own dtype.
    from onnxscript import ir
    from onnxscript import opset18 as op

    return op.Constant(value=ir.tensor(np.array(s, dtype=ir.DataType(dtype).numpy())))


def matmul(self, other):
    # A product with a vector (the ICNN's output weights, its linear term) as a product with
    # a one-column matrix: onnxruntime's MatMul with a 1-D operand is a slow path
    # (docs/design.md, "Export graph and latency"); the same maths.
    from onnxscript import opset18 as op

    if len(other.shape) != 1 or len(self.shape) < 2:
        return op.MatMul(self, other)
    axis = op.Constant(value_ints=[-1])
    return op.Squeeze(op.MatMul(self, op.Unsqueeze(other, axis)), axis)


def atan2(self, other):
    # atan2(y, x) (the log map of a pose policy's orientation) from operations onnxruntime
    # runs in both precisions: it has no float64 Atan kernel. Float64 takes the float32 angle
    # and one Newton step, theta0 + tan(theta - theta0) with tan(theta - theta0) =
    # (y cos theta0 - x sin theta0) / (x cos theta0 + y sin theta0): the float32 error of
    # about 1e-7 leaves an error of its cube, below float64 rounding.
    from onnxscript import ir
    from onnxscript import opset18 as op

    y, x = self, other
    if self.dtype != ir.DataType.DOUBLE:
        return atan2_float32(y, x)
    # atan2 is blind to a positive common factor: dividing by max(|y|, |x|) keeps the float32
    # cast from overflowing or flushing to zero.
    largest = op.Max(op.Abs(y), op.Abs(x))
    zero = op.CastLike(0.0, y)
    safe = op.Where(op.Greater(largest, zero), largest, op.CastLike(1.0, y))
    y_unit, x_unit = op.Div(y, safe), op.Div(x, safe)
    first = atan2_float32(
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


def atan2_float32(y, x):
    # atan(y / x) moved into the quadrant of (x, y); on the y axis, +-pi/2 (0 at the origin).
    # A y of -0 counts as +0 (pi, not -pi, on the negative x axis): the log map's y is a norm.
    from onnxscript import opset18 as op

    zero = op.CastLike(0.0, y)
    pi = op.CastLike(math.pi, y)
    base = op.Atan(op.Div(y, op.Where(op.Equal(x, zero), op.CastLike(1.0, y), x)))
    turned = op.Where(op.GreaterOrEqual(y, zero), op.Add(base, pi), op.Sub(base, pi))
    angle = op.Where(op.Less(x, zero), turned, base)
    return op.Where(op.Equal(x, zero), op.Mul(op.Sign(y), op.CastLike(math.pi / 2, y)), angle)


#: The translations :func:`snds.export.export_onnx` hands the exporter, by torch operation.
TRANSLATIONS = {
    torch.ops.aten.softplus.default: softplus,
    torch.ops.aten.leaky_relu.default: leaky_relu,
    torch.ops.aten.scalar_tensor.default: scalar_tensor,
    torch.ops.aten.matmul.default: matmul,
    torch.ops.aten.atan2.default: atan2,
}
