"""SDS-EF: the flow is a bijection with the right Jacobian, V decreases, it learns, it saves."""

import copy
import dataclasses

import numpy as np
import pytest
import torch

from snds.baselines.sdsef import SDSEF, SDSEFConfig, SDSEFPolicy
from snds.data import Demonstration, Demonstrations, Normalization
from snds.data.demonstrations import Split, split_samples
from snds.errors import DataError
from snds.methods import METHODS, POLICY_KINDS
from snds.stability import CheckConfig, check_stability
from snds.train import TrainConfig

from conftest import held_out_relative_mse

SMALL = SDSEFConfig(layers=4, features=16, speed_features=16, max_log_scale=0.0)
#: Affine couplings (RealNVP-style, bounded log-scale) and additive ones (NICE-style).
VARIANTS = {"affine": dataclasses.replace(SMALL, max_log_scale=2.0), "additive": SMALL}


def unit_normalization(dim: int) -> Normalization:
    return Normalization(center=np.zeros(dim), length=1.0, time=1.0)


def scrambled(config: SDSEFConfig, dim: int = 2, seed: int = 0, size: float = 0.3) -> SDSEFPolicy:
    """A float64 policy with random weights: the guarantee must not depend on training."""
    policy = SDSEFPolicy(dim=dim, normalization=unit_normalization(dim), config=config, seed=seed)
    policy = policy.double()
    generator = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in policy.parameters():
            p.add_(size * torch.randn(p.shape, generator=generator, dtype=p.dtype))
    return policy


def gaussian(*shape: int, seed: int = 0) -> torch.Tensor:
    """Seeded float64 normal samples (the global generator differs between processes)."""
    return torch.randn(*shape, dtype=torch.float64, generator=torch.Generator().manual_seed(seed))


def relative_error(value: torch.Tensor, expected: torch.Tensor) -> float:
    """Largest per-sample |value - expected| / |expected|, over all but the first axis."""
    value, expected = value.detach(), expected.detach()
    difference = (value - expected).flatten(1).norm(dim=-1)
    return float((difference / expected.flatten(1).norm(dim=-1)).max())


def warped_demos(count: int = 4, samples: int = 150) -> Demonstrations:
    r"""Demonstrations of a system SDS-EF can represent: straight latent lines, bent.

    With :math:`\psi(x) = (x_1, x_2 + \sin 3 x_1)` and :math:`\dot z = -z`,
    :math:`x(t) = \psi^{-1}(z_0 e^{-t})`: the paths wiggle (a sine along x_1) and all end at 0.
    """
    times = np.linspace(0.0, 7.0, samples)
    demos = []
    for angle in np.linspace(0.3, 2.8, count):
        z = np.array([np.cos(angle), np.sin(angle)]) * np.exp(-times)[:, None]
        x = np.stack([z[:, 0], z[:, 1] - np.sin(3.0 * z[:, 0])], axis=1)
        v = np.stack([-z[:, 0], -z[:, 1] + 3.0 * np.cos(3.0 * z[:, 0]) * z[:, 0]], axis=1)
        demos.append(Demonstration(positions=x, velocities=v, times=times))
    return Demonstrations(tuple(demos), np.zeros(2), "warped")


@pytest.fixture(scope="module")
def trained() -> tuple[SDSEFPolicy, Demonstrations, Split]:
    demos = warped_demos()
    split = split_samples(demos, test_fraction=0.2, seed=0)
    config = SDSEFConfig(layers=6, features=64, max_log_scale=0.0)
    method = SDSEF(
        policy_config=config, train_config=TrainConfig(steps=600, batch_size=256, lr=1e-2)
    )
    fitted = method.fit(demos, split, seed=0)
    assert fitted.seconds > 0 and fitted.record["train_result"]["steps"] == 600
    return fitted.policy, demos, split


@pytest.mark.parametrize("variant", list(VARIANTS))
@pytest.mark.parametrize("dim", [2, 3, 6])
def test_flow_is_a_bijection_with_positive_jacobian(variant, dim):
    # GIVEN a flow with random weights, in float64
    flow = scrambled(VARIANTS[variant], dim=dim, seed=dim).flow
    x = 2.0 * gaussian(500, dim, seed=dim)
    # THEN phi^-1(phi(x)) = x and det J_phi > 0 at every sampled state
    torch.testing.assert_close(flow.inverse(flow(x)), x, rtol=0, atol=1e-9)
    sign, _ = torch.linalg.slogdet(flow.jacobian(x))
    assert (sign > 0).all()


@pytest.mark.parametrize("variant", list(VARIANTS))
@pytest.mark.parametrize("dim", [2, 3])
def test_analytic_jacobian_gradient_and_solve_equal_autograd(variant, dim):
    policy = scrambled(VARIANTS[variant], dim=dim, seed=10 + dim)
    flow = policy.flow
    x = gaussian(200, dim, seed=dim)
    # Errors relative to each sample's norm: entries of a row can differ by orders of
    # magnitude. Worst seen over 40 seeds: 2e-11 (Jacobian), 2e-13 (gradient), 1e-9 (field,
    # through a dense solve of a matrix with condition number up to 1e4).
    jacobian = torch.func.vmap(torch.func.jacrev(lambda z: flow(z.unsqueeze(0)).squeeze(0)))(x)
    assert relative_error(flow.jacobian(x), jacobian) < 1e-9
    # grad V analytically = autograd of V
    value, grad = policy.lyapunov.value_and_grad(x)
    xr = x.clone().requires_grad_()
    (autograd,) = torch.autograd.grad(policy.lyapunov(xr).sum(), xr)
    assert relative_error(grad, autograd) < 1e-10
    torch.testing.assert_close(value, policy.lyapunov(x), rtol=1e-12, atol=0)
    # the field is -k J^-1 (phi(x) - phi(0)), J^-1 by a dense solve
    latent = flow(x) - flow(torch.zeros(1, dim, dtype=torch.float64))
    expected = -policy.gain(x).unsqueeze(-1) * torch.linalg.solve(jacobian, latent)
    assert relative_error(policy.field(x), expected) < 1e-7


@pytest.mark.parametrize("variant", list(VARIANTS))
@pytest.mark.parametrize("scale", [1e-3, 1.0, 30.0, 1e3])
def test_lyapunov_decreases_at_random_and_far_points(variant, scale):
    # GIVEN SDS-EF with random weights, in float64, at states up to 1e3 x the data's extent
    policy = scrambled(VARIANTS[variant], seed=3)
    x = scale * gaussian(5000, 2, seed=int(scale))
    # WHEN V and the field are evaluated
    with torch.no_grad():
        value, grad = policy.lyapunov.value_and_grad(x)
        pi = policy.field(x)
        decay = policy.decay(value, x)
    # THEN V > 0 away from the target and decreases at least at the claimed rate k V (the
    # exact rate is 2 k V)
    assert (value > 0).all()
    assert (decay > 0).all()
    lhs = (grad * pi).sum(-1)
    if variant == "additive":
        assert (lhs <= -decay).all()
    else:
        # Far away the affine flow's Jacobian gets ill-conditioned (cond ~ |grad V| |pi| /
        # 2 k V reaches 1e20 at 1e3 extents), and grad V . pi is a cancellation no float64 sum
        # resolves: allow its rounding, as the stability check does.
        slack = 1e-9 * grad.norm(dim=-1) * pi.norm(dim=-1)
        assert (lhs <= -decay + slack).all()


def test_target_is_the_equilibrium_and_v_vanishes_only_there():
    policy = scrambled(VARIANTS["affine"], seed=4)
    zero = torch.zeros(3, 2, dtype=torch.float64)
    with torch.no_grad():
        assert policy.lyapunov(zero).abs().max().item() == 0.0
        assert policy.field(zero).abs().max().item() == 0.0
        # the user-unit wrapper: the target is the normalisation's center
        assert policy(policy.center.double().unsqueeze(0)).abs().max().item() == 0.0
        near = 1e-6 * gaussian(100, 2)
        assert (policy.lyapunov(near) > 0).all()


def test_field_works_without_autograd_in_float32_and_after_deepcopy():
    policy = SDSEFPolicy(dim=2, normalization=unit_normalization(2), config=SMALL)
    x = gaussian(10, 2).float()
    with torch.no_grad():
        assert policy.field(x).dtype == torch.float32
        copy64 = copy.deepcopy(policy).to(torch.float64)
        out = copy64.field(x.double())
    assert out.dtype == torch.float64
    torch.testing.assert_close(out.float(), policy.field(x).detach(), rtol=1e-4, atol=1e-6)
    # at initialisation phi is the identity: pi = -k0 x
    torch.testing.assert_close(out, -SMALL.gain * x.double())


def test_one_dimensional_states_are_refused_clearly():
    with pytest.raises(DataError, match="dimension >= 2"):
        SDSEFPolicy(dim=1, normalization=unit_normalization(1), config=SMALL)


def test_registered_as_a_method_and_a_policy_kind():
    assert METHODS["sdsef"].has_lyapunov and METHODS["sdsef"].name == "sdsef"
    assert POLICY_KINDS["sdsef"] is SDSEFPolicy
    assert SDSEFConfig(**SMALL.to_dict()) == SMALL


def test_learns_a_warped_stable_system(trained):
    policy, demos, split = trained
    # held-out velocities within 1% of the mean squared speed (0.03-0.14% over seeds 0-2; the
    # untrained flow, pi = -x, is far off)
    assert held_out_relative_mse(policy, demos, split) < 0.01


def test_learned_policy_reaches_the_target_from_random_starts(trained):
    policy, demos, _ = trained
    report = check_stability(policy, demos, CheckConfig(rollouts=100, samples=2000, seed=0))
    assert report.converged_fraction == 1.0
    assert report.decrease_violations == 0 and report.samples_checked == 2000


def test_same_seed_gives_the_same_fit():
    demos = warped_demos(count=2, samples=100)
    split = split_samples(demos, test_fraction=0.2, seed=1)
    method = SDSEF(policy_config=SMALL, train_config=TrainConfig(steps=20, batch_size=64))
    first, second = (method.fit(demos, split, seed=5).policy for _ in range(2))
    for (name, a), (_, b) in zip(first.state_dict().items(), second.state_dict().items()):
        assert torch.equal(a, b), name
