import dataclasses

import numpy as np
import pytest
import torch

from snds.policy import RECTIFIERS, project

from conftest import SMALL, make_policy


def _scrambled(policy):
    # Random weights far from initialisation: the guarantee must not depend on training.
    with torch.no_grad():
        for p in policy.parameters():
            p.add_(0.5 * torch.randn_like(p))
    return policy


@pytest.mark.parametrize("warp_layers", [0, 3])
@pytest.mark.parametrize("rectifier", list(RECTIFIERS))
@pytest.mark.parametrize("scale", [1e-3, 1.0, 1e3])
def test_decrease_holds_at_random_and_far_points(spiral, rectifier, scale, warp_layers):
    # GIVEN a stable policy with arbitrary weights, in float64, with a convex or warped V
    config = dataclasses.replace(
        SMALL, rectifier=rectifier, decay_rate=0.5, warp_layers=warp_layers
    )
    policy = _scrambled(make_policy(spiral, config, seed=1))
    # WHEN it is evaluated at states up to 1e3 times the data's extent
    x = scale * torch.randn(20_000, 2, dtype=torch.float64)
    v, grad_v = policy.lyapunov.value_and_grad(x)
    pi = policy.field(x)
    # THEN V decreases at least at the promised rate everywhere
    lhs = (grad_v * pi).sum(-1)
    slack = 1e-9 * (grad_v.norm(dim=-1) * policy.nominal(x).norm(dim=-1) + v)
    assert (lhs <= -policy.decay(v, x) + slack).all()
    assert (policy.decay(v, x) >= 0.5 * v).all() and (v > 0).all()


@pytest.mark.parametrize("warp_layers", [0, 3])
def test_relaxed_mode_only_promises_non_increase(spiral, warp_layers):
    config = dataclasses.replace(SMALL, decay_rate=0.0, warp_layers=warp_layers)
    policy = _scrambled(make_policy(spiral, config, seed=2))
    x = torch.randn(10_000, 2, dtype=torch.float64)
    _, grad_v = policy.lyapunov.value_and_grad(x)
    lhs = (grad_v * policy.field(x)).sum(-1)
    # Rounding of the dot product only: a warped V's gradient reaches 1e3 here.
    slack = 1e-12 * grad_v.norm(dim=-1) * policy.nominal(x).norm(dim=-1)
    assert (lhs <= slack).all()


@pytest.mark.parametrize("warp_layers", [0, 3])
def test_target_is_an_equilibrium(spiral, warp_layers):
    config = dataclasses.replace(SMALL, warp_layers=warp_layers)
    policy = _scrambled(make_policy(spiral, config, seed=3))
    target = torch.tensor(spiral.target).unsqueeze(0)
    assert policy(target).abs().max().item() == 0.0
    # and continuous there: the speed shrinks in proportion to the distance to the target
    directions = torch.randn(100, 2, dtype=torch.float64)
    speed = [policy(target + r * directions).norm(dim=-1) for r in (1e-4, 1e-6)]
    assert (speed[1] <= 0.02 * speed[0]).all()


def test_project_leaves_fast_enough_fields_alone():
    grad_v = torch.tensor([[1.0, 0.0]], dtype=torch.float64)
    f = torch.tensor([[-2.0, 1.0]], dtype=torch.float64)
    decay = torch.tensor([1.0], dtype=torch.float64)
    # grad V . f = -2 <= -1: no correction with ReLU
    torch.testing.assert_close(project(f, grad_v, decay), f)
    # grad V . f = +3: the component along grad V is replaced so that grad V . pi = -a
    f = torch.tensor([[3.0, 1.0]], dtype=torch.float64)
    torch.testing.assert_close(project(f, grad_v, decay), torch.tensor([[-1.0, 1.0]]).double())


def test_project_is_safe_where_gradient_vanishes():
    f = torch.zeros(1, 2)
    out = project(f, torch.zeros(1, 2), torch.zeros(1))
    assert torch.isfinite(out).all() and (out == 0).all()


def test_user_units_match_model_units(spiral):
    policy = make_policy(spiral, seed=4)
    x = torch.randn(50, 2, dtype=torch.float64) * 5
    norm = policy.normalization
    expected = policy.field((x - torch.tensor(norm.center)) / norm.length) * (
        norm.length / norm.time
    )
    torch.testing.assert_close(policy(x), expected)


def test_unconstrained_policy_is_the_nominal_field(spiral):
    policy = make_policy(spiral, dataclasses.replace(SMALL, stable=False), seed=5)
    x = torch.randn(10, 2, dtype=torch.float64)
    torch.testing.assert_close(policy.field(x), policy.nominal(x))


def test_same_seed_same_policy(spiral):
    a, b = make_policy(spiral, seed=7), make_policy(spiral, seed=7)
    x = torch.randn(10, 2, dtype=torch.float64)
    assert torch.equal(a(x), b(x))


def test_a_policy_subclass_gets_units_and_a_default_zero_decay():
    # GIVEN the smallest Policy: x' = -x in model coordinates, no Lyapunov function
    from snds.data import Normalization
    from snds.policy import Policy

    class Contraction(Policy):
        kind = "contraction"

        def __init__(self, *, dim, normalization):
            super().__init__(dim=dim, normalization=normalization)
            self.scale = torch.nn.Parameter(torch.ones(()))
            self.lyapunov = None

        def field(self, x):
            return -self.scale * x

    norm = Normalization(center=np.array([1.0, 2.0]), length=4.0, time=0.5)
    policy = Contraction(dim=2, normalization=norm).double()
    # THEN user units go in and out: v = -(x - c) / length * (length / time)
    x = np.array([[5.0, 2.0], [1.0, 0.0]])
    np.testing.assert_allclose(policy.predict(x), -(x - norm.center) / norm.time)
    assert not policy.stable and policy.method == "contraction"
    v = torch.ones(3, dtype=torch.float64)
    assert torch.equal(policy.decay(v, torch.zeros(3, 2)), torch.zeros(3, dtype=torch.float64))


@pytest.mark.parametrize("warp_layers", [0, 3])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_no_velocity_spike_at_or_next_to_the_target(spiral, dtype, warp_layers):
    # GIVEN a policy whose V is a Bregman difference of O(1) terms (of a warp that shifts the
    # target by O(1)), and states at the target and within rounding distance of it, inside a
    # batch (where the target's row and the reference row g(0) round differently)
    config = dataclasses.replace(SMALL, warp_layers=warp_layers)
    policy = _scrambled(make_policy(spiral, config, seed=4)).to(dtype)
    eps = torch.finfo(dtype).eps
    near = torch.cat(
        [
            torch.zeros(1, 2),
            torch.randn(200, 2) * eps,
            torch.randn(200, 2) * eps**0.5,
        ]
    ).to(dtype)
    x = torch.cat([torch.randn(500, 2, dtype=dtype), near, torch.randn(500, 2, dtype=dtype)])
    with torch.no_grad():
        pi = policy.field(x)[500:-500]
        f = policy.nominal(x)[500:-500]
        speed = policy.field(torch.randn(2000, 2, dtype=dtype)).norm(dim=-1).max()
    # THEN the projection adds no 1/|grad V| blow-up of rounding noise: in exact arithmetic
    # |pi| <= |f| + a / |grad V|, and a / |grad V| ~ rho |x| / 2 vanishes at the target
    assert torch.isfinite(pi).all()
    assert pi[0].abs().max() <= 10 * eps * speed
    assert (pi.norm(dim=-1) <= f.norm(dim=-1) + 1e-4 * speed).all()


def test_near_target_decay_is_the_stated_profile_and_holds(spiral):
    config = dataclasses.replace(SMALL, decay_rate=0.5, decay_far=2.0, decay_near=3.0)
    policy = _scrambled(make_policy(spiral, config, seed=4))
    # By hand: rate 0.5 + 3 (1 - r / 0.2)_+ + 2 (r - 1)_+ at radii 0, 0.1, 0.2, 0.5 and 3.
    radii = torch.tensor([0.0, 0.1, 0.2, 0.5, 3.0], dtype=torch.float64)
    x = torch.stack([radii, torch.zeros_like(radii)], dim=-1)
    v = torch.ones(5, dtype=torch.float64)
    expected = torch.tensor([3.5, 2.0, 0.5, 0.5, 4.5], dtype=torch.float64)
    torch.testing.assert_close(policy.decay(v, x), expected)
    # The projection honours it: grad V . pi <= -a at random states near and far.
    x = torch.cat([0.05 * torch.randn(5000, 2), 5 * torch.randn(5000, 2)]).double()
    v, grad_v = policy.lyapunov.value_and_grad(x)
    lhs = (grad_v * policy.field(x)).sum(-1)
    slack = 1e-9 * (grad_v.norm(dim=-1) * policy.nominal(x).norm(dim=-1) + v)
    assert (lhs <= -policy.decay(v, x) + slack).all()


@pytest.mark.parametrize("warp_layers", [0, 3])
def test_field_terms_are_the_field_and_v_of_one_pass(spiral, warp_layers):
    policy = make_policy(spiral, dataclasses.replace(SMALL, warp_layers=warp_layers), seed=0)
    policy = policy.double()
    x = torch.randn(300, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    terms = policy.field_terms(x)
    value, grad = policy.lyapunov.value_and_grad(x)
    # V alone (no gradient through the warp) is the value of the pass with the gradient, up
    # to the last bits that a matrix product may round differently for another allocation.
    torch.testing.assert_close(policy.lyapunov(x), value, rtol=1e-13, atol=0)
    for got, wanted in zip(terms, (policy.field(x), policy.nominal(x), value, grad)):
        torch.testing.assert_close(got, wanted, rtol=1e-13, atol=0)


def test_data_kernel_lowers_the_rate_on_the_data_only_and_the_decrease_holds(spiral, tmp_path):
    from snds.models import load_model, save_model

    # GIVEN a policy whose anchors sit at (0.5, 0) and (-0.5, 0) (model coordinates)
    config = dataclasses.replace(
        SMALL, decay_rate=0.5, data_rate=0.02, data_radius=0.1, anchors=2, decay_near=0.0
    )
    policy = _scrambled(make_policy(spiral, config, seed=5))
    policy.set_anchors(torch.tensor([[0.5, 0.0], [0.0, 0.3], [-0.5, 0.0]], dtype=torch.float64))
    torch.testing.assert_close(policy.anchors, torch.tensor([[0.5, 0.0], [-0.5, 0.0]]).double())
    # THEN by hand: rate 0.02 on an anchor, 0.5 - 0.48 exp(-0.5) at 0.1 from one, 0.5 far
    x = torch.tensor([[0.5, 0.0], [-0.5, 0.1], [0.0, 0.7], [3.0, 0.0]], dtype=torch.float64)
    v = torch.ones(4, dtype=torch.float64)
    far = 0.5 + 2.0 * 2.0 - 0.48 * np.exp(-0.5 * 2.5**2 / 0.01)
    expected = torch.tensor([0.02, 0.5 - 0.48 * np.exp(-0.5), 0.5 - 0.48 * np.exp(-37.0), far])
    torch.testing.assert_close(policy.decay(v, x), expected.double())
    # and the projection honours it near the anchors and far away, with a rate of at least
    # min(rho, rho_data) everywhere
    x = torch.cat([0.5 + 0.1 * torch.randn(5000, 2), 5 * torch.randn(5000, 2)]).double()
    v, grad_v = policy.lyapunov.value_and_grad(x)
    lhs = (grad_v * policy.field(x)).sum(-1)
    slack = 1e-9 * (grad_v.norm(dim=-1) * policy.nominal(x).norm(dim=-1) + v)
    assert (lhs <= -policy.decay(v, x) + slack).all()
    assert (policy.decay(v, x) >= 0.02 * v * (1 - 1e-12)).all()
    # and the kernel only ever lowers the rate: with rho 0 (relaxed mode) it stays 0
    relaxed = dataclasses.replace(config, decay_rate=0.0, decay_far=0.0, data_rate=0.3)
    unforced = make_policy(spiral, relaxed, seed=5)
    unforced.set_anchors(torch.tensor([[0.5, 0.0], [-0.5, 0.0]], dtype=torch.float64))
    assert (unforced.decay(v, x) == 0).all()
    # and the anchors survive a save / load round trip
    save_model(policy, tmp_path / "m")
    loaded, _ = load_model(tmp_path / "m")
    torch.testing.assert_close(loaded.anchors.double(), policy.anchors)
    torch.testing.assert_close(loaded.decay(v, x).double(), policy.decay(v, x))


def test_data_kernel_equals_the_brute_force_nearest_anchor(spiral):
    # k(x) = exp(-d^2 / 2r^2) with d the distance to the nearest of 64 anchors, by all the
    # differences, at random states, on anchors (d = 0) and far away; float64 and float32
    config = dataclasses.replace(SMALL, anchors=64, data_radius=0.3)
    policy = make_policy(spiral, config, seed=1)
    generator = torch.Generator().manual_seed(3)
    policy.set_anchors(torch.randn(200, 2, generator=generator, dtype=torch.float64))
    x = torch.cat([torch.randn(500, 2, generator=generator, dtype=torch.float64), policy.anchors])
    x = torch.cat([x, 40 * x[:36]]).reshape(-1, 3, 2)  # 600 states
    for dtype, tolerance in ((torch.float64, 1e-12), (torch.float32, 1e-5)):
        d2 = (x.to(dtype)[..., None, :] - policy.anchors.to(dtype)).square().sum(-1).amin(-1)
        expected = torch.exp(-d2 / (2 * 0.3**2))
        kernel = policy._data_kernel(x.to(dtype))
        assert kernel.shape == x.shape[:-1] and kernel.dtype == dtype
        torch.testing.assert_close(kernel, expected, atol=tolerance, rtol=0)


def test_fit_places_the_anchors_on_the_training_states(spiral):
    from snds.data import split_samples
    from snds.train import TrainConfig, fit

    policy = make_policy(spiral, dataclasses.replace(SMALL, anchors=16), seed=0)
    split = split_samples(spiral, test_fraction=0.2, seed=0)
    fit(policy, spiral, split, TrainConfig(steps=2, seed=0), progress=False)
    train = np.concatenate([d.positions[m] for d, m in zip(spiral, split.train)])
    model = policy.normalization.positions_to_model(train)
    anchors = policy.anchors.numpy()
    # every anchor is a training state, first and last included
    distances = np.linalg.norm(anchors[:, None] - model[None], axis=-1).min(axis=1)
    assert distances.max() < 1e-6
    np.testing.assert_allclose(anchors[[0, -1]], model[[0, -1]], atol=1e-6)
