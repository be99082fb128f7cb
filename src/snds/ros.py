"""A ROS 2 node that drives a robot with a policy: ``snds ros`` (extra ``ros``).

The node subscribes to the measured state (``geometry_msgs/PoseStamped``, or
``PointStamped`` for a position model) and, at a fixed rate, publishes the command
(``geometry_msgs/TwistStamped``) of the guarded step (:func:`snds.rollout.safe_velocity`,
computed by the model's C export where a C compiler is found, :class:`Controller`):
the policy's velocity, scaled down to the speed limit and then so that holding it for one
period decreases V enough. It publishes zero, and stops commanding, when no state has
arrived for ``stale_after`` seconds, and once more on shutdown. Every period's overrun (the
time past its deadline at which it ran) is kept (:class:`Timing`); once a second the log
says how many periods overran by more than half a period. ``rate``, ``max_speed`` (0: no
limit) and ``stale_after`` are ROS parameters, settable at start and while it runs.

A position model of 2 or 3 numbers reads the position's first numbers and commands the
linear velocity; a pose model reads the pose and commands the twist (world frame). rclpy is
imported when a node is made, so the library works without it.
"""

from __future__ import annotations

import math
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from snds.errors import ConfigError
from snds.export.c import export_c
from snds.export.c_check import compiler, load_c
from snds.phase import PhaseKeeper, StartRule
from snds.policy import Policy, float64_copy
from snds.rollout import safe_velocity

__all__ = ["BACKENDS", "Controller", "NodeConfig", "Timing", "make_node"]


@dataclass(frozen=True, kw_only=True)
class NodeConfig:
    """Settings of the node (each also a ROS parameter of the same name).

    Attributes:
        state_topic: Where the measured state arrives.
        command_topic: Where the command goes.
        rate: Control rate, Hz.
        max_speed: Speed limit of the positions, user units/s (0: none).
        stale_after: Seconds without a new state after which the node commands zero.
        state_type: "PoseStamped" or "PointStamped" (positions only).
        frame_id: The frame written into the commands' headers.
    """

    state_topic: str = "/state"
    command_topic: str = "/command"
    rate: float = 500.0
    max_speed: float = 0.0
    stale_after: float = 0.1
    state_type: str = "PoseStamped"
    frame_id: str = "world"

    def __post_init__(self) -> None:
        if not (math.isfinite(self.rate) and self.rate > 0):
            raise ConfigError(f"--rate must be a positive number of Hz, got {self.rate}")
        if not (math.isfinite(self.max_speed) and self.max_speed >= 0):
            raise ConfigError(f"--max-speed must be >= 0 (0: none), got {self.max_speed}")
        if not (math.isfinite(self.stale_after) and self.stale_after > 0):
            raise ConfigError(f"--stale-after must be positive seconds, got {self.stale_after}")
        if self.state_type not in ("PoseStamped", "PointStamped"):
            raise ConfigError(
                f"--state-type must be PoseStamped or PointStamped, got {self.state_type!r}"
            )


#: How :class:`Controller` computes: "c" (the model's C export, compiled once at start: about
#: 40 us a step on the default network), "torch" (the library: about 2 ms a step, too slow for
#: 500 Hz on one core), or "auto" (c where a C compiler is found, else torch).
BACKENDS = ("auto", "c", "torch")


class Controller:
    """What the node computes each period, without ROS: the guarded, limited command.

    A model with a phase (:mod:`snds.phase`) keeps it here: the first measured state gets the
    phase of ``start_rule``, and each later one the phase advanced by the share of the last
    command the measured positions made (:func:`snds.phase.phase_step`), so that it waits
    while the robot is held.

    Arguments:
        policy: A position model (2 or 3 numbers) or a pose model, with a phase or not.
        backend: A key of :data:`BACKENDS`; both compute the same step
            (:func:`snds.rollout.safe_velocity`; the C export agrees with it to rounding).
        start_rule: How a model with a phase gives its first state a phase
            (:func:`snds.phase.start_rule`).
    """

    def __init__(
        self, policy: Policy, *, backend: str = "auto", start_rule: StartRule | None = None
    ) -> None:
        if backend not in BACKENDS:
            raise ConfigError(f"--backend must be one of {', '.join(BACKENDS)}, got {backend!r}")
        space = policy.space
        if space.phase_dim and start_rule is None:
            raise ConfigError(
                "a model with a phase needs its start rule (snds.phase.start_rule of the "
                "demonstrations it was trained on) to give the first state its phase"
            )
        base = space.dim - space.phase_dim
        if base == space.position_dim and base not in (2, 3):
            raise ConfigError(f"snds ros drives 2-D or 3-D positions or poses, not {base}-D")
        self.policy = float64_copy(policy)
        self.pose = base != space.position_dim
        self.dim = base
        self.position_dim = space.position_dim
        self.keeper = (
            PhaseKeeper(position_dim=space.position_dim, start_rule=start_rule)
            if space.phase_dim
            else None
        )
        self.backend, self._step = "torch", None
        if backend != "torch":
            if compiler() is None:
                if backend == "c":
                    raise ConfigError("--backend c needs a C compiler (gcc or cc, or set CC)")
            else:
                self._folder = tempfile.TemporaryDirectory(prefix="snds-ros-")
                header = export_c(
                    policy, Path(self._folder.name) / "policy.h", start_rule=start_rule
                )
                library = load_c(header, policy, Path(self._folder.name) / "policy.so")
                self._step, self.backend = library.stepper(), "c"

    def command(self, state: np.ndarray, *, dt: float, max_speed: float) -> np.ndarray:
        """The twist (6,) to hold for ``dt`` at the measured ``state`` (a position or a pose):
        linear velocity (zero-padded to 3), then the angular velocity (zero for a position
        model)."""
        state = np.asarray(state, dtype=np.float64)
        if self.keeper is not None:
            state = self.keeper.step(state, dt)
        v = self._velocity(state, dt, max_speed)
        if self.keeper is not None:
            self.keeper.command(v)
        twist = np.zeros(6)
        size = 6 if self.pose else self.position_dim
        twist[:size] = v[:size]
        return twist

    def _velocity(self, state: np.ndarray, dt: float, max_speed: float) -> np.ndarray:
        """The guarded, limited velocity at a whole state (phase included)."""
        if self._step is not None:
            v = self._step(np.asarray(state, dtype=np.float64), dt, max_speed or 0.0)
        else:
            x = torch.as_tensor(np.asarray(state, dtype=np.float64))[None]
            with torch.no_grad():
                velocity, _ = safe_velocity(self.policy, x, dt, max_speed=max_speed or None)
            v = velocity[0].numpy()
        return v


@dataclass
class Timing:
    """The node's measured periods.

    Attributes:
        starts: When each period's callback ran (monotonic seconds).
        overruns: How late each ran past its deadline, seconds (0 if on time).
        commands: How many non-zero commands were published.
        stopped: Whether the last period commanded zero for want of a fresh state.
    """

    starts: list[float] = field(default_factory=list)
    overruns: list[float] = field(default_factory=list)
    commands: int = 0
    stopped: bool = True

    def summary(self, rate: float) -> dict:
        """Achieved rate (from the mean period, and from the median one, which a few stalls of
        a busy machine do not move), jitter (standard deviation and largest deviation of the
        periods from 1 / rate, seconds), the periods that ran more than half a period late,
        and the median and largest lateness (seconds)."""
        periods = np.diff(self.starts)
        if not len(periods):
            return {"periods": 0}
        return {
            "periods": int(len(periods)),
            "rate": float(1.0 / periods.mean()),
            "median_rate": float(1.0 / np.median(periods)),
            "jitter_std": float(periods.std()),
            "jitter_max": float(np.abs(periods - 1.0 / rate).max()),
            # Late by more than half a period (the timer always wakes a few us late).
            "overruns": int(sum(o > 0.5 / rate for o in self.overruns)),
            "median_overrun": float(np.median(self.overruns)),
            "largest_overrun": float(max(self.overruns, default=0.0)),
        }


def make_node(
    policy: Policy,
    config: NodeConfig,
    *,
    context=None,
    name: str = "snds",
    backend: str = "auto",
    start_rule: StartRule | None = None,
):
    """The rclpy node of ``policy`` (rclpy must be initialised, in ``context`` if given);
    ``backend`` and ``start_rule`` (a model with a phase) as :class:`Controller`'s.

    Returns:
        The node; its ``timing`` is a :class:`Timing`, ``stop()`` publishes zero.

    Raises:
        ConfigError: Without rclpy, or for a model the node cannot drive.
    """
    try:
        from geometry_msgs.msg import PointStamped, PoseStamped, TwistStamped
        from rcl_interfaces.msg import SetParametersResult
        from rclpy.node import Node
    except ImportError as error:
        raise ConfigError(f"snds ros needs rclpy: pip install 'snds[ros]' ({error})") from error
    controller = Controller(policy, backend=backend, start_rule=start_rule)
    if controller.pose and config.state_type != "PoseStamped":
        raise ConfigError("a pose model reads PoseStamped states")

    class SndsNode(Node):
        def __init__(self) -> None:
            super().__init__(name, context=context)
            self.timing = Timing()
            self.late: list[float] = []
            self.logged = time.monotonic()
            self.lock = threading.Lock()
            self.state: np.ndarray | None = None
            self.received = -math.inf
            for key in ("rate", "max_speed", "stale_after"):
                self.declare_parameter(key, float(getattr(config, key)))
            self.settings = {
                k: float(getattr(config, k)) for k in ("rate", "max_speed", "stale_after")
            }
            self.add_on_set_parameters_callback(self._on_parameters)
            message = PoseStamped if config.state_type == "PoseStamped" else PointStamped
            self.create_subscription(message, config.state_topic, self._on_state, 10)
            self.publisher = self.create_publisher(TwistStamped, config.command_topic, 10)
            self._start_timer()

        def _start_timer(self) -> None:
            self.period = 1.0 / self.settings["rate"]
            self.deadline = time.monotonic() + self.period
            self.timer = self.create_timer(self.period, self._on_timer)

        def _on_parameters(self, parameters):
            updated = dict(self.settings)
            for parameter in parameters:
                value = float(parameter.value)
                if parameter.name == "max_speed" and not value >= 0:
                    return SetParametersResult(successful=False, reason="max_speed must be >= 0")
                if parameter.name in ("rate", "stale_after") and not value > 0:
                    return SetParametersResult(
                        successful=False, reason=f"{parameter.name} must be > 0"
                    )
                updated[parameter.name] = value
            rate_changed = updated["rate"] != self.settings["rate"]
            self.settings = updated
            if rate_changed:
                self.destroy_timer(self.timer)
                self._start_timer()
            return SetParametersResult(successful=True)

        def _on_state(self, message) -> None:
            if isinstance(message, PoseStamped):
                p, q = message.pose.position, message.pose.orientation
                state = [p.x, p.y, p.z, q.x, q.y, q.z, q.w] if controller.pose else [p.x, p.y, p.z]
            else:
                p = message.point
                state = [p.x, p.y, p.z]
            with self.lock:
                self.state = np.asarray(state[: controller.dim], dtype=np.float64)
                self.received = time.monotonic()

        def _publish(self, twist: np.ndarray) -> None:
            message = TwistStamped()
            message.header.stamp = self.get_clock().now().to_msg()
            message.header.frame_id = config.frame_id
            linear, angular = message.twist.linear, message.twist.angular
            linear.x, linear.y, linear.z = (float(v) for v in twist[:3])
            angular.x, angular.y, angular.z = (float(v) for v in twist[3:])
            self.publisher.publish(message)

        def _on_timer(self) -> None:
            now = time.monotonic()
            overrun = max(0.0, now - self.deadline)
            # The next deadline is one period after this one, or after now when a whole
            # period was missed (the timer does not run twice to catch up).
            self.deadline = max(self.deadline + self.period, now)
            self.timing.starts.append(now)
            self.timing.overruns.append(overrun)
            # Every period's overrun is kept; the log gets one line a second for the periods
            # that ran more than half a period late (rclpy's logger costs about 10 ms a call
            # here: a line per period would make the overruns it reports).
            if overrun > self.period / 2:
                self.late.append(overrun)
            if self.late and now - self.logged >= 1.0:
                self.get_logger().warning(
                    f"{len(self.late)} periods overran by more than half a period in the last "
                    f"{now - self.logged:.1f} s (largest {max(self.late) * 1e3:.2f} ms)"
                )
                self.late, self.logged = [], now
            with self.lock:
                state, received = self.state, self.received
            if state is None or now - received > self.settings["stale_after"]:
                if not self.timing.stopped:
                    self.get_logger().warning(
                        f"no state for {self.settings['stale_after']} s: commanding zero"
                    )
                self.timing.stopped = True
                self._publish(np.zeros(6))
                return
            self.timing.stopped = False
            twist = controller.command(state, dt=self.period, max_speed=self.settings["max_speed"])
            self._publish(twist)
            self.timing.commands += 1

        def stop(self) -> None:
            """Publishes a zero command (on shutdown)."""
            self.timing.stopped = True
            self._publish(np.zeros(6))

    return SndsNode()
