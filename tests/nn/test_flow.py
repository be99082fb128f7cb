import pytest
import torch

from snds.errors import ConfigError
from snds.nn import EuclideanizingFlow, Lyapunov, WarpedLyapunov
from snds.policy import PolicyConfig, StablePolicy


def _warped(dim: int, seed: int) -> WarpedLyapunov:
    torch.manual_seed(seed)
    convex = Lyapunov(dim, hidden=(16, 16), quadratic=0.05)
    warp = EuclideanizingFlow(dim, layers=4, features=16, scale=1.0, seed=seed)
    lyapunov = WarpedLyapunov(convex, warp).double()
    # Weights far from the identity warp: the properties must not depend on training.
    with torch.no_grad():
        for p in lyapunov.parameters():
            p.add_(torch.randn_like(p))
    return lyapunov


def _shift_bound(warp: EuclideanizingFlow) -> float:
    """B with |phi(x) - x| <= B everywhere: each layer adds sqrt(2/m) cos(.) W, |cos| <= 1."""
    return sum(
        layer.amplitude * float((layer.weight * layer.transformed).detach().norm(dim=-1).sum())
        for layer in warp.layers
    )


@pytest.mark.parametrize("dim", [2, 3])
def test_warped_v_is_zero_at_the_target_only_and_radially_unbounded(dim):
    lyapunov = _warped(dim, seed=0)
    value, grad = lyapunov.value_and_grad(torch.zeros(1, dim, dtype=torch.float64))
    # V exactly; grad V_c(0) (and so grad V) to rounding, as for the convex V alone
    assert value.item() == 0.0 and grad.abs().max().item() < 1e-12
    # and in a batch, where the target's row rounds differently from the reference row
    x = torch.cat([torch.randn(100, dim, dtype=torch.float64), torch.zeros(1, dim).double()])
    value, grad = lyapunov.value_and_grad(x)
    assert value[-1].item() == 0.0 and grad[-1].abs().max().item() < 1e-12
    x = torch.randn(20_000, dim, dtype=torch.float64) * torch.logspace(-4, 4, 20_000)[:, None]
    value = lyapunov(x)
    assert (value > 0).all()
    # V >= d (|x| - 2B)^2: the additive couplings shift any state by at most B
    shift = _shift_bound(lyapunov.warp)
    floor = 0.05 * (x.norm(dim=-1) - 2 * shift).clamp_min(0) ** 2
    assert (value >= floor * (1 - 1e-9)).all()
    assert (floor > 0).any()  # the check reaches beyond the shift


@pytest.mark.parametrize("dim", [2, 3])
def test_warped_gradient_matches_autograd_and_is_differentiable(dim):
    lyapunov = _warped(dim, seed=1)
    x = torch.randn(256, dim, dtype=torch.float64, requires_grad=True)
    value, analytic = lyapunov.value_and_grad(x)
    (auto,) = torch.autograd.grad(value.sum(), x)
    # Scrambled weights make V and its gradient large (up to ~1e3): a relative tolerance.
    scale = float(auto.abs().max())
    torch.testing.assert_close(analytic, auto, rtol=1e-8, atol=1e-10 * scale)
    # Training differentiates the analytic gradient once more (in the weights and states).
    small = x[:4].detach().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda y: lyapunov.value_and_grad(y)[1], (small,))


def test_warped_v_has_no_critical_point_but_the_target():
    # grad V = J^T grad V_c(z), so grad V . J^-1 z = grad V_c(z) . z >= V_c(z) > 0 for z != 0
    # (convexity): grad V vanishes nowhere but at the target, and the projection is defined.
    lyapunov = _warped(2, seed=2)
    x = torch.randn(20_000, 2, dtype=torch.float64) * torch.logspace(-3, 3, 20_000)[:, None]
    value, grad = lyapunov.value_and_grad(x)
    y, caches = lyapunov.warp.forward_with_caches(torch.cat([x, x.new_zeros(1, 2)]))
    z = y - y[-1:]
    pulled = lyapunov.warp.solve(caches, z)[:-1]
    assert ((grad * pulled).sum(-1) >= value * (1 - 1e-9)).all()


def test_warp_starts_as_the_identity_so_a_warped_policy_starts_as_the_convex_one(spiral):
    from snds.data import Normalization

    def make(layers: int) -> StablePolicy:
        config = PolicyConfig(hidden=(16,), fourier_features=8, warp_layers=layers)
        normalization = Normalization.fit(spiral)
        return StablePolicy(dim=2, normalization=normalization, config=config, seed=3).double()

    x = torch.randn(500, 2, dtype=torch.float64)
    torch.testing.assert_close(make(4).field(x), make(0).field(x), rtol=1e-12, atol=1e-12)


def test_warp_needs_two_dimensions_and_valid_sizes(spiral):
    from snds.data import Normalization

    normalization = Normalization(center=[0.0], length=1.0, time=1.0)
    with pytest.raises(ConfigError, match="warp_layers needs a state of dimension >= 2"):
        StablePolicy(dim=1, normalization=normalization, config=PolicyConfig(warp_layers=2))
    for bad in ({"warp_layers": -1}, {"warp_features": 0}, {"warp_scale": 0.0}):
        with pytest.raises(ConfigError, match="warp_layers >= 0"):
            PolicyConfig(**bad)


def test_default_warp_is_four_layers_for_positions_and_none_elsewhere(spiral):
    from snds.data import Normalization
    from snds.policy import DEFAULT_WARP_LAYERS
    from snds.se3 import PoseConfig

    def built(dim: int, **fields) -> StablePolicy:
        normalization = Normalization(center=[0.0] * dim, length=1.0, time=1.0)
        return StablePolicy(dim=dim, normalization=normalization, config=PolicyConfig(**fields))

    # GIVEN the default architecture (warp_layers None)
    # THEN a position policy of dimension >= 2 gets the warp and stores the number it took
    for dim in (2, 3):
        policy = built(dim)
        assert policy.config.warp_layers == DEFAULT_WARP_LAYERS == 4
        assert isinstance(policy.lyapunov, WarpedLyapunov)
        assert len(policy.lyapunov.warp.layers) == 4
    # and 1-D states and behavioural cloning keep the convex V
    for policy in (built(1), built(2, stable=False)):
        assert policy.config.warp_layers == 0 and isinstance(policy.lyapunov, Lyapunov)
    # pose policies take the positions' default warp (the chart is 6-D)
    assert PoseConfig().warp_layers == DEFAULT_WARP_LAYERS
    # while an explicit number is taken as given
    assert built(2, warp_layers=0).config.warp_layers == 0
    assert built(2, stable=False, warp_layers=2).config.warp_layers == 2
