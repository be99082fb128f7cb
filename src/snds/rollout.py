r"""Rollouts: the one engine that integrates a policy from a batch of starts.

:func:`rollout` serves every consumer: reproductions of the demonstrations, the stability
check (:mod:`snds.stability`, with or without obstacles), the plots, the simulator's reference
paths and the page. It takes a :class:`~snds.policy.Policy` (or any
:class:`~snds.steppers.Dynamics`), a :class:`~snds.steppers.Stepper` (plain
:class:`~snds.steppers.Euler`, :class:`~snds.steppers.RK4`, or
:class:`~snds.steppers.GuardedEuler`, whose every step decreases V), an optional obstacle
scene that modulates the field and that no guarded step ends in, and a stopping rule; every
state shape (positions, poses, a phase after either) moves through its space's ``advance``.

Fixed steps (the default) integrate the whole batch at every step, so a row's path does not
depend on when the others stop. With a :class:`StepControl` the steps adapt to the local
error, and each row leaves the batch once it has finished (arrived and settled, its budget
spent, or at the horizon): the stability check's rollouts.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from snds.arrival import arrival_time
from snds.errors import ConfigError
from snds.policy import Policy
from snds.spaces import Space
from snds.steppers import (
    Dynamics,
    Euler,
    Field,
    Stepper,
    guarded_step,
    policy_guard,
    safe_velocity,
    speed_scale,
)

__all__ = [
    "Arrival",
    "Rollout",
    "StepControl",
    "converged_at",
    "guarded_step",
    "policy_guard",
    "rollout",
    "rollout_numpy",
    "safe_velocity",
    "speed_scale",
]


@dataclass(frozen=True, kw_only=True)
class Arrival:
    """When a state has arrived: within ``tolerance`` of every error scale of the target.

    Attributes:
        space: The states' space (its :meth:`~snds.spaces.Space.errors`).
        target: The target state, shape (m,).
        scales: The error scales (:meth:`~snds.spaces.Space.error_scales`), shape (k,).
        tolerance: Arrived within this many error scales of every component.
    """

    space: Space
    target: Tensor
    scales: Tensor
    tolerance: float

    @classmethod
    def of(cls, space: Space, target: Tensor, extent: float, *, tolerance: float) -> Arrival:
        """The arrival rule of ``space`` around ``target`` for data of ``extent``."""
        scales = torch.as_tensor(space.error_scales(extent), dtype=target.dtype).to(target.device)
        return cls(space=space, target=target, scales=scales, tolerance=tolerance)

    def errors(self, x: Tensor) -> Tensor:
        """The errors of states (*, m) in their scales, (*, k)."""
        return self.space.errors(x, self.target) / self.scales

    def __call__(self, x: Tensor) -> Tensor:
        """Whether states (*, m) are within the tolerance, (*,)."""
        return (self.errors(x) <= self.tolerance).all(dim=-1)

    def steps(self, states: Tensor) -> np.ndarray:
        """The step from which each rollout (T + 1, B, m) stays arrived to its end
        (:func:`snds.arrival.arrival_time`), shape (B,); -1 where it ends outside."""
        errors = self.errors(states).transpose(0, 1).cpu().numpy()  # (B, T + 1, k)
        times = np.arange(states.shape[0])
        found = np.array([arrival_time(times, e, self.tolerance) for e in errors])
        return np.nan_to_num(found, nan=-1).astype(int)


@dataclass(frozen=True, kw_only=True)
class StepControl:
    r"""Error-controlled steps for :func:`rollout`.

    A step's local error is estimated as :math:`e = \tfrac{h}{2} |\pi(x_{k+1}) - \pi(x_k)|`
    (the leading term of Euler's, from the velocity the next step needs anyway; each component
    in its :meth:`~snds.spaces.Space.tangent_scales`). A step with :math:`e` above
    ``tolerance`` is rejected unless it is no longer than ``min_step``; the next step is
    :math:`h \sqrt{\text{tol} / e}` (times 0.9, within [0.2, 4] times h), within
    [``min_step``, ``max_step``], and no longer than moves a state by ``approach`` of its
    distance to the target (unless that is below ``min_step``); the last step ends at the
    ``horizon``. A row stops at the horizon, after ``budget`` accepted steps, or once its V
    is below ``settle`` (a sublevel set inside the arrival ball, :func:`settle_level`).

    Attributes:
        tolerance: Local error allowed per step, in tangent scales.
        min_step: The shortest step, always accepted (seconds).
        max_step: The longest step (seconds).
        horizon: The cap on each rollout's duration (seconds).
        budget: Most accepted steps of one rollout.
        tangent_scales: The space's tangent scales, shape (k,).
        settle: V below which a row has settled (None: none).
        approach: Largest fraction of the distance to the target one step may cover.
    """

    tolerance: float
    min_step: float
    max_step: float
    horizon: float
    budget: int
    tangent_scales: Tensor
    settle: float | None = None
    approach: float = 0.05


@dataclass(frozen=True)
class Rollout:
    """What :func:`rollout` computed.

    Attributes:
        states: The recorded states, (R, B, m): every step with fixed steps (R = steps + 1);
            with a :class:`StepControl`, the states still integrated at the start and every
            ``record_every`` steps, concatenated, shape (R, m).
        times: The time of each recorded state, (R, B) with fixed steps (else None).
        taken: The step each row took at each step, (steps, B) with fixed steps (0 where a
            scene's guard held the state; None with a control).
        final: The last state of each row, (B, m).
        final_time: The time of each row's last state, (B,).
        arrival_time: With a control, the time from which each row has been arrived, NaN if
            it ends outside (else None).
        steps: Integration steps taken (of the longest row).
        out_of_steps: Rows stopped by the budget before the horizon, (B,) (control only).
        budget: The control's step budget of one row (0 without a control).
        shortened: Rows at one of whose recorded states a plain Euler step of ``dt`` would not
            have met the guard's condition (control with V only; else all False).
        v_rises: Accepted steps at which V rose even after every halving.
        held: Steps at which a scene's guard held a state.
        min_clearance: Smallest distance of each row to a scene's physical shapes, (B,)
            (None without a scene).
        entered: Rows with a state inside an inflated obstacle, (B,) (None without a scene).
    """

    states: Tensor
    times: Tensor | None
    taken: Tensor | None
    final: Tensor
    final_time: Tensor
    arrival_time: Tensor | None = None
    steps: int = 0
    out_of_steps: Tensor | None = None
    budget: int = 0
    shortened: Tensor | None = None
    v_rises: int = 0
    held: int = 0
    min_clearance: Tensor | None = None
    entered: Tensor | None = None


@torch.no_grad()
def rollout(
    system: Policy | Dynamics | Field,
    x0: Tensor,
    *,
    dt: float | Tensor,
    steps: int | Tensor | None = None,
    stepper: Stepper = Euler(),
    scene=None,
    guard: bool = True,
    start_time: float = 0.0,
    duration: float | None = None,
    until=None,
    check_every: int = 1,
    control: StepControl | None = None,
    arrival: Arrival | None = None,
    record_every: int = 10,
) -> Rollout:
    r"""Integrates :math:`\dot x = \pi(x)` from a batch of starts.

    Arguments:
        system: A policy (along its space, guarded by its V if stable and ``guard``), a
            :class:`~snds.steppers.Dynamics`, or a bare field (B, n) -> (B, n) in R^n.
        x0: Start states, shape (B, m).
        dt: The nominal step, one or one per row (B,), seconds; with a control, the first.
        steps: Most steps, one or one per row (B,): a row stops after its own. With a
            control, unused (the control's budget applies).
        stepper: The one-step method.
        scene: Obstacles (:class:`snds.obstacles.Scene`) for a policy's field; moving ones
            move with the shared clock (step index times ``dt``).
        guard: With a policy, whether a stable one's V guards the steps.
        start_time: The time of the starts, seconds (fixed steps).
        duration: A row stops once its time reaches this (fixed steps).
        until: A rule states (B, m) -> (B,) bool (such as an :class:`Arrival`): the rollout
            ends at the first check, every ``check_every`` steps, at which it holds for every
            row (or the row is held by a static scene's guard, for good).
        check_every: Steps between checks of ``until``.
        control: Error-controlled adaptive steps (:class:`StepControl`), which need
            ``arrival``.
        arrival: The arrival rule a control measures arrival times with.
        record_every: With a control, record the states every this many steps.
    """
    if isinstance(system, Policy):
        dynamics = Dynamics.of(system, scene=scene, guard=guard)
    elif isinstance(system, Dynamics):
        dynamics = system
    else:
        dynamics = Dynamics(field=system)
    if control is not None:
        if arrival is None:
            raise ValueError("a rollout with a step control needs an arrival rule")
        return _adaptive(dynamics, x0, dt, stepper, control, arrival, record_every)
    h = dt.to(x0) if isinstance(dt, Tensor) else torch.full_like(x0[:, 0], dt)
    if steps is None:
        raise ValueError("a rollout with fixed steps needs steps")
    remaining = torch.as_tensor(steps, device=x0.device).expand(len(x0)).clone()
    moving = dynamics.scene is not None and dynamics.scene.moving
    if moving and isinstance(dt, Tensor):
        raise ConfigError("rollouts among moving obstacles need one time step for all rows")
    x, value, time = x0, None, torch.full_like(h, start_time)
    static = dynamics.scene is not None and not moving
    held = torch.zeros_like(h, dtype=torch.bool) if static else None
    states, times, taken = [x0], [time], []
    for step in range(int(remaining.max()) if len(x0) else 0):
        live = remaining > 0
        if duration is not None:
            live = live & (time < duration)
        if not bool(live.any()):
            break
        # The obstacles do not wait: the shared clock advances by the nominal step.
        t = start_time + step * float(dt) if moving else 0.0
        result = stepper.step(dynamics, x, h, t=t, value=value, held=held)
        if bool(live.all()):
            x, moved, value = result.states, result.taken, result.value
        else:
            x = torch.where(live.unsqueeze(-1), result.states, x)
            moved = torch.where(live, result.taken, 0.0)
            if value is not None and result.value is not None:
                value = torch.where(live, result.value, value)
            else:
                value = None
        time = time + moved
        remaining = remaining - 1
        if static:
            # A held state stays held: the same state, velocity and scene.
            held = held | (live & (moved == 0))
        states.append(x)
        times.append(time)
        taken.append(moved)
        if until is not None and len(taken) % check_every == 0:
            # A row a static scene holds will not move again: it has ended as well.
            ended = until(x) if held is None else until(x) | held
            if bool(ended.all()):
                break
    taken_t = torch.stack(taken) if taken else h.new_zeros((0, len(x0)))
    return Rollout(
        torch.stack(states),
        torch.stack(times),
        taken_t,
        x,
        time,
        steps=len(taken),
        held=int((taken_t == 0).sum()) if dynamics.scene is not None else 0,
    )


def _adaptive(
    dynamics: Dynamics,
    starts: Tensor,
    dt: float | Tensor,
    stepper: Stepper,
    control: StepControl,
    arrival: Arrival,
    every: int,
) -> Rollout:
    """The rollout of :func:`rollout` with a :class:`StepControl`; rows leave the batch as
    they finish. ``dt`` is the data's step, at which the ``shortened`` probe is taken."""
    count, scene = len(starts), dynamics.scene
    dt = float(dt)
    x = starts.clone()
    like = {"dtype": x.dtype, "device": x.device}
    tangent = control.tangent_scales.to(**like)
    tolerance, horizon = arrival.tolerance, control.horizon
    min_step, max_step = control.min_step, control.max_step
    time = torch.zeros(count, **like)
    h = torch.full_like(time, min_step)
    # Time since which each rollout has been within the tolerance (NaN while outside).
    since = torch.zeros_like(time)
    active = torch.arange(count, device=x.device)
    visited = []
    shortened = torch.zeros(count, dtype=torch.bool, device=x.device)
    # Counted on the device, read once at the end: no host sync per step.
    rises = torch.zeros((), dtype=torch.long, device=x.device)
    lyapunov, rate = dynamics.lyapunov, dynamics.rate
    # V is carried from step to step where it guards every step (no scene); a scene's guard
    # asks for V only outside the obstacles' influence.
    carried = lyapunov is not None and scene is None and dynamics.velocity_and_value is not None
    value = gammas = clear = entered = None
    if carried:
        velocity, value = dynamics.velocity_and_value(x)
    else:
        velocity, gammas = dynamics.velocity(x)
    if scene is not None:
        clear = scene.clearances(x).min(dim=-1).values
        entered = ~scene.free(x)
    held = 0
    since[(arrival.errors(x) > tolerance).any(dim=-1)] = float("nan")
    taken = torch.zeros(count, dtype=torch.long, device=x.device)
    steps = 0
    while len(active):
        xa, va, ha = x[active], velocity[active], h[active]
        if steps % every == 0:
            visited.append(xa.clone())
            if carried:
                # Would plain Euler at the data's step meet the guard's condition here?
                before = value[active]
                after = lyapunov(dynamics.advance(xa, torch.full_like(ha, dt), va))
                required = 0.5 * dt * rate(xa, before)
                bad = ~((after <= before - required) & (after < before)) & (before > 0)
                shortened[active[bad]] = True
        # No step moves a state by more than ``approach`` of its distance to the target:
        # relative accuracy on the final approach, and arrival times resolved to a twentieth
        # of the time left. The last step ends exactly at the horizon.
        distance = arrival.errors(xa).max(dim=-1).values
        reach = control.approach * distance / (va / tangent).norm(dim=-1)
        ha = torch.minimum(ha, reach.nan_to_num(nan=dt).clamp_min(min_step))
        ha = torch.minimum(ha, horizon - time[active])
        nominal = ha
        if carried:
            before = value[active]
            # V at the full step comes from the pass that gives the velocity there; only the
            # steps the guard shortens need the velocity again.
            candidate = dynamics.advance(xa, ha, va)
            v_new, new = dynamics.velocity_and_value(candidate)
            result = stepper.step(
                dynamics, xa, ha, velocity=va, value=before, first=(candidate, new)
            )
            candidate, ha = result.states, result.taken
            new = new if result.value is None else result.value
            shorter = (ha < nominal).nonzero()[:, 0]
            if len(shorter):
                v_new[shorter] = dynamics.field(candidate[shorter])
        else:
            known = {} if gammas is None else {"gammas": gammas[active]}
            result = stepper.step(dynamics, xa, ha, velocity=va, **known)
            candidate, ha = result.states, result.taken
            v_new, g_new = dynamics.velocity(candidate)
        error = 0.5 * ha * ((v_new - va) / tangent).norm(dim=-1)
        # A step no longer than the shortest standard one is always accepted: at worst the
        # rollout integrates at that step, never slower.
        accept = (error <= control.tolerance) | (ha <= min_step)
        # A non-finite error (a diverging field without V) shrinks the step, to dt at least.
        grow = (0.9 * (control.tolerance / error).sqrt()).nan_to_num(nan=0.2).clamp(0.2, 4.0)
        proposed = torch.where(accept, ha * grow, ha * grow.clamp_max(0.9))
        # A state a scene's guard held waits a longer period next (it may be a stall); its
        # clock passes the period it waited.
        stuck = ha == 0
        if scene is not None:
            held += int(stuck.sum())
            proposed = torch.where(stuck, 4.0 * nominal, proposed)
        h[active] = proposed.clamp(min_step, max_step)
        done = active[accept]
        x[done], velocity[done] = candidate[accept], v_new[accept]
        time[done] = time[done] + torch.where(stuck, nominal, ha)[accept]
        taken[done] += 1
        if carried:
            # Only a step that ran out of halvings can raise V (V below 1e-12 is the target
            # up to rounding).
            rose = (new > before * (1 + 1e-9)) & (before > 1e-12) & accept
            rises += rose.sum()
            value[done] = new[accept]
        if gammas is not None:
            gammas[done] = g_new[accept]
        if scene is not None:
            clear[done] = torch.minimum(clear[done], scene.clearances(x[done]).min(dim=-1).values)
            entered[done] = entered[done] | ~scene.free(x[done])
        outside = (arrival.errors(x[done]) > tolerance).any(dim=-1)
        since[done[outside]] = float("nan")
        entered_ball = done[~outside & since[done].isnan()]
        since[entered_ball] = time[entered_ball]
        steps += 1
        finished = (time[active] >= horizon * (1 - 1e-12)) | (taken[active] >= control.budget)
        if control.settle is not None:
            level = value[active] if carried else lyapunov(x[active])
            finished = finished | (level < control.settle)
        active = active[~finished]
    return Rollout(
        torch.cat(visited),
        None,
        None,
        x,
        time,
        arrival_time=since,
        steps=steps,
        out_of_steps=(taken >= control.budget) & (time < horizon * (1 - 1e-12)),
        budget=control.budget,
        shortened=shortened,
        v_rises=int(rises),
        held=held,
        min_clearance=clear,
        entered=entered,
    )


def converged_at(states: Tensor, target: Tensor, tolerance: float) -> Tensor:
    """First step index from which each rollout stays within ``tolerance`` of the target.

    Arguments:
        states: Rollouts, shape (T + 1, B, n).
        target: The target, shape (n,).
        tolerance: Distance counted as arrived.

    Returns:
        Indices, shape (B,); -1 for rollouts that do not end within the tolerance.
    """
    inside = (states - target).norm(dim=-1) <= tolerance  # (T + 1, B)
    # The last index at which a rollout was outside, plus one; 0 if it never was.
    outside = ~inside
    steps = torch.arange(states.shape[0], device=states.device).unsqueeze(-1)
    last_out = torch.where(outside, steps, torch.full_like(steps, -1)).max(dim=0).values
    first_in = last_out + 1
    return torch.where(inside[-1], first_in, torch.full_like(first_in, -1))


def rollout_numpy(
    policy: Policy,
    x0: np.ndarray,
    *,
    dt: float,
    steps: int,
    stepper: Stepper = Euler(),
    scene=None,
    dtype: torch.dtype = torch.float64,
) -> np.ndarray:
    """NumPy convenience: :func:`rollout` of a policy in user units, along its space.

    Arguments:
        policy: The policy (evaluated in ``dtype`` if it is in that precision already; a
            float64 copy is the caller's choice).
        x0: Start states, shape (B, space.dim).
        dt: Time step in seconds.
        steps: Number of steps.
        stepper: The one-step method.
        scene: Obstacles, or None.
        dtype: Precision of the integration.

    Returns:
        The rollouts, shape (B, steps + 1, space.dim).
    """
    x = torch.tensor(np.asarray(x0, dtype=np.float64), dtype=dtype)
    states = rollout(policy, x, dt=dt, steps=steps, stepper=stepper, scene=scene).states
    return states.transpose(0, 1).cpu().numpy()
