"""SE(3) pose policies: quaternion maths, the double cover, SO(3) rollouts, learning a pose task."""

from __future__ import annotations

import numpy as np
import pytest
import roma
import torch
from scipy.spatial.transform import Rotation

from snds.data import no_split
from snds.data.poses import angular_velocities, with_synthetic_orientations
from snds.evaluate import accuracy
from snds.models import load_model, save_model
from snds.rollout import policy_guard, rollout, safe_velocity
from snds.se3 import PosePolicy, make_pose_policy
from snds.so3 import left_jacobian, left_jacobian_inverse, relative_rotvec, rotate
from snds.spaces import SE3
from snds.stability import CheckConfig, check_stability
from snds.steppers import Dynamics
from snds.train import TrainConfig, fit

from conftest import SMALL, spiral_demos

# One thread: these networks are tiny, and two threads on a busy 2-core machine spin-wait.
torch.set_num_threads(1)


def random_quats(count: int, seed: int = 0) -> torch.Tensor:
    return roma.random_unitquat(
        count, dtype=torch.float64, generator=torch.Generator().manual_seed(seed)
    )


@pytest.fixture(scope="module")
def pose_demos():
    # A decaying spiral in the plane, lifted to poses turning by ~90 degrees to the target.
    return with_synthetic_orientations(
        spiral_demos(count=2, samples=200), target_orientation=(0.0, 0.6, 0.0, 0.8), seed=1
    )


@pytest.fixture(scope="module")
def untrained(pose_demos) -> PosePolicy:
    policy = make_pose_policy(pose_demos, config=SMALL, seed=0)
    return policy.to(torch.float64).eval()


@pytest.fixture(scope="module")
def trained(pose_demos):
    torch.manual_seed(0)
    policy = make_pose_policy(pose_demos, config=SMALL, seed=0)
    # As snds train --se3 (the default recipe), shortened, at the rate this short fit was
    # written for.
    config = TrainConfig(steps=400, lr=1e-2, seed=0)
    fit(policy, pose_demos, no_split(pose_demos), config, progress=False)
    return policy.to(torch.float64).eval()


def test_log_exp_round_trip_over_all_of_so3():
    # GIVEN random orientations (all of SO(3)) and random targets
    q, target = random_quats(2000, 0), random_quats(2000, 1)
    # WHEN the relative rotation vector is taken and applied back to the target
    r = relative_rotvec(q, target)
    back = rotate(r, target)
    # THEN the angle is canonical and the orientation is recovered up to the sign
    assert (r.norm(dim=-1) <= torch.pi + 1e-12).all()
    assert torch.allclose((back * q).sum(-1).abs(), torch.ones(2000, dtype=torch.float64))


def test_exp_log_round_trip_inside_the_ball():
    # GIVEN rotation vectors of angle < pi, including tiny ones
    r = torch.randn(1000, 3, dtype=torch.float64)
    r = r / r.norm(dim=-1, keepdim=True) * torch.rand(1000, 1, dtype=torch.float64) * 3.1
    r[:10] *= 1e-9
    identity = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=torch.float64)
    # THEN log(exp(r)) = r
    assert torch.allclose(relative_rotvec(rotate(r, identity.expand(1000, 4)), identity), r)


def test_relative_rotvec_is_blind_to_both_signs():
    q, target = random_quats(500, 2), random_quats(1, 3)[0]
    r = relative_rotvec(q, target)
    assert torch.allclose(relative_rotvec(-q, target), r, atol=1e-12)
    assert torch.allclose(relative_rotvec(q, -target), r, atol=1e-12)


def test_policy_output_is_the_same_for_q_and_minus_q(untrained):
    # GIVEN random poses over all of SO(3)
    p = torch.randn(500, 3, dtype=torch.float64) * 10
    q = random_quats(500, 4)
    # THEN the two quaternions of each orientation give the same linear and angular velocity
    x = torch.cat([p, q], -1)
    assert torch.allclose(untrained(x), untrained(torch.cat([p, -q], -1)), atol=1e-10)


def test_a_twist_moves_the_chart_as_the_chart_velocity_says(untrained):
    # GIVEN random poses over all of SO(3) and the twist the policy commands there
    x = torch.cat([torch.randn(300, 3, dtype=torch.float64), random_quats(300, 9)], -1)
    twist = untrained(x)
    # WHEN the pose moves along the twist on SE(3) for a short time h
    h = 1e-6
    moved = SE3().advance(x, torch.full((300,), h, dtype=x.dtype), twist)
    # THEN the model coordinates move at the policy's own velocity field there (the twist is
    # the exact image of the chart's flow, so V falls along the robot's real motion)
    z = untrained.to_model(x)
    rate = (untrained.to_model(moved) - z) / h
    expected = untrained.field(z) / untrained.time
    far_from_cut = relative_rotvec(x[:, 3:], untrained.target_orientation).norm(dim=-1) < 3.0
    assert torch.allclose(rate[far_from_cut], expected[far_from_cut], rtol=1e-4, atol=1e-5)


@pytest.mark.parametrize("scale", [1e-5, 0.5, 2.0, 3.1])
def test_left_jacobian_is_the_derivative_of_exp(scale):
    # GIVEN rotation vectors r and a small step delta
    r = torch.randn(200, 3, dtype=torch.float64)
    r = scale * r / r.norm(dim=-1, keepdim=True)
    delta = 1e-6 * torch.randn(200, 3, dtype=torch.float64)
    identity = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=torch.float64).expand(200, 4)
    # WHEN exp(r + delta) exp(r)^-1 is taken
    step = roma.quat_product(
        rotate(r + delta, identity), roma.quat_conjugation(rotate(r, identity))
    )
    # THEN it is exp(J_l(r) delta) to first order, and J_l^-1 inverts J_l
    small = relative_rotvec(step, identity[0])
    predicted = (left_jacobian(r) @ delta[..., None])[..., 0]
    assert torch.allclose(small, predicted, atol=1e-11)
    eye = torch.eye(3, dtype=torch.float64).expand(200, 3, 3)
    assert torch.allclose(left_jacobian_inverse(r) @ left_jacobian(r), eye, atol=1e-9)


def _spinning(x: torch.Tensor) -> torch.Tensor:
    """A stand-in for a policy: a state-dependent angular velocity, cheap enough for 10^4 steps."""
    return torch.cat([-x[:, :3], 3.0 * x[:, 3:6] + torch.tensor([1.0, -2.0, 0.5])], -1)


def test_unit_norm_kept_over_ten_thousand_steps():
    # GIVEN random start poses turned fast (about 3 rad/s) for 10,000 steps, in float64
    x0 = torch.cat([torch.randn(64, 3, dtype=torch.float64), random_quats(64, 5)], -1)
    states = rollout(
        Dynamics(field=_spinning, advance=SE3().advance), x0, dt=0.01, steps=10_000
    ).states
    # THEN every quaternion is unit
    assert (states[..., 3:].norm(dim=-1) - 1).abs().max() < 1e-12


def test_untrained_policy_keeps_unit_norm(untrained):
    x0 = torch.cat([torch.randn(8, 3, dtype=torch.float64), random_quats(8, 8)], -1)
    states = rollout(untrained, x0, dt=0.05, steps=200).states
    assert (states[..., 3:].norm(dim=-1) - 1).abs().max() < 1e-12


def test_so3_integration_is_exact_for_a_constant_turn():
    # GIVEN a constant world-frame angular velocity and the exponential-map step
    omega = torch.tensor([[0.3, -1.1, 0.7]], dtype=torch.float64)
    q = random_quats(1, 6)
    start = q
    for _ in range(1000):
        q = roma.quat_normalize(rotate(0.01 * omega, q))
    # THEN after 10 s the orientation is exactly exp(10 omega) q0 (no Euler drift off SO(3))
    expected = rotate(10.0 * omega, start)
    assert float((q * expected).sum().abs()) == pytest.approx(1.0, abs=1e-12)


def test_angular_velocities_recover_a_known_turn():
    times = np.linspace(0, 2, 401)
    omega = np.array([0.2, 0.5, -0.4])
    rotations = Rotation.from_rotvec(times[:, None] * omega) * Rotation.from_quat([0, 0, 1, 0])
    assert np.allclose(angular_velocities(rotations.as_quat(), times), omega, atol=1e-9)


def test_decrease_holds_on_random_poses_before_training(untrained, pose_demos):
    report = check_stability(untrained, pose_demos, CheckConfig(rollouts=1, samples=5_000))
    assert report.samples_checked == 5_000
    assert report.decrease_violations == 0


@pytest.mark.slow
def test_synthetic_pose_task_is_learned_and_converges(trained, untrained, pose_demos):
    # GIVEN a policy trained briefly on the synthetic pose task
    split = no_split(pose_demos)
    after = accuracy(trained, pose_demos, split)
    before = accuracy(untrained, pose_demos, split)
    # THEN it follows the demonstrated path and orientations far better than before training
    assert after["angle_error_along"] < 0.15  # radians; the turn is ~1.6 rad
    assert after["angle_error_along"] < 0.6 * before["angle_error_along"]
    assert after["dtw"] < 0.3 * before["dtw"]
    # AND reaches the target pose from random positions and all orientations
    config = CheckConfig(rollouts=50, samples=2_000, seed=1)
    report = check_stability(trained, pose_demos, config)
    assert report.converged_fraction == 1.0
    assert report.decrease_violations == 0
    assert report.max_final_errors["angle"] <= report.tolerances["angle"]
    # AND every guarded step on SO(3) lowered V (no step ran out of halvings)
    assert report.v_rises == 0


def test_save_load_round_trip(trained, tmp_path):
    save_model(trained, tmp_path / "model")
    loaded, description = load_model(tmp_path / "model")
    assert isinstance(loaded, PosePolicy) and description["kind"] == "se3"
    x = torch.cat([torch.randn(50, 3, dtype=torch.float64), random_quats(50, 7)], -1)
    assert torch.equal(loaded(x), trained(x))
    assert loaded.config == trained.config


@pytest.mark.slow
def test_cli_trains_evaluates_and_plots_a_pose_file(pose_demos, tmp_path):
    import json

    from snds.cli import main

    # GIVEN a pose CSV file (auto-detected: no --se3 needed)
    lines = ["demo,t,x,y,z,qx,qy,qz,qw"]
    for d, demo in enumerate(pose_demos):
        for t, p, q in zip(demo.times, demo.positions, demo.orientations):
            lines.append(",".join(f"{v:.17g}" for v in [d, t, *p, *q]))
    data = tmp_path / "poses.csv"
    data.write_text("\n".join(lines) + "\n")
    out = tmp_path / "model"
    checks = ["--rollouts", "5", "--samples", "200"]
    # WHEN it is trained, evaluated and plotted from the command line
    assert (
        main(
            ["--quiet", "train", "--data", str(data), "--steps", "20", "--out", str(out)]
            + ["--architecture", "compact", *checks]
        )
        == 0
    )
    assert main(["--quiet", "evaluate", str(out), *checks]) == 0
    assert main(["--quiet", "plot", str(out)]) == 0
    # THEN the model is a pose policy and every SE(3) metric and plot is there
    description = json.loads((out / "model.json").read_text())
    assert description["kind"] == "se3"
    # --architecture applies to pose policies as to positions.
    assert description["policy"]["hidden"] == [64, 64]
    # Pose models train as positions do: the default recipe, a warped V.
    from snds.recipes import RECIPES

    default = RECIPES["default"].train
    assert description["train"]["shape_weight"] == default.shape_weight
    assert description["train"]["position_noise"] == default.position_noise
    assert description["policy"]["warp_layers"] == 4
    metrics = json.loads((out / "metrics.json").read_text())
    assert {"dtw", "angle_error_along", "final_angle_error", "angular_velocity_mse"} <= set(metrics)
    assert metrics["stability"]["rollouts"] == 5
    assert (out / "paths3d.png").is_file() and (out / "rollout_lyapunov.png").is_file()


def test_safe_twist_held_for_one_period_decreases_v(untrained, pose_demos):
    rng = np.random.default_rng(4)
    x = torch.as_tensor(SE3().uniform(pose_demos.target, 3 * pose_demos.extent(), 500, rng))
    dt = 2.0  # a long control period, so that some twists must be scaled down
    lyapunov, _ = policy_guard(untrained)
    with torch.no_grad():
        twist, h = safe_velocity(untrained, x, dt)
        # holding the scaled twist for dt is the guarded step of length h
        after = untrained.space.advance(x, torch.full((len(x),), dt, dtype=x.dtype), twist)
        before, now = lyapunov(x), lyapunov(after)
    assert (h <= dt).all() and (h < dt).any()
    assert (now < before).all()
    assert torch.allclose(after[:, 3:].norm(dim=-1), torch.ones(len(x), dtype=x.dtype))
