"""Simulated runs of an SE(3) pose policy (PyBullet, headless): the policy drives the tool's
position and orientation to the target pose, through a push, and the CLI records both."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation
from test_plotting import assert_png

from snds.cli import main
from snds.data import no_split
from snds.data.poses import PoseDemonstration, with_synthetic_orientations
from snds.models import save_model
from snds.policy import PolicyConfig
from snds.se3 import make_pose_policy
from snds.sim import Push, SimConfig, SimulationError, simulate
from snds.train import TrainConfig, fit

from conftest import SMALL, spiral_demos

pytest.importorskip("pybullet", reason="the simulation tests need the sim extra")

#: A fast guaranteed decay, so that a briefly trained policy arrives within a short run.
FAST = PolicyConfig(**{**SMALL.to_dict(), "decay_rate": 2.0})


@pytest.fixture(autouse=True, scope="module")
def one_thread():
    # One torch thread, as in the CLI: a control loop evaluates one state at a time.
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def pose_demos():
    # A decaying spiral on z = 0, lifted to poses turning by ~89 degrees to a target
    # orientation that is not the identity (so the placement's rotation is not trivial).
    return with_synthetic_orientations(
        spiral_demos(count=2, samples=200), target_orientation=(0.0, 0.6, 0.0, 0.8), seed=1
    )


@pytest.fixture(scope="module")
def pose_policy(pose_demos):
    torch.manual_seed(0)
    policy = make_pose_policy(pose_demos, config=FAST, seed=0)
    # Clean states, as `snds train --se3` trains pose models.
    config = TrainConfig(steps=300, seed=0, position_noise=0.0, noise_correction=0.0)
    fit(policy, pose_demos, no_split(pose_demos), config, progress=False)
    return policy.to(torch.float64).eval()


def start_pose(demo: PoseDemonstration) -> np.ndarray:
    """A demonstration's first pose as the simulator takes it: position, quaternion (7,)."""
    return np.r_[demo.positions[0], demo.orientations[0]]


@pytest.fixture(scope="module")
def pose_run(pose_policy, pose_demos):
    # Pushed 3 cm straight up off the motion's plane, where the target lies: away from it. The
    # default placement of the orientations, so the push lands where the geometry below
    # expects; the search for a turn that fits the arm is tested in test_orient.py and by the
    # CLI run below.
    push = Push(step=300, displacement=(0.0, 0.0, 0.03))
    config = SimConfig(robot="iiwa", push=push, time_limit=15.0, fit_orientation=False)
    return simulate(pose_policy, start_pose(pose_demos[0]), config)


def test_pose_policy_drives_position_and_orientation_to_the_target(pose_run, pose_demos) -> None:
    run, config = pose_run, pose_run.config
    distance = np.linalg.norm(run.positions - run.placement.origin, axis=1)
    # it starts at the requested pose, about 20 cm and 89 degrees from the target
    assert run.start_error < 1e-4 and run.start_orientation_error < 1e-3
    np.testing.assert_allclose(run.states[0], pose_demos[0].positions[0], atol=1e-2)
    assert distance[0] > 0.15 and run.orientation_errors[0] > 1.4
    # it stops within both tolerances, well before the time limit, and not before
    assert run.reached and run.drives_orientation
    assert run.final_error <= config.tolerance
    assert run.final_orientation_error <= config.angle_tolerance
    assert run.times[-1] < config.time_limit
    assert distance[-2] > config.tolerance or run.orientation_errors[-2] > config.angle_tolerance
    # both errors fell a lot: positions 150x, orientations 70x
    assert run.final_error < distance[0] / 150
    assert run.final_orientation_error < run.orientation_errors[0] / 70


def test_the_policy_sees_the_angle_the_arm_has(pose_run, pose_policy) -> None:
    # GIVEN the measured world orientations, mapped back into the task
    rotation = Rotation.from_quat(pose_run.rotation)
    task = rotation.inv() * Rotation.from_quat(pose_run.orientations)
    target = Rotation.from_quat(pose_policy.config.target_orientation)
    # THEN their angle to the task's target is the world angle to the goal orientation: the
    # placement turns the whole task rigidly
    np.testing.assert_allclose(
        (task * target.inv()).magnitude(), pose_run.orientation_errors, atol=1e-9
    )
    # and the goal orientation is the image of the target orientation
    assert (rotation * target).approx_equal(Rotation.from_quat(pose_run.goal_orientation))


def test_orientation_stays_a_unit_quaternion(pose_run) -> None:
    norms = np.linalg.norm(pose_run.orientations, axis=1)
    assert pose_run.orientations.shape == (len(pose_run.times), 4)
    assert np.abs(norms - 1).max() < 1e-6


def test_pose_run_recovers_from_the_push(pose_run) -> None:
    run = pose_run
    distance = np.linalg.norm(run.positions - run.placement.origin, axis=1)
    pushed = int(np.searchsorted(run.times, run.push_time))
    assert run.push_time == pytest.approx(3.0)
    np.testing.assert_allclose(run.push_offset, [0.0, 0.0, 0.03], atol=1e-3)
    # a push moves the tool, it does not turn it: the angle changes across the push step as
    # across the step before it, by the policy's turning in one control step
    angles = run.orientation_errors
    turning = abs(angles[pushed - 1] - angles[pushed - 2])
    assert abs(angles[pushed] - angles[pushed - 1]) < 1.5 * turning + 1e-4
    assert distance[pushed] > distance[pushed - 1] + 0.005
    assert run.recovery_time is not None and 0 < run.recovery_time < run.times[-1] - 3.0


def test_pose_run_keeps_the_joints_within_limits(pose_run) -> None:
    q = pose_run.joints
    assert np.all(q >= pose_run.joint_lower) and np.all(q <= pose_run.joint_upper)


def test_pose_record_is_json_with_the_orientation(pose_run) -> None:
    record = json.loads(json.dumps(pose_run.to_dict()))
    assert record["drives_orientation"] is True
    assert record["settings"]["angle_tolerance"] == 0.02
    assert len(record["orientation_path"]) == len(record["time"])
    assert len(record["orientation_error_path_rad"]) == len(record["time"])
    assert record["final_orientation_error_rad"] == pose_run.final_orientation_error
    assert len(record["placement"]["rotation"]) == 4


def test_a_pose_model_needs_a_pose_to_start(pose_policy) -> None:
    with pytest.raises(SimulationError, match="7 numbers"):
        simulate(pose_policy, np.zeros(3), SimConfig(time_limit=0.1))
    with pytest.raises(SimulationError, match="unit quaternion"):
        simulate(pose_policy, np.r_[np.zeros(3), 0.0, 0.0, 0.0, 2.0], SimConfig(time_limit=0.1))


def test_cli_simulate_a_pose_model(pose_policy, pose_demos, tmp_path: Path, capsys) -> None:
    # GIVEN a saved pose model and its demonstrations as a pose file
    save_model(pose_policy, tmp_path / "model")
    data = tmp_path / "poses.npz"
    np.savez(
        data,
        pos=np.stack([d.positions for d in pose_demos]),
        quat=np.stack([d.orientations for d in pose_demos]),
        t=pose_demos[0].times,
    )
    out = tmp_path / "out"
    args = ["simulate", str(tmp_path / "model"), "--data", str(data), "--out", str(out)]
    # WHEN the CLI drives the iiwa with it
    assert main([*args, "--frames", "2", "--time-limit", "15", "--angle-tolerance", "0.03"]) == 0
    # THEN the record has the orientation, and the path picture its error over time
    record = json.loads((out / "sim.json").read_text())
    assert record["reached"] and record["drives_orientation"]
    assert record["final_orientation_error_rad"] <= 0.03
    assert record["settings"]["angle_tolerance"] == 0.03
    assert record["settings"]["fit_orientation"] is True
    # (the default placement leaves a joint within 0.1 rad of its limit on this path: turned)
    assert np.linalg.norm(record["placement"]["orientation_turn_rad"]) > 0.4
    assert np.allclose(record["task_path"][0], pose_demos[0].positions[0], atol=1e-2)
    assert_png(out / "path.png")
    assert_png(out / "frames.png")
    assert " rad" in capsys.readouterr().out
