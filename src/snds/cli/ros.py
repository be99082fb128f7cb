"""``snds ros``: a ROS 2 node that drives a robot with a saved model (extra ``ros``)."""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from snds.cli._common import start_rule_of
from snds.models import load_model
from snds.ros import BACKENDS, NodeConfig, make_node

__all__ = ["register", "run"]


def register(commands: argparse._SubParsersAction) -> None:
    """Adds ``snds ros`` to the subcommands."""
    parser = commands.add_parser(
        "ros",
        help="run a ROS 2 node: state in (PoseStamped), guarded and speed-limited "
        "TwistStamped out (pip install 'snds[ros]')",
    )
    defaults = NodeConfig()
    parser.add_argument("model", type=Path, help="model directory")
    parser.add_argument("--state-topic", default=defaults.state_topic)
    parser.add_argument("--command-topic", default=defaults.command_topic)
    parser.add_argument(
        "--state-type", choices=["PoseStamped", "PointStamped"], default=defaults.state_type
    )
    parser.add_argument("--rate", type=float, default=defaults.rate, help="control rate, Hz")
    parser.add_argument(
        "--max-speed",
        type=float,
        default=defaults.max_speed,
        help="speed limit of the positions, user units/s (0: none)",
    )
    parser.add_argument(
        "--stale-after",
        type=float,
        default=defaults.stale_after,
        help="seconds without a state after which the node commands zero",
    )
    parser.add_argument("--frame-id", default=defaults.frame_id)
    parser.add_argument(
        "--backend",
        choices=list(BACKENDS),
        default="auto",
        help="c: the model's C export, compiled at start (about 40 us a step); torch: the "
        "library (about 2 ms); auto: c where a C compiler is found",
    )
    parser.add_argument(
        "--duration", type=float, default=None, help="stop after this many seconds (default: run)"
    )
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    config = NodeConfig(
        state_topic=args.state_topic,
        command_topic=args.command_topic,
        rate=args.rate,
        max_speed=args.max_speed,
        stale_after=args.stale_after,
        state_type=args.state_type,
        frame_id=args.frame_id,
    )
    policy, description = load_model(args.model)
    rule = start_rule_of(args.model, description) if policy.space.phase_dim else None
    import rclpy

    rclpy.init()
    node = make_node(policy, config, backend=args.backend, start_rule=rule)
    end = None if args.duration is None else time.monotonic() + args.duration
    try:
        while rclpy.ok() and (end is None or time.monotonic() < end):
            rclpy.spin_once(node, timeout_sec=0.1)
    except KeyboardInterrupt:
        pass
    finally:
        node.stop()
        summary = node.timing.summary(node.settings["rate"])
        node.destroy_node()
        rclpy.try_shutdown()
    if not args.quiet:
        print(f"snds ros: {json.dumps(summary)}")
    return 0
