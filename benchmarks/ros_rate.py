"""The ROS 2 node's achieved rate, jitter and overruns in a closed loop (one process).

The node (``snds.ros``) drives an integrator robot that publishes its position as
PoseStamped; both run in one rclpy executor for ``--seconds``, the robot started 3 extents
from the target and put back there every 5 s.

    python benchmarks/ros_rate.py --model tests/fixtures/models-c52752d/sine --rate 500

Writes ``benchmarks/results/ros_rate.json``.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import time
from pathlib import Path

import numpy as np
import rclpy
import torch
from _readme import cpu_name
from geometry_msgs.msg import PoseStamped, TwistStamped
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node

from snds.models import load_model
from snds.ros import NodeConfig, make_node

HERE = Path(__file__).resolve().parent


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", type=Path, default=Path("tests/fixtures/models-c52752d/sine"))
    parser.add_argument("--rate", type=float, default=500.0)
    parser.add_argument("--seconds", type=float, default=20.0)
    args = parser.parse_args()
    torch.set_num_threads(1)  # as the CLI
    policy, _ = load_model(args.model)
    start = policy.target + 3 * policy.normalization.length
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    context = rclpy.context.Context()
    rclpy.init(context=context, domain_id=150 + os.getpid() % 50)
    config = NodeConfig(state_topic="/bench/state", command_topic="/bench/command", rate=args.rate)
    node = make_node(policy, config, context=context)
    robot = Node("robot", context=context)
    state = {
        "x": start.copy(),
        "v": np.zeros(2),
        "last": time.monotonic(),
        "reset": time.monotonic(),
    }
    publisher = robot.create_publisher(PoseStamped, config.state_topic, 10)

    def on_command(message):
        state["v"] = np.array([message.twist.linear.x, message.twist.linear.y])

    def on_timer():
        now = time.monotonic()
        state["x"] = state["x"] + (now - state["last"]) * state["v"]
        state["last"] = now
        if now - state["reset"] >= 5.0:
            state["x"], state["reset"] = start.copy(), now
        message = PoseStamped()
        message.pose.position.x, message.pose.position.y = (float(v) for v in state["x"])
        publisher.publish(message)

    robot.create_subscription(TwistStamped, config.command_topic, on_command, 10)
    robot.create_timer(1.0 / args.rate, on_timer)
    executor = SingleThreadedExecutor(context=context)
    executor.add_node(node)
    executor.add_node(robot)
    wall, cpu = time.monotonic(), time.process_time()
    while time.monotonic() - wall < args.seconds:
        executor.spin_once(timeout_sec=0.01)
    summary = node.timing.summary(args.rate)
    summary.update(
        requested_rate=args.rate,
        wall_s=time.monotonic() - wall,
        cpu_s=time.process_time() - cpu,
        date=datetime.date.today().isoformat(),
        processor=cpu_name(),
        model=str(args.model),
        load_average=os.getloadavg(),
    )
    node.stop()
    executor.shutdown()
    rclpy.shutdown(context=context)
    (HERE / "results" / "ros_rate.json").write_text(json.dumps(summary, indent=2) + "\n")
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
