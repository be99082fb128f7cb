"""State spaces: one behavioural test per property, parametrised over every space, and the one
pipeline (check, accuracy) run on a policy of each."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from snds.data import no_split
from snds.data.poses import with_synthetic_orientations
from snds.evaluate import accuracy
from snds.methods import make_policy
from snds.models import load_model, save_model
from snds.policy import float64_copy
from snds.spaces import SE3, Euclidean, Space
from snds.stability import CheckConfig, check_stability, decrease_violations

from conftest import SMALL, spiral_demos

SPACES = [Euclidean(1), Euclidean(2), Euclidean(3), SE3()]


def _states(space: Space, count: int, seed: int) -> torch.Tensor:
    rng = np.random.default_rng(seed)
    center = np.zeros(space.dim)
    if space.dim > space.position_dim:
        center[-1] = 1.0  # the identity quaternion
    return torch.as_tensor(space.uniform(center, 2.0, count, rng))


@pytest.mark.parametrize("space", SPACES, ids=repr)
def test_a_zero_step_stays_and_a_state_is_at_zero_error_from_itself(space: Space) -> None:
    x = _states(space, 200, 0)
    v = torch.randn(200, space.tangent_dim, dtype=x.dtype)
    assert torch.allclose(space.advance(x, torch.zeros(200, dtype=x.dtype), v), x, atol=1e-15)
    errors = space.errors(x, x)
    assert errors.shape == (200, len(space.error_names))
    assert errors.abs().max() < 1e-7


@pytest.mark.parametrize("space", SPACES, ids=repr)
def test_errors_are_symmetric_and_nonnegative(space: Space) -> None:
    x, y = _states(space, 300, 1), _states(space, 300, 2)
    assert (space.errors(x, y) >= 0).all()
    assert torch.allclose(space.errors(x, y), space.errors(y, x), atol=1e-12)


@pytest.mark.parametrize("space", SPACES, ids=repr)
def test_two_half_steps_along_a_constant_velocity_make_one_step(space: Space) -> None:
    # A constant velocity (a world-frame twist for poses) is a one-parameter group: the
    # step of 2h is two steps of h.
    x = _states(space, 100, 3)
    v = torch.randn(100, space.tangent_dim, dtype=x.dtype)
    h = torch.full((100,), 0.3, dtype=x.dtype)
    once = space.advance(x, 2 * h, v)
    twice = space.advance(space.advance(x, h, v), h, v)
    assert space.errors(once, twice).max() < 1e-12


@pytest.mark.parametrize("space", SPACES, ids=repr)
def test_random_states_lie_in_the_box_and_on_the_space(space: Space) -> None:
    rng = np.random.default_rng(4)
    center = np.arange(space.dim, dtype=float)
    for draw in (space.uniform, space.grid):
        x = draw(center, 0.5, 64, rng)
        assert x.shape[1] == space.dim and len(x) >= 64
        offset = np.abs(space.positions(x) - space.positions(center))
        assert offset.max() <= 0.5 + 1e-12
        if space.dim > space.position_dim:  # unit quaternions
            np.testing.assert_allclose(np.linalg.norm(x[:, 3:], axis=1), 1.0, atol=1e-12)
    grid = space.grid(center, 0.5, 64, rng)
    corner = space.positions(center) + 0.5
    assert np.isclose(space.positions(grid), corner).all(axis=1).any()


@pytest.mark.parametrize("space", SPACES, ids=repr)
def test_scales_have_one_entry_per_component(space: Space) -> None:
    assert space.error_scales(2.0).shape == (len(space.error_names),)
    assert space.error_scales(2.0)[0] == 2.0
    assert space.tangent_scales(2.0).shape == (space.tangent_dim,)
    assert sum(space.velocity_sizes) == space.tangent_dim
    assert len(space.velocity_names) == len(space.velocity_sizes)


def _demos(space: str):
    """Two spiral demonstrations: 2-D or 3-D positions, or lifted to poses."""
    demos = spiral_demos(count=2, samples=150, dim=3 if space == "positions-3d" else 2)
    if space == "poses":
        demos = with_synthetic_orientations(demos, target_orientation=(0.0, 0.6, 0.0, 0.8), seed=1)
    return demos


@pytest.fixture(scope="module", params=["positions-2d", "poses"])
def task(request):
    demos = _demos(request.param)
    return demos, float64_copy(make_policy(demos, config=SMALL, seed=0))


def test_one_check_and_one_accuracy_serve_every_space(task) -> None:
    # GIVEN an untrained stable policy of positions, and one of poses
    demos, policy = task
    # WHEN the one stability check and the one accuracy run on it
    report = check_stability(policy, demos, CheckConfig(rollouts=20, samples=2000, seed=0))
    record = accuracy(policy, demos, no_split(demos))
    # THEN the guarantee holds in both spaces, and every space's error component is reported
    space = policy.space
    assert report.decrease_violations == 0 and report.samples_checked == 2000
    assert report.v_rises == 0
    assert set(report.max_final_errors) == set(space.error_names) == set(report.tolerances)
    assert report.tolerance == report.tolerances["distance"]
    assert record["dtw"] >= 0 and np.isfinite(record["velocity_mse"])
    for name in space.error_names[1:]:
        assert f"{name}_error_along" in record and f"final_{name}_error" in record
    for name in space.velocity_names[1:]:
        assert f"{name}_mse" in record


POLICIES = [
    pytest.param(space, stable, id=f"{space}-{'snds' if stable else 'bc'}")
    for space in ("positions-2d", "positions-3d", "poses")
    for stable in (True, False)
]


@pytest.mark.parametrize(("space", "stable"), POLICIES)
def test_every_policy_saves_exports_and_keeps_its_guarantee(space, stable, tmp_path) -> None:
    pytest.importorskip("onnxruntime", reason="the export leg needs the export extra")
    pytest.importorskip("onnxscript", reason="the export leg needs the export extra")
    from snds import export

    # GIVEN an untrained SNDS or BC policy of each kind of state, in float64
    demos = _demos(space)
    config = dataclasses.replace(SMALL, stable=stable)
    policy = float64_copy(make_policy(demos, config=config, seed=0))
    x = torch.as_tensor(export.random_states(policy, 2000, seed=0))
    # WHEN it is saved and loaded, and exported to ONNX
    save_model(policy, tmp_path / "model")
    loaded, _ = load_model(tmp_path / "model")
    path = export.export_onnx(policy, tmp_path / "policy.onnx", dtype=torch.float64)
    check = export.verify(path, policy, samples=2000)
    # THEN the loaded model and the exported graph compute the policy (states near the target
    # and up to 1,000 extents away), and a stable one's V decreases at every one of them
    assert torch.equal(loaded.double()(x), policy(x))
    assert check.passed and check.max_error <= 1e-9, check
    velocities = policy(x)
    assert velocities.shape == (2000, policy.space.tangent_dim)
    assert torch.isfinite(velocities).all()
    assert policy.stable is stable
    if stable:
        assert decrease_violations(policy, x) == 0
