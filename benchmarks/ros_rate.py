"""The ROS 2 node's achieved rate, jitter and overruns in a closed loop (one process).

The node (``snds.ros``) drives an integrator robot that publishes its position as
PoseStamped; both run in one rclpy executor for ``--seconds``, the robot started 3 extents
from the target and put back there every 5 s.

    python benchmarks/ros_rate.py --model tests/fixtures/models-c52752d/sine --rate 500

Writes ``benchmarks/results/ros_rate.json`` and the ``ros-rate`` block of
``benchmarks/README.md``.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np
import rclpy
from _runner import RESULTS, machine, machine_line, parser, set_threads, write_readme_section
from geometry_msgs.msg import PoseStamped, TwistStamped
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node

from snds.cli._common import start_rule_of
from snds.models import load_model
from snds.ros import NodeConfig, make_node


def main() -> None:
    options = parser(__doc__)
    options.add_argument("--model", type=Path, default=Path("tests/fixtures/models-c52752d/sine"))
    options.add_argument("--rate", type=float, default=500.0)
    options.add_argument("--seconds", type=float, default=20.0)
    args = options.parse_args()
    set_threads(args.threads)  # one, as the CLI
    policy, description = load_model(args.model)
    dim = policy.space.position_dim  # the robot's positions; a phase is the node's own
    start = policy.target[:dim] + 3 * np.asarray(policy.normalization.length).reshape(-1)[:dim]
    rule = start_rule_of(args.model, description) if policy.space.phase_dim else None
    os.environ.setdefault("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    context = rclpy.context.Context()
    rclpy.init(context=context, domain_id=150 + os.getpid() % 50)
    config = NodeConfig(state_topic="/bench/state", command_topic="/bench/command", rate=args.rate)
    node = make_node(policy, config, context=context, start_rule=rule)
    robot = Node("robot", context=context)
    state = {
        "x": start.copy(),
        "v": np.zeros(dim),
        "last": time.monotonic(),
        "reset": time.monotonic(),
    }
    publisher = robot.create_publisher(PoseStamped, config.state_topic, 10)

    def on_command(message):
        linear = message.twist.linear
        state["v"] = np.array([linear.x, linear.y, linear.z])[:dim]

    def on_timer():
        now = time.monotonic()
        state["x"] = state["x"] + (now - state["last"]) * state["v"]
        state["last"] = now
        if now - state["reset"] >= 5.0:
            state["x"], state["reset"] = start.copy(), now
        message = PoseStamped()
        for axis, value in zip("xyz", state["x"], strict=False):
            setattr(message.pose.position, axis, float(value))
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
        model=str(args.model),
        **machine(threads=args.threads),
    )
    node.stop()
    executor.shutdown()
    rclpy.shutdown(context=context)
    (RESULTS / "ros_rate.json").write_text(json.dumps(summary, indent=2) + "\n")
    print(json.dumps(summary))
    if not args.no_readme:
        write_readme_section("ros-rate", table(summary))


def table(s: dict) -> str:
    """The README block: achieved rate, jitter and overruns."""
    load = f", load average {s['load_average'][0]:.1f}" if "load_average" in s else ""
    where = machine_line(s) if "cpu" in s else f"Measured {s['date']} on {s['processor']}{load}."
    return (
        f"{where} `python benchmarks/ros_rate.py --model {s['model']} --rate "
        f"{s['requested_rate']:g} --seconds {s['wall_s']:.0f}`.\n\n"
        "| requested | achieved (mean / median period) | jitter: std / worst (ms) "
        "| periods > half a period late | median / largest lateness (ms) | CPU s / wall s |\n"
        "|---|---|---|---|---|---|\n"
        f"| {s['requested_rate']:g} Hz | {s['rate']:.0f} / {s['median_rate']:.0f} Hz "
        f"| {1e3 * s['jitter_std']:.1f} / {1e3 * s['jitter_max']:.0f} "
        f"| {s['overruns']:,} of {s['periods']:,} "
        f"| {1e3 * s['median_overrun']:.2f} / {1e3 * s['largest_overrun']:.0f} "
        f"| {s['cpu_s']:.1f} / {s['wall_s']:.1f} |"
    )


if __name__ == "__main__":
    main()
