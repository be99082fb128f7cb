"""The task-space controller and the task placement: pure NumPy, no simulator needed."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from snds.errors import SimulationError
from snds.sim.arm import joint_velocity, orientation_error
from snds.sim.config import Push, SimConfig
from snds.sim.placement import Placement, PosePlacement
from snds.sim.robots import ROBOTS, get_robot


@pytest.fixture
def jacobian() -> np.ndarray:
    return np.random.default_rng(0).normal(size=(6, 7))


def test_damped_least_squares_produces_the_twist(jacobian: np.ndarray) -> None:
    # GIVEN a full-rank Jacobian and little damping
    twist = np.random.default_rng(1).normal(size=6) * 0.1
    q = np.zeros(7)
    qdot = joint_velocity(jacobian, twist, q, rest=q, max_speed=np.full(7, 100.0), damping=1e-4)
    # THEN the end effector moves with the requested twist
    np.testing.assert_allclose(jacobian @ qdot, twist, atol=1e-7)


def test_posture_term_does_not_move_the_end_effector(jacobian: np.ndarray) -> None:
    # GIVEN the same twist with and without a pull towards a far rest posture
    twist = np.array([0.1, 0.0, -0.05, 0.0, 0.2, 0.0])
    q = np.linspace(-1, 1, 7)
    limits = np.full(7, 100.0)
    plain = joint_velocity(jacobian, twist, q, rest=q, max_speed=limits)
    pulled = joint_velocity(jacobian, twist, q, rest=q + 2.0, max_speed=limits)
    # THEN the joints move differently, the end effector the same
    assert np.linalg.norm(pulled - plain) > 0.1
    np.testing.assert_allclose(jacobian @ pulled, jacobian @ plain, atol=1e-9)


def test_speed_limits_scale_the_whole_motion(jacobian: np.ndarray) -> None:
    twist = np.array([5.0, -3.0, 2.0, 0.0, 0.0, 1.0])
    q = np.zeros(7)
    limits = np.full(7, 0.5)
    free = joint_velocity(jacobian, twist, q, rest=q, max_speed=np.full(7, 1e6))
    limited = joint_velocity(jacobian, twist, q, rest=q, max_speed=limits)
    assert np.all(np.abs(limited) <= limits + 1e-12)
    assert np.isclose(np.max(np.abs(limited) / limits), 1.0)
    # the same direction: the end effector slows down along its path, it does not veer off
    np.testing.assert_allclose(limited / np.linalg.norm(limited), free / np.linalg.norm(free))


def test_orientation_error_is_the_rotation_between_two_poses() -> None:
    rng = np.random.default_rng(2)
    for _ in range(20):
        current, wanted = Rotation.random(2, random_state=rng)
        error = orientation_error(current.as_quat(), wanted.as_quat())
        assert np.linalg.norm(error) <= np.pi + 1e-12
        moved = Rotation.from_rotvec(error) * current
        assert moved.approx_equal(wanted, atol=1e-9)


@pytest.mark.parametrize("name", list(ROBOTS))
def test_placement_maps_the_task_into_the_work_plane(name: str) -> None:
    robot = get_robot(name)
    target = np.array([3.0, -2.0])
    placement = Placement.for_task(robot, target, scale=0.01)
    x = np.array([[3.0, -2.0], [13.0, -2.0], [-7.0, 8.0]])
    world = np.array([placement.to_world(s) for s in x])
    # the target lands on the plane origin, distances scale, states round-trip
    np.testing.assert_allclose(world[0], robot.plane_origin)
    assert np.linalg.norm(world[1] - world[0]) == pytest.approx(0.1)
    for s, p in zip(x, world):
        np.testing.assert_allclose(placement.to_task(p), s, atol=1e-12)
        np.testing.assert_allclose(placement.off_task(p), 0.0, atol=1e-12)
    # a displacement off the plane is invisible to the task and held by the controller
    up = world[2] + 0.05 * np.cross(*np.array(robot.plane_axes))
    np.testing.assert_allclose(placement.to_task(up), x[2], atol=1e-12)
    assert np.linalg.norm(placement.off_task(up)) == pytest.approx(0.05)
    np.testing.assert_allclose(
        placement.velocity_to_world(np.array([1.0, 0.0])) / 0.01, robot.plane_axes[0]
    )


def test_pose_placement_turns_the_task_rigidly_onto_the_rest_orientation() -> None:
    # GIVEN a pose task with a target off the origin and a non-trivial target orientation
    rng = np.random.default_rng(3)
    robot = get_robot("iiwa")
    rest = Rotation.random(random_state=rng).as_quat()
    target_p, target_q = np.array([1.0, -2.0, 0.5]), Rotation.random(random_state=rng).as_quat()
    placement = PosePlacement.for_task(robot, target_p, target_q, 0.02, rest)
    # THEN the target pose lands on the work point in the rest orientation
    origin, goal = placement.to_world(target_p, target_q)
    np.testing.assert_allclose(origin, robot.plane_origin)
    assert Rotation.from_quat(goal).approx_equal(Rotation.from_quat(rest), atol=1e-12)
    for _ in range(20):
        p, q = target_p + rng.normal(size=3), Rotation.random(random_state=rng)
        world_p, world_q = placement.to_world(p, q.as_quat())
        # poses round-trip, and the angle to the target is the world angle to the goal
        back_p, back_q = placement.to_task(world_p, world_q)
        np.testing.assert_allclose(back_p, p, atol=1e-12)
        assert Rotation.from_quat(back_q).approx_equal(q, atol=1e-12)
        angle = (q * Rotation.from_quat(target_q).inv()).magnitude()
        assert np.linalg.norm(orientation_error(world_q, goal)) == pytest.approx(angle, abs=1e-9)
        # a step of the task's twist is the same step of the world's twist: the flow maps
        twist, dt = rng.normal(size=6), 0.01
        stepped = placement.to_world(p + dt * twist[:3], _turn(dt * twist[3:], q))
        world_twist = placement.twist_to_world(twist)
        np.testing.assert_allclose(stepped[0], world_p + dt * world_twist[:3], atol=1e-12)
        moved = Rotation.from_rotvec(dt * world_twist[3:]) * Rotation.from_quat(world_q)
        assert moved.approx_equal(Rotation.from_quat(stepped[1]), atol=1e-12)


def _turn(rotvec: np.ndarray, q: Rotation) -> np.ndarray:
    return (Rotation.from_rotvec(rotvec) * q).as_quat()


def test_bad_settings_are_refused() -> None:
    with pytest.raises(SimulationError, match="unknown robot"):
        get_robot("ur5")
    with pytest.raises(SimulationError, match="scale"):
        SimConfig(scale=-1.0)
    with pytest.raises(SimulationError, match="angle tolerance"):
        SimConfig(angle_tolerance=0.0)
    with pytest.raises(SimulationError):
        Push(step=-1, displacement=(0.0, 0.0, 0.0))
    with pytest.raises(SimulationError):
        Placement.for_task(get_robot("iiwa"), np.zeros(4), 1.0)
