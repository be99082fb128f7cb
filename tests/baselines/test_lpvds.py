"""LPV-DS: the LMIs hold on the stored numbers, it learns stable systems, files round-trip."""

import dataclasses

import numpy as np
import pytest
import torch

from snds.data import Demonstration, Demonstrations, Normalization
from snds.data.demonstrations import split_samples
from snds.errors import SNDSError
from snds.stability import CheckConfig, check_stability

from conftest import held_out_relative_mse, lie_derivative_eigenvalues

pytest.importorskip("sklearn", reason="LPV-DS needs the baselines extra (scikit-learn)")
pytest.importorskip("cvxpy", reason="LPV-DS needs the baselines extra (cvxpy)")

from snds.baselines import lpvds  # noqa: E402
from snds.baselines.lpvds import (  # noqa: E402
    LPVDS,
    LPVDSPolicy,
    fit_lyapunov_matrix,
    lyapunov_matrix_from_factor,
    physically_consistent_mixture,
    similarity,
)
from snds.baselines.mixture import MixtureConfig  # noqa: E402


def curved_demos(count: int = 3, samples: int = 300) -> Demonstrations:
    """Demonstrations of the nonlinear stable system x1' = -x1, x2' = -2 x2 + 3 x1^2.

    Closed form: x1 = a e^-t, x2 = (b + 3 a^2 t) e^-2t; the paths bulge (not linear).
    """
    times = np.linspace(0.0, 8.0, samples)
    demos = []
    for b in np.linspace(-0.5, 0.5, count):
        x1 = np.exp(-times)
        x2 = (b + 3.0 * times) * np.exp(-2.0 * times)
        x = np.stack([x1, x2], axis=1)
        v = np.stack([-x1, -2.0 * x2 + 3.0 * x1**2], axis=1)
        demos.append(Demonstration(positions=x, velocities=v, times=times))
    return Demonstrations(tuple(demos), np.zeros(2), "curved")


@pytest.fixture(scope="module")
def fitted(spiral_split):
    demos, split = spiral_split
    return LPVDS().fit(demos, split, seed=0)


@pytest.fixture(scope="module")
def curved():
    demos = curved_demos()
    split = split_samples(demos, test_fraction=0.2, seed=0)
    return demos, split, LPVDS().fit(demos, split, seed=0)


def test_v_floor_is_the_smallest_eigenvalue_of_p(fitted):
    # (The LMIs and the verified rate: test_mixtures.py, for both mixture baselines.)
    policy = fitted.policy
    p = policy.lyapunov.matrix.detach().numpy()
    assert policy.lyapunov.quadratic == pytest.approx(np.linalg.eigvalsh(p).min())


def test_the_fit_record_names_its_components_and_programs(fitted):
    record = fitted.record["lpvds"]
    assert record["components"] >= 1 and record["fallbacks"] == []
    assert record["systems_program"]["status"] == "optimal"


def test_lyapunov_gradient_matches_autograd(fitted):
    x = torch.randn(50, 2, dtype=torch.float64, requires_grad=True)
    v, grad = fitted.policy.lyapunov.value_and_grad(x)
    (auto,) = torch.autograd.grad(fitted.policy.lyapunov(x).sum(), x)
    torch.testing.assert_close(grad, auto)
    torch.testing.assert_close(v, fitted.policy.lyapunov(x))


def test_bic_picks_several_components_and_they_fit_a_curved_motion_better(curved):
    demos, split, auto = curved
    assert auto.record["lpvds"]["components"] > 1
    assert (lie_derivative_eigenvalues(auto.policy) < 0).all()
    single = dataclasses.replace(LPVDS(), components=1).fit(demos, split, seed=0)
    assert single.record["lpvds"]["components"] == 1
    auto_error = held_out_relative_mse(auto.policy, demos, split)
    assert auto_error < 0.05
    assert auto_error < 0.5 * held_out_relative_mse(single.policy, demos, split)


def test_curved_motion_reaches_the_target(curved):
    demos, _, fitted = curved
    report = check_stability(fitted.policy, demos, CheckConfig(rollouts=100, samples=2000, seed=0))
    assert report.converged_fraction == 1.0 and report.decrease_violations == 0


def test_a_failed_lyapunov_program_falls_back_to_the_identity(spiral_split, monkeypatch):
    demos, split = spiral_split
    monkeypatch.setattr(lpvds, "fit_lyapunov_matrix", lambda *a, **k: (None, {"status": "x"}))
    fitted = dataclasses.replace(LPVDS(), max_components=2).fit(demos, split, seed=0)
    assert "P = I" in fitted.record["lpvds"]["fallbacks"]
    np.testing.assert_array_equal(fitted.policy.lyapunov.matrix.numpy(), np.eye(2))
    assert (lie_derivative_eigenvalues(fitted.policy) < 0).all()


def test_an_unverifiable_solution_is_refused(spiral_split, monkeypatch):
    # A "solver" whose answer violates the LMIs: every attempt fails the check, so no
    # policy is returned rather than an unstable one.
    demos, split = spiral_split

    def unstable(x, v, gamma, p, **kwargs):
        return np.tile(np.eye(x.shape[1]), (gamma.shape[1], 1, 1)), {"status": "optimal"}

    monkeypatch.setattr(lpvds, "fit_linear_systems", unstable)
    with pytest.raises(SNDSError, match="stability"):
        dataclasses.replace(LPVDS(), max_components=2).fit(demos, split, seed=0)


def test_unfitted_policy_is_stable_and_rebuilds_from_its_config():
    norm = Normalization(center=np.zeros(2), length=1.0, time=1.0)
    policy = LPVDSPolicy(dim=2, normalization=norm, config=MixtureConfig(components=4))
    assert policy.matrices.shape == (4, 2, 2) and policy.means.shape == (4, 2)
    x = torch.randn(10, 2)
    torch.testing.assert_close(policy(x), -x)
    assert MixtureConfig(**policy.config.to_dict()) == policy.config


def test_lyapunov_parametrisation_has_trace_n_and_the_eigenvalue_floor():
    generator = torch.Generator().manual_seed(0)
    for n in (2, 3):
        for _ in range(50):
            factor = torch.randn(n, n, dtype=torch.float64, generator=generator)
            factor[0] *= 1e-6  # nearly singular M: the floor must still hold
            p = lyapunov_matrix_from_factor(factor, 0.1)
            values = torch.linalg.eigvalsh(p)
            assert float(torch.trace(p)) == pytest.approx(n)
            assert values.min() >= 0.1 - 1e-12 and values.max() <= n


def test_the_p_estimate_finds_a_v_the_demonstrations_descend_where_identity_fails():
    # GIVEN samples of x' = A x, stable, whose symmetric part is indefinite: under V = |x|^2
    # a good share of them climb, but V = x^T P x with A^T P + P A < 0 exists.
    a = np.array([[-1.0, 6.0], [0.0, -1.0]])
    rng = np.random.default_rng(0)
    angles = rng.uniform(0, 2 * np.pi, 500)
    x = np.stack([np.cos(angles), np.sin(angles)], 1) * rng.uniform(0.1, 1, (500, 1))
    v = x @ a.T
    # WHEN P is estimated, with the paper's small reward w for descending samples, or none
    p, record = fit_lyapunov_matrix(x, v, min_eigenvalue=0.01, weight=1e-4, starts=3, seed=0)
    strict, strict_record = fit_lyapunov_matrix(
        x, v, min_eigenvalue=0.01, weight=0.0, starts=3, seed=0
    )
    # THEN 2 in 5 samples climb |x|^2, at most 1 in 50 climb V (w trades a few nearly flat
    # climbs for steeper descents elsewhere), and none with w = 0
    assert record["climbing_identity"] == pytest.approx(0.4, abs=0.05)
    assert record["climbing"] <= 0.02 and record["objective"] < record["objective_identity"]
    psi = ((x @ p) * v).sum(-1) / np.linalg.norm(x @ p, axis=1) / np.linalg.norm(v, axis=1)
    assert psi.max() < 0.05
    assert strict_record["climbing"] == 0 and ((x @ strict) * v).sum(-1).max() <= 0
    for matrix in (p, strict):
        assert np.trace(matrix) == pytest.approx(2)
        assert np.linalg.eigvalsh(matrix).min() >= 0.01 - 1e-12


def test_similarity_by_hand():
    x = np.array([[0.0, 0.0], [0.3, 0.4], [0.0, 0.0], [1.0, 0.0]])
    v = np.array([[1.0, 0.0], [2.0, 0.0], [-1.0, 0.0], [0.0, 0.0]])
    s = similarity(x, v, length_scale=0.5)
    assert s[0, 1] == pytest.approx(np.exp(-0.25 / 0.5))  # same direction, distance 0.5
    assert s[0, 2] == 0  # same place, opposite directions
    assert s[1, 1] == 1
    assert s[0, 3] == pytest.approx(0.5 * np.exp(-1 / 0.5))  # at rest: a half-match
    np.testing.assert_allclose(s, s.T)


def test_physically_consistent_clusters_separate_opposite_lanes():
    # GIVEN a hairpin: right along y = +0.1, then back left along y = -0.1
    t = np.linspace(-1, 1, 200)
    x = np.concatenate([np.stack([t, 0.1 + 0 * t], 1), np.stack([t[::-1], -0.1 + 0 * t], 1)])
    v = np.concatenate([np.tile([1.0, 0.0], (200, 1)), np.tile([-1.0, 0.0], (200, 1))])
    # WHEN two clusters are asked for
    mixture = physically_consistent_mixture(
        x, v, components=2, max_components=2, length_scale=0.1, reg_covar=1e-4, seed=0
    )
    # THEN each is one lane (a mixture over positions alone would split left from right)
    assert sorted(np.round(mixture.means[:, 1], 6)) == [-0.1, 0.1]
    np.testing.assert_allclose(mixture.weights, [0.5, 0.5])
    np.testing.assert_allclose(mixture.means[:, 0], [0, 0], atol=1e-12)


def test_paper_variants_fit_and_stay_stable(spiral_split):
    demos, split = spiral_split
    for features in ("position_velocity", "position"):
        for estimate in (True, False):
            method = dataclasses.replace(
                LPVDS(), features=features, estimate_lyapunov=estimate, max_components=3
            )
            fitted = method.fit(demos, split, seed=0)
            assert (lie_derivative_eigenvalues(fitted.policy) < 0).all()
            if not estimate:
                p = fitted.policy.lyapunov.matrix.numpy()
                np.testing.assert_array_equal(p, np.eye(2))
    with pytest.raises(ValueError, match="features"):
        LPVDS(features="velocity")
