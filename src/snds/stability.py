r"""Stability checks: does the policy reach the target in useful time, from everywhere?

The guarantee of :func:`snds.policy.project` is :math:`\nabla V^\top \pi \le -a(x)`; this
module checks it numerically on a dense sample and, independently of any Lyapunov function,
rolls the policy out from random starts far from the demonstrations.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import torch

from snds.arrival import ARRIVAL_TOLERANCE
from snds.decrease import decrease_violations, largest_safe_step
from snds.errors import ConfigError
from snds.policy import Policy, float64_copy
from snds.rollout import Arrival, Rollout, StepControl, rollout
from snds.steppers import GuardedEuler

__all__ = [
    "ROLLOUTS",
    "SAMPLES",
    "CheckConfig",
    "StabilityReport",
    "check_rollouts",
    "check_stability",
    "decrease_violations",
    "largest_safe_step",
    "settle_level",
]

#: Random starts of the stability check by default. If every one of N independent uniform
#: starts converges, the fraction of the start box from which the policy does not converge is
#: below 1 - 0.05^(1/N) with 95% confidence: 0.6% for N = 500.
ROLLOUTS = 500
#: States of the decrease-condition check by default: with no violation among N uniform
#: states, the violating fraction of the sample box is below 3 / N (6e-5) with 95% confidence.
SAMPLES = 50_000


@dataclass(frozen=True, kw_only=True)
class CheckConfig:
    """The settings of :func:`check_stability` and of the check under obstacles
    (:func:`snds.obstacles.check_obstacles`), with the library's defaults.

    One configuration serves both checks, because what they report means the same: with
    ``rollouts`` = 500 starts that all arrive, the fraction of the box from which the policy
    does not arrive is below 0.6% with 95% confidence, obstacles or not; and a local error of
    3e-3 extents per step keeps arrival times and end points to well within the arrival
    tolerance (1e-2 extents) in both. These are the defaults the check without obstacles has
    always had, so its results are unchanged.

    Attributes:
        rollouts: Random starts (with ``grid``, at least this many grid points).
        samples: Random states of the decrease check (0 to skip it).
        grid: Start from a regular grid of positions over the box (k points per axis,
            k^n >= rollouts, corners included) instead of uniform random states.
        box_factor: Half-width of the box of starts, in extents.
        horizon_factor: The cap on a rollout's duration, in longest-demonstration durations:
            rollouts run until they arrive (and a policy with V until it has settled), at
            most this long; the report gives their times to arrive.
        tolerance_factor: Arrival tolerance, in error scales (the extent for positions; pi
            radians for angles): :data:`snds.arrival.ARRIVAL_TOLERANCE`.
        min_step_budget: Fewest integration steps a rollout may take before it counts as
            still moving (see :func:`check_rollouts`): a step the guard shortens is one
            step, so a stiff field runs out of steps before the cap.
        sample_box_factor: Half-width of the decrease samples' box, in extents.
        step_tolerance_factor: Local error allowed per adaptive step, in extents.
        seed: Seed of the random starts and samples.
        chunk: States per batch of the decrease check (bounds memory).
        max_halvings: Halvings of a guarded step before it is taken anyway.
    """

    rollouts: int = ROLLOUTS
    samples: int = SAMPLES
    grid: bool = False
    box_factor: float = 3.0
    horizon_factor: float = 10.0
    tolerance_factor: float = ARRIVAL_TOLERANCE
    min_step_budget: int = 2000
    sample_box_factor: float = 10.0
    step_tolerance_factor: float = 3e-3
    seed: int = 0
    chunk: int = 20_000
    max_halvings: int = 30

    def __post_init__(self) -> None:
        if self.rollouts < 1:
            raise ConfigError(f"rollouts must be >= 1, got {self.rollouts}")
        if self.samples < 0:
            raise ConfigError(f"samples must be >= 0, got {self.samples}")

    def to_dict(self) -> dict:
        """JSON-ready form."""
        return asdict(self)


@dataclass(frozen=True)
class StabilityReport:
    """Outcome of :func:`check_stability`.

    Attributes:
        rollouts: Number of rollouts from random starts.
        converged_fraction: Fraction that ended within the tolerance of the target.
        max_final_distance: Largest distance of a rollout's end position from the target's
            (user units); a settled rollout (see :func:`check_rollouts`) ends where it
            settled.
        max_final_errors: The largest end error of each component of the policy's space
            (:meth:`snds.spaces.Space.errors`: "distance", and "angle" in radians for poses).
        spurious_attractors: Places where rollouts stopped away from the target: end points
            outside the tolerance where the policy's speed is below 1e-3 of the fastest
            demonstrated speed, clustered within 5% of the extent; each {"center", "count"},
            the 20 largest clusters, largest first.
        still_moving: Rollouts outside the tolerance at the end that were still moving (too
            slow, or circling).
        out_of_steps: Rollouts that had not arrived when their step budget ran out, before
            the cap (the guard kept shortening their steps: a stiff field).
        median_time_to_converge: Median time (s) to enter the tolerance for good, over the
            converged rollouts (NaN if none converged); the same as ``time_to_arrive_median``.
        time_to_arrive_median: Median time to arrive (:func:`snds.arrival.arrival_time`), s,
            over the rollouts that arrived (NaN if none did).
        time_to_arrive_max: The longest time to arrive, s, over those that arrived.
        duration: The longest demonstration's duration, s: the unit of the two below.
        time_to_arrive_median_durations: ``time_to_arrive_median`` / ``duration``.
        time_to_arrive_max_durations: ``time_to_arrive_max`` / ``duration``.
        samples_checked: States at which the decrease condition was checked (0 for a policy
            without a Lyapunov function).
        decrease_violations: States where grad V . pi > -a(x) beyond rounding error.
        largest_safe_dt: Largest Euler step (s) that decreases V at every sampled state and at
            every state visited by the rollouts (NaN for a policy without a Lyapunov
            function); compare with ``dt``: plain Euler at a step above it may cycle.
        largest_safe_dt_on_rollouts: The same over the visited states only (stiff spots of
            the field near the target are found there rather than by random sampling).
        integrator: "guarded euler" for a policy with a Lyapunov function (see
            :func:`snds.rollout.guarded_step`), else "euler".
        shortened_fraction: Fraction of rollouts in which the guard shortened a step, i.e.
            where plain Euler at ``dt`` would not have decreased V (0 without a guard).
        v_rises: Accepted steps at which V rose even after the guard's halvings (0 for a
            policy without V): the discrete decrease along the rollouts, as the robot moves.
        box: Half-width of the box of random starts, in user units.
        horizon: The cap on each rollout's duration, in seconds (``horizon_factor`` x
            ``duration``); a rollout stops earlier once it has arrived and settled.
        step_budget: The most integration steps of one rollout.
        dt: Time step of the rollouts, in seconds.
        tolerance: Distance counted as arrived, in user units.
        tolerances: The arrival tolerance of each error component (a rollout has converged
            when it is within all of them).
    """

    rollouts: int
    converged_fraction: float
    max_final_distance: float
    max_final_errors: dict
    spurious_attractors: list
    still_moving: int
    out_of_steps: int
    median_time_to_converge: float
    time_to_arrive_median: float
    time_to_arrive_max: float
    duration: float
    time_to_arrive_median_durations: float
    time_to_arrive_max_durations: float
    samples_checked: int
    decrease_violations: int
    largest_safe_dt: float
    largest_safe_dt_on_rollouts: float
    integrator: str
    shortened_fraction: float
    v_rises: int
    box: float
    horizon: float
    step_budget: int
    dt: float
    tolerance: float
    tolerances: dict

    def to_dict(self) -> dict:
        """JSON-ready form."""
        return asdict(self)


@torch.no_grad()
def check_stability(
    policy: Policy, demos: Any, config: CheckConfig = CheckConfig()
) -> StabilityReport:
    """Rolls out from random starts and checks the decrease condition on a dense sample.

    One check for every state space (the policy's :attr:`~snds.policy.Policy.space`): rollouts
    start in a box of half-width ``box_factor`` x the extent (the largest distance of a
    demonstrated position from the target) around the target, with orientations uniform over all
    of SO(3) for poses, and run until they arrive, for ``horizon_factor`` x the longest
    demonstration's duration at most, adaptive Euler steps of at least the demonstrations' mean
    time step along the space's :meth:`~snds.spaces.Space.advance`, guarded (see
    :func:`snds.rollout.guarded_step`) for a policy with a Lyapunov function; the report gives
    their times to arrive, says in how many rollouts the guard had to shorten a step, and the
    largest step that is safe along the rollouts. A rollout has converged if it ends within
    ``tolerance_factor`` x each error scale of the target (the extent; pi radians for an angle):
    the robot must get there in useful time, not only asymptotically. Rollouts of a policy with
    a Lyapunov function stop early once they are provably settled (see
    :func:`check_rollouts`).
    Everything runs in float64.

    Arguments:
        policy: The policy (a copy is evaluated in float64; the original is not changed).
        demos: The demonstrations that define the extent, time step and horizon
            (:class:`~snds.data.Demonstrations`, or :class:`~snds.data.PoseDemonstrations`
            for a pose policy).
        config: The check's sizes and factors.
    """
    policy = float64_copy(policy)
    space = policy.space
    rng = np.random.default_rng(config.seed)
    extent = demos.extent()
    target = np.asarray(demos.target, dtype=np.float64)
    dt = demos.mean_dt()
    duration = demos.max_duration()
    horizon = config.horizon_factor * duration
    half_width = config.box_factor * extent
    draw = space.grid if config.grid else space.uniform
    points = draw(target, half_width, config.rollouts, rng)
    # On the policy's device (a policy trained with --device cuda is checked there too).
    device = getattr(policy, "center", torch.empty(0)).device
    starts = torch.as_tensor(points, device=device)
    target_t = torch.tensor(target, device=device)
    arrivals = check_rollouts(
        policy, starts, target_t, dt=dt, horizon=horizon, extent=extent, config=config
    )
    tolerance = config.tolerance_factor
    scales_t = torch.as_tensor(space.error_scales(extent), device=device)
    errors = space.errors(arrivals.final, target_t) / scales_t  # (B, k), in error scales
    outside = (errors > tolerance).any(dim=-1) | ~torch.isfinite(errors).all(dim=-1)
    attractors, moving = _stalled(policy, demos, arrivals.final[outside], extent=extent)
    times = arrivals.arrival_time[~outside & ~arrivals.arrival_time.isnan()]
    median = float(times.median()) if len(times) else float("nan")
    slowest = float(times.max()) if len(times) else float("nan")
    violations, checked = 0, 0
    safe_dt = safe_dt_rollouts = float("nan")
    if policy.stable:
        upper = 10.0 * demos.max_duration()
        visited = arrivals.states
        if len(visited) > config.chunk:
            pick = rng.choice(len(visited), config.chunk, replace=False)
            visited = visited[torch.as_tensor(pick, device=device)]
        safe_dt = safe_dt_rollouts = largest_safe_step(policy, visited, upper=upper)
    if policy.stable and config.samples > 0:
        points = space.uniform(target, config.sample_box_factor * extent, config.samples, rng)
        for begin in range(0, config.samples, config.chunk):
            batch = torch.as_tensor(points[begin : begin + config.chunk], device=device)
            terms = policy.field_terms(policy.to_model(batch))
            violations += decrease_violations(policy, batch, terms=terms)
            safe_dt = min(safe_dt, largest_safe_step(policy, batch, upper=safe_dt, terms=terms))
        checked = config.samples
    scales = space.error_scales(extent)
    finite = bool(torch.isfinite(errors).all())
    largest = errors.max(dim=0).values.cpu().numpy() * scales
    return StabilityReport(
        rollouts=len(starts),
        converged_fraction=float((~outside).double().mean()),
        max_final_distance=float(largest[0]) if finite else float("inf"),
        max_final_errors={
            name: float(value) if finite else float("inf")
            for name, value in zip(space.error_names, largest)
        },
        spurious_attractors=attractors,
        still_moving=moving,
        out_of_steps=int((arrivals.out_of_steps & outside).sum()),
        median_time_to_converge=median,
        time_to_arrive_median=median,
        time_to_arrive_max=slowest,
        duration=duration,
        time_to_arrive_median_durations=median / duration,
        time_to_arrive_max_durations=slowest / duration,
        samples_checked=checked,
        decrease_violations=violations,
        largest_safe_dt=safe_dt,
        largest_safe_dt_on_rollouts=safe_dt_rollouts,
        integrator="guarded euler" if policy.stable else "euler",
        shortened_fraction=float(arrivals.shortened.double().mean()),
        v_rises=arrivals.v_rises,
        box=half_width,
        horizon=horizon,
        step_budget=arrivals.budget,
        dt=dt,
        tolerance=float(tolerance * scales[0]),
        tolerances={
            name: float(tolerance * scale) for name, scale in zip(space.error_names, scales)
        },
    )


def _scaled_speed(space_scales: torch.Tensor, velocity: torch.Tensor) -> torch.Tensor:
    """Speeds (B,) of velocities (B, k) with each component divided by its scale."""
    return (velocity / space_scales).norm(dim=-1)


def _stalled(
    policy: Policy, demos: Any, ends: torch.Tensor, *, extent: float
) -> tuple[list[dict], int]:
    """Clusters the end points that stalled (spurious attractors); counts those still moving.

    A state has stalled where the policy's speed, each component in its scale (see
    :meth:`snds.spaces.Space.tangent_scales`), is below 1e-3 of the fastest demonstrated
    one; end points within 5% of every error scale of each other form one cluster.
    """
    if len(ends) == 0:
        return [], 0
    space = policy.space
    scales = torch.as_tensor(space.tangent_scales(extent), device=ends.device)
    fastest = max(
        float(_scaled_speed(scales.cpu(), torch.tensor(demo.velocities)).max()) for demo in demos
    )
    finite = torch.isfinite(ends).all(dim=-1)
    speed = _scaled_speed(scales, policy(ends[finite]))
    stalled = ends[finite][speed < 1e-3 * fastest]
    clusters: list[dict] = []
    # Greedy clustering: few points, and a cluster radius much smaller than the box.
    for point in stalled:
        for cluster in clusters:
            if bool((space.scaled_errors(point, cluster["center"], extent) <= 0.05).all()):
                cluster["count"] += 1
                break
        else:
            clusters.append({"center": point, "count": 1})
    clusters.sort(key=lambda c: -c["count"])
    # The 20 largest are enough to see where a policy gets stuck and keep metrics.json short.
    attractors = [{"center": c["center"].tolist(), "count": c["count"]} for c in clusters[:20]]
    return attractors, int(len(ends) - len(stalled))


def settle_level(lyapunov: torch.nn.Module, radius: float, *, dim: int, count: int = 4096) -> float:
    r"""A level c whose sublevel set :math:`\{V < c\}` lies inside the ball :math:`|x| < r`.

    With a quadratic floor :math:`V \ge d |x|^2` (model coordinates), :math:`c = d r^2`
    exactly. Without one (``quadratic = 0``, SDS-EF), c is half the smallest V found on
    ``count`` points of the sphere :math:`|x| = r` (a seeded Fibonacci lattice in 2-D, a seeded
    uniform sample above). That is enough: the sublevel sets of a strict Lyapunov function are
    connected (each component would hold a minimum of V, a critical point, and the only one is
    the target), so a set that contains the target and misses the sphere lies inside it. The
    sample makes c a well-founded estimate rather than a bound; the factor 1/2 is its margin.

    Arguments:
        lyapunov: V in model coordinates, with its ``quadratic`` floor d.
        radius: r, in model coordinates.
        dim: The state dimension n.
        count: Points on the sphere when there is no floor.
    """
    floor = float(lyapunov.quadratic)
    if floor > 0:
        return floor * radius**2
    if dim == 2:
        angles = torch.arange(count, dtype=torch.float64) * (2 * torch.pi / count)
        directions = torch.stack([angles.cos(), angles.sin()], dim=-1)
    else:
        generator = torch.Generator().manual_seed(0)
        directions = torch.randn(count, dim, generator=generator, dtype=torch.float64)
        directions = directions / directions.norm(dim=-1, keepdim=True)
    like = next(lyapunov.parameters(), torch.empty(0, dtype=torch.float64))
    return 0.5 * float(lyapunov((radius * directions).to(like)).min())


@torch.no_grad()
def check_rollouts(
    policy: Policy,
    starts: torch.Tensor,
    target: torch.Tensor,
    *,
    dt: float,
    horizon: float,
    extent: float,
    config: CheckConfig,
    scene: Any = None,
) -> Rollout:
    r"""The check's rollouts: adaptive guarded Euler (:func:`snds.rollout.rollout` with a
    :class:`~snds.rollout.StepControl`) that stop integrating each start once it has settled.

    Each rollout takes Euler steps along the policy's space whose length follows the local
    error, kept below ``step_tolerance_factor`` tangent scales, between the shortest standard
    step (the data's step ``dt``, or horizon / 500 for data sampled coarser) and horizon /
    50; no step moves a state by more than 5% of its distance to the target, unless it is no
    longer than the shortest. A policy with a Lyapunov function takes the guarded step
    (:class:`~snds.steppers.GuardedEuler`, Armijo's condition on V), so V falls at every
    accepted step; with a ``scene`` the step also never ends inside an inflated obstacle. The
    sublevel set {V < c} of :func:`settle_level` lies inside the model-coordinate ball whose
    image is within half of every tolerance (:meth:`~snds.policy.Policy.model_scale`), and
    guarded steps never leave it: a start whose state enters it is settled and no longer
    integrated (with a scene, only if no obstacle reaches that ball), so the check costs the
    time rollouts take to arrive.

    A rollout takes at most as many accepted steps as fixed steps of the shortest standard
    step would take to the horizon, and at least ``min_step_budget``; those stopped by this
    budget before the horizon are marked ``out_of_steps``. States are recorded at the start
    and every 10 steps; ``shortened`` marks the rollouts at one of whose recorded states
    plain Euler at ``dt`` would not have met the guard's condition.
    """
    space = policy.space
    tolerance = config.tolerance_factor
    min_step = min(dt, horizon / 500)
    level = None
    if policy.stable:
        # The model-coordinate radius whose image lies within half of every tolerance.
        reach = policy.model_scale() / space.error_scales(extent)
        radius = 0.5 * tolerance / float(reach.max())
        if scene is None or not _reaches(scene, target, 0.5 * tolerance * extent):
            level = settle_level(policy.lyapunov, radius, dim=policy.dim)
    control = StepControl(
        tolerance=config.step_tolerance_factor,
        min_step=min_step,
        max_step=horizon / 50,
        horizon=horizon,
        # Steps the guard shortens still count as steps, so a field so stiff that the guard
        # shrinks every step ends after as many steps as fixed steps would take.
        budget=max(int(np.ceil(horizon / min_step)), config.min_step_budget),
        tangent_scales=torch.as_tensor(space.tangent_scales(extent)),
        settle=level,
    )
    arrival = Arrival.of(space, target, extent, tolerance=tolerance)
    return rollout(
        policy,
        starts,
        dt=dt,
        stepper=GuardedEuler(max_halvings=config.max_halvings),
        scene=scene,
        control=control,
        arrival=arrival,
    )


def _reaches(scene: Any, target: torch.Tensor, radius: float) -> bool:
    """Whether any body of a scene modulates the field within ``radius`` of the target."""
    generator = torch.Generator().manual_seed(0)
    directions = torch.randn(256, len(target), generator=generator, dtype=target.dtype)
    ball = target[None] + radius * directions / directions.norm(dim=-1, keepdim=True)
    return bool(scene.influenced(ball).any()) or bool(scene.influenced(target[None])[0])
