"""SEDS: every A_k + A_k^T < 0 by construction and on the stored numbers; it learns stable
systems; files round-trip."""

import dataclasses

import numpy as np
import pytest
import torch

from snds.data import Demonstration, Demonstrations, Normalization
from snds.data.demonstrations import split_samples
from snds.stability import CheckConfig, check_stability

from conftest import held_out_relative_mse

pytest.importorskip("sklearn", reason="SEDS needs the baselines extra (scikit-learn)")

from snds.baselines.mixture import MixtureConfig  # noqa: E402
from snds.baselines.seds import (  # noqa: E402
    SEDS,
    SEDSPolicy,
    _project_stable,
    _SEDSParameters,
)


def symmetric_part_eigenvalues(matrices: np.ndarray) -> np.ndarray:
    """Largest eigenvalue of A_k + A_k^T for every k, shape (K,)."""
    return np.linalg.eigvalsh(matrices + np.swapaxes(matrices, -1, -2)).max(-1)


@pytest.fixture(scope="module")
def fitted(spiral_split):
    demos, split = spiral_split
    return dataclasses.replace(SEDS(), max_components=4).fit(demos, split, seed=0)


def test_stored_matrices_are_stable_with_v_the_squared_norm(fitted):
    policy = fitted.policy
    matrices = policy.matrices.detach().numpy()
    assert (symmetric_part_eigenvalues(matrices) < 0).all()
    np.testing.assert_array_equal(policy.lyapunov.matrix.numpy(), np.eye(2))
    assert policy.lyapunov.quadratic == 1.0
    # The promised decay is the verified margin, at least 2 eps by construction.
    eps = SEDS().eps
    assert 2 * eps * (1 - 1e-6) <= float(policy.rate) <= -symmetric_part_eigenvalues(matrices).max()


def test_parametrisation_is_stable_for_any_parameter_values():
    # GIVEN arbitrary, even huge or tiny, unconstrained parameters
    generator = torch.Generator().manual_seed(0)
    for scale in (1e-6, 1.0, 1e3):
        params = _SEDSParameters(
            weights=np.full(3, 1 / 3),
            means=np.zeros((3, 2)),
            covariances=np.tile(np.eye(2), (3, 1, 1)),
            matrices=np.zeros((3, 2, 2)),
            eps=1e-3,
            reg_covar=1e-4,
        )
        with torch.no_grad():
            for p in params.parameters():
                p.copy_(scale * torch.randn(p.shape, generator=generator, dtype=p.dtype))
            # THEN every A_k + A_k^T <= -2 eps I and every covariance is positive definite
            a = params.matrices().numpy()
            assert (symmetric_part_eigenvalues(a) <= -2e-3 * (1 - 1e-6)).all()
            if scale <= 1:  # (beyond, exp of the log-diagonal of C_k overflows)
                assert (np.linalg.eigvalsh(params.covariances().numpy()) > 0).all()


def test_projection_keeps_admissible_matrices_and_fixes_the_others():
    rng = np.random.default_rng(0)
    raw = rng.normal(size=(5, 3, 3)) * 3
    factors, skew = _project_stable(raw, 1e-3)
    a = -(factors @ np.swapaxes(factors, -1, -2) + 1e-3 * np.eye(3)) + (
        skew - np.swapaxes(skew, -1, -2)
    )
    assert (symmetric_part_eigenvalues(a) < 0).all()
    # The skew part, which does not affect |x|^2, is kept.
    np.testing.assert_allclose(a - a.swapaxes(-1, -2), raw - raw.swapaxes(-1, -2))
    stable = -np.eye(3) + np.array([[0, 1, 0], [-1, 0, 0], [0, 0, 0]])
    factors, skew = _project_stable(stable[None], 1e-3)
    again = -(factors @ factors.swapaxes(-1, -2) + 1e-3 * np.eye(3)) + skew - skew.swapaxes(-1, -2)
    np.testing.assert_allclose(again[0], stable, atol=1e-12)


def test_the_fit_record_shows_the_optimisation_improved_it(fitted):
    record = fitted.record["seds"]
    assert record["mse"] <= record["mse_initial"] and record["status"] == "ok"


def test_curved_motion_uses_several_components_and_stays_stable():
    # x1' = -x1, x2' = -2 x2 + 3 x1^2 (closed form): paths that bulge, nonlinear field.
    times = np.linspace(0.0, 8.0, 300)
    demos = []
    for b in (-0.5, 0.0, 0.5):
        x1, x2 = np.exp(-times), (b + 3.0 * times) * np.exp(-2.0 * times)
        demos.append(
            Demonstration(
                positions=np.stack([x1, x2], 1),
                velocities=np.stack([-x1, -2 * x2 + 3 * x1**2], 1),
                times=times,
            )
        )
    demos = Demonstrations(tuple(demos), np.zeros(2))
    split = split_samples(demos, test_fraction=0.2, seed=0)
    fitted = dataclasses.replace(SEDS(), max_components=5, steps=200).fit(demos, split, seed=0)
    assert fitted.record["seds"]["components"] > 1
    assert held_out_relative_mse(fitted.policy, demos, split) < 0.1
    report = check_stability(fitted.policy, demos, CheckConfig(rollouts=100, samples=2000, seed=0))
    assert report.converged_fraction == 1.0 and report.decrease_violations == 0


def test_steps_bound_the_iterations(spiral_split):
    demos, split = spiral_split
    short = dataclasses.replace(SEDS(), max_components=4).fit(demos, split, seed=0, steps=2)
    assert short.record["seds"]["iterations"] <= 2


def test_unfitted_policy_rebuilds_from_its_config():
    norm = Normalization(center=np.zeros(3), length=2.0, time=1.0)
    policy = SEDSPolicy(dim=3, normalization=norm, config=MixtureConfig(components=2))
    assert policy.matrices.shape == (2, 3, 3) and policy.precision_factors.shape == (2, 3, 3)
    assert MixtureConfig(**policy.config.to_dict()) == policy.config
    x = torch.randn(7, 3)
    torch.testing.assert_close(policy(x), -x)  # the stable placeholder -x, in user units


def test_a_failed_optimisation_keeps_the_stable_initial_fit(spiral_split, monkeypatch):
    demos, split = spiral_split

    def broken(self, closure):
        closure()
        raise RuntimeError("cholesky failed")

    monkeypatch.setattr(torch.optim.LBFGS, "step", broken)
    fitted = dataclasses.replace(SEDS(), max_components=2).fit(demos, split, seed=0)
    record = fitted.record["seds"]
    assert record["status"].startswith("failed") and record["mse"] == record["mse_initial"]
    assert (symmetric_part_eigenvalues(fitted.policy.matrices.numpy()) < 0).all()
