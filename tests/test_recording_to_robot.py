"""From a recording to a robot, end to end: a rosbag2 (MCAP) of PoseStamped written by the
test -> snds train --topic -> snds export --format c -> the compiled controller reaches the
target in a closed loop; and the same model through snds ros and an rclpy integrator."""

from __future__ import annotations

import ctypes
import json
import os
import time

import numpy as np
import pytest
import torch

from snds.cli import main
from snds.data import DataSource
from snds.export import c_check
from snds.models import load_model
from snds.phase import start_rule
from snds.ros import NodeConfig, make_node
from snds.so3 import geodesic_angle

pytest.importorskip("rosbags", reason="the bag reader needs the rosbag extra")
if c_check.compiler() is None:
    pytest.skip("no C compiler (gcc or cc) to build the C export", allow_module_level=True)

from recording_files import line_poses, write_bag  # noqa: E402


def _trained(folder, *options: str):
    """A pose model trained from a bag of PoseStamped on /ee_pose, with its C export."""
    write_bag(folder / "rec", line_poses(80))
    mcap = next((folder / "rec").glob("*.mcap"))
    out = folder / "model"
    argv = ["--quiet", "train", "--data", str(mcap), "--topic", "/ee_pose", "--out", str(out)]
    assert main([*argv, "--steps", "150", "--rollouts", "20", "--samples", "500", *options]) == 0
    code = main(
        ["--quiet", "export", str(out), "--format", "c", "--samples", "2000", "--max-speed", "0.2"]
    )
    assert code == 0
    return out


@pytest.fixture(scope="module")
def model(tmp_path_factory):
    """The default: a pose model with a phase after the pose."""
    return _trained(tmp_path_factory.mktemp("robot"))


def test_the_compiled_controller_reaches_the_target_from_the_recordings_start(model):
    # GIVEN the C export compiled into a library, and the recording's first pose
    policy, _ = load_model(model)
    checks = json.loads((model / "policy.h.check.json").read_text())
    assert all(c["passed"] for c in checks)
    library = c_check.compile_shared(model / "policy.h", model / "policy.so")
    step = ctypes.CDLL(str(library)).snds_step
    pointer = ctypes.POINTER(ctypes.c_double)
    step.argtypes = [pointer, ctypes.c_double, ctypes.c_double, pointer, pointer]
    step.restype = ctypes.c_double
    # The recording's first pose, given its phase by the controller's own start rule
    space = policy.space
    assert space.phase_dim == 3
    start = ctypes.CDLL(str(library)).snds_start_state
    start.argtypes = [pointer, pointer]
    pose, x = np.array(line_poses(80)[0]), np.zeros(space.dim)
    start(pose.ctypes.data_as(pointer), x.ctypes.data_as(pointer))
    np.testing.assert_array_equal(x[:7], pose)
    command, reached = np.zeros(space.tangent_dim), np.zeros(space.dim)
    # WHEN a 100 Hz loop holds its command for 20 s on an ideal robot (the state it reaches
    # is the step's own next state), under the exported limit of 0.2 m/s
    peak = 0.0
    for _ in range(2_000):
        step(
            x.ctypes.data_as(pointer),
            0.01,
            0.2,
            command.ctypes.data_as(pointer),
            reached.ctypes.data_as(pointer),
        )
        peak = max(peak, float(np.linalg.norm(command[:3])))
        x = reached.copy()
    # THEN it is at the target: within 1 % of the extent and 0.05 rad, never faster than 0.2
    target = policy.target
    extent = float(policy.extents()[0])
    assert np.linalg.norm(x[:3] - target[:3]) <= 0.01 * extent
    assert geodesic_angle(x[3:7], target[3:7]) <= 0.05
    assert peak <= 0.2 * (1 + 1e-12)


def test_snds_ros_drives_an_rclpy_robot_to_the_target(model):
    rclpy = pytest.importorskip("rclpy", reason="the ROS node needs the ros extra")
    from geometry_msgs.msg import PoseStamped, TwistStamped
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node

    policy, description = load_model(model)
    space = policy.space
    # The default model has a phase: the node keeps it, from the demonstrations' start rule
    assert space.phase_dim == 3
    rule = start_rule(DataSource.from_record(description["data"], poses=True).load())
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    context = rclpy.context.Context()
    rclpy.init(context=context, domain_id=100 + (os.getpid() + 50) % 100)
    tag = f"e2e{os.getpid()}"
    config = NodeConfig(
        state_topic=f"/{tag}/ee_pose", command_topic=f"/{tag}/ee_twist", rate=50.0, max_speed=0.2
    )
    node = make_node(policy, config, context=context, start_rule=rule)
    robot = Node("robot", context=context)
    state = {"x": np.array(line_poses(80)[0]), "twist": np.zeros(6), "last": time.monotonic()}
    publisher = robot.create_publisher(PoseStamped, config.state_topic, 10)

    def on_twist(message):
        linear, angular = message.twist.linear, message.twist.angular
        state["twist"] = np.array([linear.x, linear.y, linear.z, angular.x, angular.y, angular.z])

    def on_timer():
        # The robot: the pose moved along the held twist (SE(3): p + h v, exp(h w) q).
        now = time.monotonic()
        h = torch.tensor([now - state["last"]], dtype=torch.float64)
        x = torch.as_tensor(state["x"])[None]
        state["x"] = space.base.advance(x, h, torch.as_tensor(state["twist"])[None])[0].numpy()
        state["last"] = now
        message = PoseStamped()
        p, q = message.pose.position, message.pose.orientation
        p.x, p.y, p.z = (float(v) for v in state["x"][:3])
        q.x, q.y, q.z, q.w = (float(v) for v in state["x"][3:])
        publisher.publish(message)

    robot.create_subscription(TwistStamped, config.command_topic, on_twist, 10)
    robot.create_timer(0.02, on_timer)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    executor.add_node(robot)
    target, extent = policy.target, float(policy.extents()[0])

    def arrived() -> bool:
        x = state["x"]
        return (
            np.linalg.norm(x[:3] - target[:3]) <= 0.01 * extent
            and geodesic_angle(x[3:], target[3:7]) <= 0.05
        )

    try:
        end = time.monotonic() + 40.0
        while time.monotonic() < end and not arrived():
            executor.spin_once(timeout_sec=0.01)
        assert arrived(), state["x"]
        assert node.timing.commands > 10
    finally:
        node.stop()
        executor.shutdown()
        node.destroy_node()
        robot.destroy_node()
        rclpy.shutdown(context=context)
