"""The Gaussian-mixture baselines (LPV-DS, SEDS), one behaviour for both: a blend of stable
linear systems that learns a linear spiral almost exactly, reaches the target from random
starts, keeps V decreasing and the blend convex far from the data, fits other dimensions,
round-trips through files and repeats itself for a seed."""

import copy
import dataclasses

import numpy as np
import pytest
import torch

from snds.data import Demonstration, Demonstrations
from snds.data.demonstrations import split_samples
from snds.methods import METHODS, POLICY_KINDS, Method
from snds.stability import CheckConfig, check_stability

from conftest import held_out_relative_mse, lie_derivative_eigenvalues, spiral_demos

pytest.importorskip("sklearn", reason="the mixture baselines need the baselines extra")
pytest.importorskip("cvxpy", reason="LPV-DS needs the baselines extra (cvxpy)")

#: Each mixture baseline as these tests fit it: its default, at most 4 components.
MIXTURES: dict[str, Method] = {
    name: dataclasses.replace(METHODS[name], max_components=4) for name in ("lpvds", "seds")
}


@pytest.fixture(scope="module", params=list(MIXTURES))
def fitted(request, spiral_split):
    demos, split = spiral_split
    return request.param, MIXTURES[request.param].fit(demos, split, seed=0)


def test_registered_as_a_method_and_a_policy_kind(fitted):
    name, result = fitted
    assert METHODS[name].name == name and METHODS[name].has_lyapunov
    assert type(result.policy) is POLICY_KINDS[name]


def test_learns_a_linear_spiral_almost_exactly(fitted, spiral_split):
    demos, split = spiral_split
    assert held_out_relative_mse(fitted[1].policy, demos, split) < 0.01


def test_stored_systems_are_stable_and_the_promised_decay_is_verified(fitted):
    policy = fitted[1].policy
    p = policy.lyapunov.matrix.detach().numpy()
    np.testing.assert_array_equal(p, p.T)
    assert np.linalg.eigvalsh(p).min() > 0
    assert (lie_derivative_eigenvalues(policy) < 0).all()
    assert 0 < float(policy.rate) <= -lie_derivative_eigenvalues(policy).max()


def test_reaches_the_target_from_random_starts(fitted, spiral_split):
    demos, _ = spiral_split
    report = check_stability(fitted[1].policy, demos, CheckConfig(rollouts=100, samples=2000))
    assert report.converged_fraction == 1.0
    assert report.decrease_violations == 0 and report.samples_checked == 2000


def test_decrease_and_responsibilities_hold_far_from_the_data(fitted):
    # GIVEN states up to 1e3 times the data's extent, in float64
    policy = copy.deepcopy(fitted[1].policy).to(torch.float64)
    x = 1e3 * torch.randn(5000, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        gamma = policy.responsibilities(x)
        v, grad_v = policy.lyapunov.value_and_grad(x)
        xdot = policy.field(x)
    # THEN the blend is a convex combination, V is the quadratic and it decreases as promised
    assert torch.isfinite(gamma).all() and torch.isfinite(xdot).all()
    torch.testing.assert_close(gamma.sum(-1), torch.ones(5000, dtype=torch.float64))
    torch.testing.assert_close(v, torch.einsum("bi,ij,bj->b", x, policy.lyapunov.matrix, x))
    lhs = (grad_v * xdot).sum(-1)
    assert (lhs <= -policy.decay(v, x) + 1e-9 * grad_v.norm(dim=-1) * xdot.norm(dim=-1)).all()


def test_same_seed_gives_the_same_fit(fitted, spiral_split):
    name, result = fitted
    demos, split = spiral_split
    again = MIXTURES[name].fit(demos, split, seed=0)
    for key, tensor in result.policy.state_dict().items():
        torch.testing.assert_close(again.policy.state_dict()[key], tensor, rtol=0, atol=0)


def line_demos() -> Demonstrations:
    """1-D demonstrations of x' = -x from both sides of the target."""
    times = np.linspace(0.0, 5.0, 200)
    return Demonstrations(
        tuple(
            Demonstration(
                positions=(s * np.exp(-times))[:, None],
                velocities=(-s * np.exp(-times))[:, None],
                times=times,
            )
            for s in (1.0, -2.0)
        ),
        np.zeros(1),
    )


@pytest.mark.parametrize("name", list(MIXTURES))
@pytest.mark.parametrize("dim", [1, 3])
def test_other_dimensions(name, dim):
    demos = line_demos() if dim == 1 else spiral_demos(dim=dim)
    split = split_samples(demos, test_fraction=0.2, seed=0)
    method = dataclasses.replace(MIXTURES[name], max_components=3)
    fitted = method.fit(demos, split, seed=0, steps=100)
    assert (lie_derivative_eigenvalues(fitted.policy) < 0).all()
    assert held_out_relative_mse(fitted.policy, demos, split) < 0.01
    report = check_stability(fitted.policy, demos, CheckConfig(rollouts=30, samples=500, seed=0))
    assert report.converged_fraction == 1.0 and report.decrease_violations == 0
