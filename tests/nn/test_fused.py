"""The training path's fused operations equal the reference path (snds.nn.fused)."""

import contextlib

import pytest
import torch

from snds.nn import ICNN, EuclideanizingFlow, Lyapunov, WarpedLyapunov, fused
from snds.nn.fused import sincos


@contextlib.contextmanager
def _reference():
    fused.ENABLED = False
    try:
        yield
    finally:
        fused.ENABLED = True


def test_sincos_values_are_torchs_and_its_gradients_check():
    angles = torch.randn(7, 5, dtype=torch.float64) * 4
    sin, cos = sincos(angles)
    assert torch.equal(sin, torch.sin(angles)) and torch.equal(cos, torch.cos(angles))
    x = angles.clone().requires_grad_()
    # outside torch.func, the direct call records the function's own backward node
    assert type(sincos(x)[0].grad_fn).__name__ == "SinCosBackward"
    assert torch.autograd.gradcheck(lambda a: sincos(a), (x,))
    assert torch.autograd.gradgradcheck(lambda a: sincos(a), (x,))
    # one output used alone
    assert torch.autograd.gradcheck(lambda a: sincos(a)[0] * 3, (x,))
    assert torch.autograd.gradcheck(lambda a: sincos(a)[1] ** 2, (x,))


def test_sincos_under_vmap():
    angles = torch.randn(3, 4, 5, dtype=torch.float64, requires_grad=True)
    sin, cos = torch.func.vmap(sincos)(angles)
    (sin * cos).sum().backward()
    assert torch.allclose(angles.grad, torch.cos(2 * angles.detach()), atol=1e-12)


# torch.jit.trace is deprecated, and still a tracer the fused path must stay out of.
@pytest.mark.filterwarnings("ignore:`torch.jit.trace` is deprecated:DeprecationWarning")
def test_the_fused_path_is_taken_only_where_autograd_records():
    assert fused.active()
    with torch.no_grad():
        assert not fused.active()
    with _reference():
        assert not fused.active()
    # nor while a graph is traced, in any grad mode (exports see the plain operations)
    seen = []

    def probe(x):
        seen.append(fused.active())
        return x * 2

    torch.jit.trace(probe, torch.ones(2))
    torch.export.export(_Probe(probe), (torch.ones(2),))
    assert seen and not any(seen)


class _Probe(torch.nn.Module):
    def __init__(self, fn):
        super().__init__()
        self.fn = fn

    def forward(self, x):
        return self.fn(x)


def _warped(dim: int, max_log_scale: float, seed: int) -> WarpedLyapunov:
    torch.manual_seed(seed)
    convex = Lyapunov(dim, hidden=(16, 16), quadratic=0.05)
    warp = EuclideanizingFlow(
        dim, layers=3, features=16, scale=1.0, max_log_scale=max_log_scale, seed=seed
    )
    lyapunov = WarpedLyapunov(convex, warp).double()
    with torch.no_grad():
        for p in lyapunov.parameters():
            p.add_(0.5 * torch.randn_like(p))
    return lyapunov


def _values_and_gradients(module: torch.nn.Module, compute) -> list[torch.Tensor]:
    module.zero_grad()
    outputs = compute()
    loss = sum(
        (out * torch.linspace(-1, 1, out.numel()).reshape(out.shape).double()).sum()
        for out in outputs
    )
    loss.backward()
    return [out.detach() for out in outputs] + [p.grad.clone() for p in module.parameters()]


def _assert_close(got: list[torch.Tensor], want: list[torch.Tensor]) -> None:
    # Relative to each tensor's size, at least 1: a gradient that is 0 in exact arithmetic
    # (the last layer's bias cancels in phi(x) - phi(0)) is rounding noise on both paths.
    for a, b in zip(got, want, strict=True):
        scale = max(float(b.abs().max()), 1.0)
        assert float((a - b).abs().max()) <= 1e-10 * scale


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("max_log_scale", [0.0, 2.0])
def test_fused_warped_v_equals_the_reference_with_its_parameter_gradients(dim, max_log_scale):
    lyapunov = _warped(dim, max_log_scale, seed=dim)
    x = torch.randn(64, dim, dtype=torch.float64)
    probe = torch.randn(64, dim, dtype=torch.float64)

    def compute():
        value, grad = lyapunov.value_and_grad(x)
        _, caches = lyapunov.warp.forward_with_caches(x)
        jvp = lyapunov.warp.jvp(caches, probe)
        solve = lyapunov.warp.solve(caches, probe)
        return value, grad, jvp, solve

    got = _values_and_gradients(lyapunov, compute)
    with _reference():
        want = _values_and_gradients(lyapunov, compute)
    _assert_close(got, want)


def test_fused_icnn_equals_the_reference_with_input_and_parameter_gradients():
    torch.manual_seed(0)
    icnn = ICNN(3, hidden=(16, 16, 8)).double()
    x = torch.randn(50, 3, dtype=torch.float64, requires_grad=True)

    def compute():
        x.grad = None
        value, grad = icnn.value_and_grad(x)
        return value, grad

    got = _values_and_gradients(icnn, compute)
    with _reference():
        want = _values_and_gradients(icnn, compute)
    _assert_close(got, want)
    # the analytic input gradient still matches autograd on the fused path
    assert torch.autograd.gradcheck(lambda y: icnn.value_and_grad(y)[1], (x,))
