r"""The stability check under obstacles: :func:`snds.stability.check_rollouts` with a scene.

The same check as without obstacles (one :class:`~snds.stability.CheckConfig`, the same
adaptive guarded rollouts of :func:`snds.rollout.rollout`), from random starts in the free part
of the box and from the demonstrations' starts, with what obstacles add: penetrations, the
smallest clearance, where rollouts stalled and why, and DTW to the demonstrations the
obstacles leave free.
"""

from __future__ import annotations

import dataclasses
import math
import time as _time
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from snds.data.demonstrations import Demonstrations
from snds.errors import ConfigError
from snds.evaluate import reproduce
from snds.metrics import dtw
from snds.obstacles.scene import Scene
from snds.policy import Policy, float64_copy
from snds.rollout import Rollout, rollout
from snds.stability import CheckConfig, check_rollouts
from snds.steppers import Dynamics, GuardedEuler

__all__ = ["ObstacleReport", "RolloutCheck", "check_obstacles", "free_starts"]


@dataclass(frozen=True)
class RolloutCheck:
    """Outcome of rollouts under obstacles from one set of starts.

    Attributes:
        starts: Number of rollouts.
        reached: Rollouts that ended within the tolerance of the target.
        converged_fraction: reached / starts.
        stalled: Rollouts that did not (the rest), listed in ``stall_points``.
        stall_points: Where they ended, clustered within 5% of the extent: each {"center",
            "count", "gamma", "speed", "kind"}: "saddle" (the field vanishes on an inflated
            boundary: the measure-zero set the modulation cannot avoid), "held" (the field
            points into an obstacle and the guard holds the state: a concave junction of
            overlapping obstacles), "attractor" (the field vanishes in free space) or
            "moving" (too slow for the horizon).
        penetrated: Rollouts with a state inside an inflated obstacle (Gamma <= 1); must be 0.
        min_clearance: Smallest distance of a state to a physical obstacle surface (or
            workspace wall), user units; compare with ``margin``.
        margin: The smallest margin in the scene.
        held_steps: Steps at which the guard held a state (no halving was safe).
    """

    starts: int
    reached: int
    converged_fraction: float
    stalled: int
    stall_points: list
    penetrated: int
    min_clearance: float
    margin: float
    held_steps: int

    def to_dict(self) -> dict:
        """JSON-ready form."""
        return dataclasses.asdict(self)


@dataclass(frozen=True)
class ObstacleReport:
    """Outcome of :func:`check_obstacles`.

    Attributes:
        scene: The scene, as :meth:`Scene.to_dict`.
        random: Rollouts from random starts in the free part of the box.
        demos: Rollouts from the demonstrations' starts (those in free space).
        blocked_demos: Demonstrations whose path comes within the margin of an obstacle.
        dtw_free: Mean DTW (paper eq. 7, user units) of the rollouts from the starts of the
            demonstrations the obstacles leave free, to those demonstrations (None if none).
        dtw_free_without_obstacles: The same rollouts without the obstacles, for comparison.
        free_demos: Indices of those demonstrations.
        box: Half-width of the box of random starts, user units.
        horizon: Rollout duration, seconds.
        dt: Nominal step, seconds.
        tolerance: Distance counted as arrived, user units.
        cpu_seconds: Process CPU time of the check.
        wall_seconds: Wall-clock time of the check.
    """

    scene: dict
    random: RolloutCheck
    demos: RolloutCheck
    blocked_demos: list
    dtw_free: float | None
    dtw_free_without_obstacles: float | None
    free_demos: list
    box: float
    horizon: float
    dt: float
    tolerance: float
    cpu_seconds: float
    wall_seconds: float

    def to_dict(self) -> dict:
        """JSON-ready form."""
        return dataclasses.asdict(self)


def free_starts(
    scene: Scene, center: np.ndarray, half_width: float, count: int, rng: np.random.Generator
) -> np.ndarray:
    """``count`` uniform states of the box around ``center`` that are in free space, (count, n)."""
    found: list[np.ndarray] = []
    total = 0
    for _ in range(1000):
        draw = center + rng.uniform(-half_width, half_width, size=(2 * count, len(center)))
        keep = draw[scene.free(torch.as_tensor(draw)).numpy()]
        found.append(keep)
        total += len(keep)
        if total >= count:
            return np.concatenate(found)[:count]
    raise ConfigError("the obstacles leave almost no free space in the box of random starts")


def _cluster(policy: Policy, scene: Scene, ends: Tensor, extent: float, speed: float) -> list[dict]:
    """Clusters stalled end points; each {"center", "count", "gamma", "speed", "kind"}:
    "saddle" where the modulated field itself vanishes on a boundary, "held" where it still
    points into an obstacle and only the guard stops it (a concave junction of overlapping
    obstacles), "attractor" where the field vanishes in free space, else "moving"."""
    clusters: list[dict] = []
    for point in ends:
        for cluster in clusters:
            if float((point - cluster["point"]).norm()) <= 0.05 * extent:
                cluster["count"] += 1
                break
        else:
            clusters.append({"point": point, "count": 1})
    clusters.sort(key=lambda c: -c["count"])
    out = []
    for cluster in clusters[:20]:
        p = cluster["point"][None]
        velocity, gammas = Dynamics.of(policy, scene=scene, guard=False).velocity(p)
        gamma = float(gammas.min()) if gammas.numel() else math.inf
        fast = float(velocity.norm())
        on_boundary = gamma < 1.0 + 1e-3
        still = fast < 1e-3 * speed
        kind = (
            ("saddle" if still else "held") if on_boundary else ("attractor" if still else "moving")
        )
        out.append(
            {
                "center": p[0].tolist(),
                "count": cluster["count"],
                "gamma": gamma,
                "speed": fast,
                "kind": kind,
            }
        )
    return out


@torch.no_grad()
def check_obstacles(
    policy: Policy,
    demos: Demonstrations,
    scene: Scene,
    *,
    config: CheckConfig = CheckConfig(),
) -> ObstacleReport:
    """The stability report under obstacles: random free starts, the demonstrations' starts,
    and DTW to the demonstrations the obstacles leave free.

    Random starts are ``config.rollouts`` uniform states in the free part of the box of
    half-width ``box_factor`` x the extent around the target (rejection sampling, seeded by
    ``config.seed``); their rollouts are the check's (:func:`snds.stability.check_rollouts`,
    guarded against the obstacles), for ``horizon_factor`` x the longest demonstration's
    duration or until a stable policy's V shows them settled in a ball that no obstacle
    reaches. Among moving obstacles the steps are fixed at the data's step (the obstacles do
    not wait). A rollout has reached the target within ``tolerance_factor`` x the extent.
    Everything in float64.

    Arguments:
        policy: Any policy (a float64 copy is evaluated).
        demos: The demonstrations (extent, step, horizon, starts).
        scene: The obstacles.
        config: The check's settings (the decrease samples do not apply: the modulated field
            has no Lyapunov function).
    """
    wall, cpu = _time.perf_counter(), _time.process_time()
    policy = float64_copy(policy)
    scene.check(demos.dim, demos.target)
    rng = np.random.default_rng(config.seed)
    extent, target = demos.extent(), torch.tensor(demos.target)
    dt, horizon = demos.mean_dt(), config.horizon_factor * demos.max_duration()
    tolerance = config.tolerance_factor * extent
    box = config.box_factor * extent

    def rolled(starts: Tensor) -> RolloutCheck:
        if scene.moving:
            result = _moving(policy, scene, starts, dt=dt, horizon=horizon, config=config)
        else:
            result = check_rollouts(
                policy,
                starts,
                target,
                dt=dt,
                horizon=horizon,
                extent=extent,
                config=config,
                scene=scene,
            )
        return _summary(policy, scene, result, target, tolerance, extent, demos.max_speed())

    random = rolled(torch.as_tensor(free_starts(scene, demos.target, box, config.rollouts, rng)))
    demo_starts = torch.tensor(np.stack([d.positions[0] for d in demos]))
    from_demos = rolled(demo_starts[scene.free(demo_starts)])
    blocked, free_demos = [], []
    for i, demo in enumerate(demos):
        path = torch.tensor(demo.positions)
        (free_demos if bool(scene.free(path).all()) else blocked).append(i)
    dtw_free = dtw_plain = None
    if free_demos:
        paths = _reproduce_avoiding(policy, scene, demos, free_demos)
        plain = reproduce(policy, demos, free_demos)
        dtw_free = float(np.mean([dtw(p, demos[i].positions) for p, i in zip(paths, free_demos)]))
        dtw_plain = float(np.mean([dtw(p, demos[i].positions) for p, i in zip(plain, free_demos)]))
    return ObstacleReport(
        scene=scene.to_dict(),
        random=random,
        demos=from_demos,
        blocked_demos=blocked,
        dtw_free=dtw_free,
        dtw_free_without_obstacles=dtw_plain,
        free_demos=free_demos,
        box=box,
        horizon=horizon,
        dt=dt,
        tolerance=tolerance,
        cpu_seconds=_time.process_time() - cpu,
        wall_seconds=_time.perf_counter() - wall,
    )


def _moving(
    policy: Policy, scene: Scene, starts: Tensor, *, dt: float, horizon: float, config: CheckConfig
) -> Rollout:
    """Fixed guarded steps of ``dt`` among moving obstacles, to the horizon, with the
    clearance and penetrations of each state measured against the scene at its time."""
    steps = math.ceil(horizon / dt - 1e-9)
    stepper = GuardedEuler(max_halvings=config.max_halvings)
    result = rollout(policy, starts, dt=dt, steps=steps, stepper=stepper, scene=scene)
    clear = torch.full((len(starts),), math.inf, dtype=starts.dtype)
    entered = torch.zeros(len(starts), dtype=torch.bool)
    for k, states in enumerate(result.states):
        now = scene.at(k * dt)
        clear = torch.minimum(clear, now.clearances(states).min(dim=-1).values)
        entered = entered | ~now.free(states)
    return dataclasses.replace(result, min_clearance=clear, entered=entered)


def _summary(
    policy: Policy,
    scene: Scene,
    result: Rollout,
    target: Tensor,
    tolerance: float,
    extent: float,
    speed: float,
) -> RolloutCheck:
    """The :class:`RolloutCheck` of the check's rollouts from one set of starts."""
    count = len(result.final)
    arrived = (result.final - target).norm(dim=-1) <= tolerance
    margins = [b.margin for b in scene.bodies] or [0.0]
    return RolloutCheck(
        starts=count,
        reached=int(arrived.sum()),
        converged_fraction=float(arrived.double().mean()) if count else float("nan"),
        stalled=int((~arrived).sum()),
        stall_points=_cluster(policy, scene, result.final[~arrived], extent, speed),
        penetrated=int(result.entered.sum()),
        min_clearance=float(result.min_clearance.min()) if count else float("nan"),
        margin=float(min(margins)),
        held_steps=result.held,
    )


def _reproduce_avoiding(
    policy: Policy, scene: Scene, demos: Demonstrations, indices: list[int]
) -> list[np.ndarray]:
    """Guarded rollouts under the obstacles from demonstrations' starts, each with its own
    mean step and number of steps (as :func:`snds.evaluate.reproduce` without them)."""
    steps = [len(demos[i].times) - 1 for i in indices]
    dt = torch.tensor([demos[i].duration / k for i, k in zip(indices, steps)], dtype=torch.float64)
    x0 = torch.as_tensor(np.stack([demos[i].positions[0] for i in indices]))
    result = rollout(
        policy,
        x0,
        dt=dt,
        steps=torch.tensor(steps),
        stepper=GuardedEuler(max_halvings=40),
        scene=scene,
    )
    paths = result.states.transpose(0, 1).numpy()
    return [paths[row, : k + 1] for row, k in enumerate(steps)]
