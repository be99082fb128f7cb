r"""Branch and bound over dyadic cells of a box: prove, split, or refute.

The box :math:`[-B, B]^n` (model coordinates, target at 0) is cut into dyadic cells: a cell
of level L and integer index i is :math:`[-B + i s, -B + (i + 1) s]` with
:math:`s = 2B / 2^L`. Each cell is proven by :func:`snds.certify.bounds.cell_bounds`, or
excluded (inside the ball of radius r around the target, where a = 0 at the target makes a
proof impossible), or split into its :math:`2^n` children, down to ``max_level``; a cell
that fails there stays open. A failing cell's centre is also stepped with the exported
controller's own arithmetic, and a step that raises V there (V bounded rigorously at both
states) refutes the cell with that concrete state.
"""

from __future__ import annotations

import time
from collections import deque
from dataclasses import dataclass, field

import numpy as np
import torch

from snds.certify import interval as ia
from snds.certify.bounds import cell_bounds
from snds.certify.model import PolicyModel, v_jet
from snds.export import signature
from snds.policy import Policy

__all__ = ["Counterexample", "Search", "corners", "deployed_step", "prove"]


@dataclass(frozen=True)
class Counterexample:
    """A state where one deployed step raises V: V(next) >= V_next_lo > V_hi >= V(state).

    Attributes:
        state: The state, user units (n,).
        next: The state after one step as the controller computes it, user units (n,).
        v_hi: Upper bound of V at ``state``.
        v_next_lo: Lower bound of V at ``next``.
    """

    state: list[float]
    next: list[float]
    v_hi: float
    v_next_lo: float


@dataclass
class Search:
    """What a branch and bound found: cells as (level, index...) rows, and bounds.

    Attributes:
        proven: Proven cells (K, 1 + n), with their bounds ``bounds`` (K, 6): a_lo, P, G, Q,
            the decrease's lower bound and the cell's largest proven step (model time).
        excluded: Cells inside the excluded ball.
        open: Cells neither proven nor refuted.
        open_bounds: The bounds of the open cells (0 for cells never bounded).
        refuted: Cells whose centre is a counterexample.
        counterexamples: One per refuted cell.
        evaluated: Cells bounded.
        unbounded: Open cells never bounded (the budget ran out, or a counterexample stopped
            the search first).
        cpu_seconds, wall_seconds: Time taken.
    """

    proven: np.ndarray
    bounds: np.ndarray
    excluded: np.ndarray
    open: np.ndarray
    open_bounds: np.ndarray
    refuted: np.ndarray
    counterexamples: list[Counterexample] = field(default_factory=list)
    evaluated: int = 0
    unbounded: int = 0
    cpu_seconds: float = 0.0
    wall_seconds: float = 0.0

    def largest_step(self) -> float:
        """The largest step (model time) that the bounds prove on every cell outside the
        ball (0 if a cell is refuted or was never bounded)."""
        if len(self.refuted):
            return 0.0
        steps = np.concatenate([self.bounds[:, 5], self.open_bounds[:, 5]])
        return float(steps.min()) if len(steps) else 0.0

    @property
    def complete(self) -> bool:
        """Every cell proven or excluded."""
        return len(self.open) == 0 and len(self.refuted) == 0


def corners(cells: np.ndarray, half_width: float) -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper corners (K, n) of dyadic cells (K, 1 + n), widened outward by a
    rounding's worth so that each float box holds its exact cell."""
    level = cells[:, :1].astype(np.float64)
    size = (2.0 * half_width) / 2.0**level
    lo = -half_width + cells[:, 1:] * size
    hi = -half_width + (cells[:, 1:] + 1) * size
    slack = 4 * ia.UNIT * half_width
    return lo - slack, hi + slack


def _children(cells: np.ndarray) -> np.ndarray:
    n = cells.shape[1] - 1
    offsets = np.array(np.meshgrid(*[[0, 1]] * n, indexing="ij")).reshape(n, -1).T
    kids = 2 * cells[:, None, 1:] + offsets[None]
    levels = np.broadcast_to(cells[:, None, :1] + 1, (*kids.shape[:2], 1))
    return np.concatenate([levels, kids], -1).reshape(-1, n + 1)


def deployed_step(
    policy: Policy, states: np.ndarray, *, dt: float, dtype: torch.dtype
) -> np.ndarray:
    """x + dt pi(x) at user states (K, n) as the exported controller computes it in
    ``dtype`` (the graph that ``snds export`` traces), returned as float64."""
    module = signature(policy).module(dtype)
    with torch.no_grad():
        x = torch.as_tensor(states, dtype=dtype)
        out = x + torch.as_tensor(dt, dtype=dtype) * module(x)
    return out.numpy().astype(np.float64)


def _v_bounds(model: PolicyModel, user: np.ndarray, center: np.ndarray) -> ia.Iv:
    """V at user states (K, n), rigorously: the model coordinates (x - x*) / L are rounded
    twice, which the widening covers."""
    z = (user - center) / model.length
    lo = z - np.abs(z) * (4 * ia.UNIT) - ia.TINY
    hi = z + np.abs(z) * (4 * ia.UNIT) + ia.TINY
    return v_jet(model, lo, hi, order=1).value[:, 0]


def _refute(
    model: PolicyModel, policy: Policy, lo: np.ndarray, hi: np.ndarray, *, dt: float, dtype
) -> list[Counterexample | None]:
    center_user = np.asarray(policy.target, dtype=np.float64)
    states = (0.5 * (lo + hi)) * model.length + center_user
    states = states.astype(np.dtype(str(dtype).removeprefix("torch."))).astype(np.float64)
    nxt = deployed_step(policy, states, dt=dt, dtype=dtype)
    before = _v_bounds(model, states, center_user)
    after = _v_bounds(model, nxt, center_user)
    found: list[Counterexample | None] = [None] * len(states)
    # A controller steps one state at a time, and a batched product may round differently in
    # the last bit: each candidate is stepped again alone, and only what that shows counts.
    for k in np.flatnonzero(after.lo > before.hi)[:_ALONE]:
        alone = deployed_step(policy, states[k : k + 1], dt=dt, dtype=dtype)
        v_next = _v_bounds(model, alone, center_user)
        if v_next.lo[0] > before.hi[k]:
            found[k] = Counterexample(
                states[k].tolist(), alone[0].tolist(), float(before.hi[k]), float(v_next.lo[0])
            )
    return found


#: Candidate counterexamples per batch stepped again one at a time.
_ALONE = 64


def prove(
    model: PolicyModel,
    policy: Policy,
    *,
    half_width: float,
    dt: float,
    radius: float,
    eta: float,
    dtype: torch.dtype = torch.float64,
    start_level: int = 3,
    max_level: int = 16,
    budget: int = 200_000,
    chunk: int = 4096,
    start: np.ndarray | None = None,
    stop_at_refutation: bool = True,
) -> Search:
    """Branch and bound over the box [-B, B]^n at one step.

    Arguments:
        model: The policy's weights (:class:`PolicyModel`).
        policy: The policy itself, whose export refutes cells.
        half_width: B, model coordinates.
        dt: The controller's period, seconds.
        radius: The excluded ball's radius, model coordinates.
        eta: Relative error allowed to a deployed step.
        dtype: The controller's precision (for counterexamples).
        start_level: Level of the first, regular grid of cells.
        max_level: Deepest level; a cell failing there stays open.
        budget: Most cells bounded; what is still pending then stays open.
        chunk: Cells bounded per pass.
        start: Cells to start from instead of the regular grid (a partition of the box).
        stop_at_refutation: Stop at the first counterexample (the step is refuted; the
            cells not yet proven stay open).

    Returns:
        The :class:`Search`.
    """
    cpu, wall = time.process_time(), time.perf_counter()
    n = model.dim
    step = dt / model.time
    if start is None:
        side = 2**start_level
        grid = np.array(np.meshgrid(*[np.arange(side)] * n, indexing="ij")).reshape(n, -1).T
        start = np.concatenate([np.full((len(grid), 1), start_level), grid], 1)
    # Breadth first, so that a budget that runs out leaves the open cells spread evenly.
    pending = deque([np.asarray(start, dtype=np.int64)])
    proven, bounds, excluded, still_open, refuted, examples = [], [], [], [], [], []
    open_bounds = []
    evaluated = unbounded = 0
    while pending:
        cells = pending.popleft()
        if evaluated >= budget or (stop_at_refutation and examples):
            still_open.append(cells)
            open_bounds.append(np.zeros((len(cells), 6)))
            unbounded += len(cells)
            continue
        if len(cells) > chunk:
            pending.appendleft(cells[chunk:])
            pending.appendleft(cells[:chunk])
            continue
        lo, hi = corners(cells, half_width)
        far = np.sqrt((np.maximum(np.abs(lo), np.abs(hi)) ** 2).sum(-1)) * (1 + 1e-12)
        inside = far <= radius
        excluded.append(cells[inside])
        cells, lo, hi = cells[~inside], lo[~inside], hi[~inside]
        if not len(cells):
            continue
        evaluated += len(cells)
        result = cell_bounds(model, lo, hi, step=step, eta=eta)
        ok = result.proven
        table = np.stack(
            [
                result.a_lo,
                result.speed,
                result.grad_hi,
                result.quadratic,
                result.decrease,
                result.largest_step,
            ],
            1,
        )
        proven.append(cells[ok])
        bounds.append(table[ok])
        failing, f_lo, f_hi, f_table = cells[~ok], lo[~ok], hi[~ok], table[~ok]
        if not len(failing):
            continue
        found = _refute(model, policy, f_lo, f_hi, dt=dt, dtype=dtype)
        bad = np.array([c is not None for c in found])
        refuted.append(failing[bad])
        examples += [c for c in found if c is not None]
        rest, rest_table = failing[~bad], f_table[~bad]
        deepest = rest[:, 0] >= max_level
        still_open.append(rest[deepest])
        open_bounds.append(rest_table[deepest])
        if (~deepest).any():
            pending.append(_children(rest[~deepest]))

    def stack(parts: list[np.ndarray], width: int) -> np.ndarray:
        parts = [p for p in parts if len(p)]
        return np.concatenate(parts) if parts else np.zeros((0, width), dtype=np.int64)

    return Search(
        proven=stack(proven, n + 1),
        bounds=stack(bounds, 6).astype(np.float64),
        excluded=stack(excluded, n + 1),
        open=stack(still_open, n + 1),
        open_bounds=stack(open_bounds, 6).astype(np.float64),
        refuted=stack(refuted, n + 1),
        counterexamples=examples,
        evaluated=evaluated,
        unbounded=unbounded,
        cpu_seconds=time.process_time() - cpu,
        wall_seconds=time.perf_counter() - wall,
    )
