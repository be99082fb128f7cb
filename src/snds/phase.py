r"""A phase in the state: which demonstration a rollout follows, and how far along it is.

A field of position alone, :math:`\dot x = \pi(x)`, has one velocity per place, so it cannot
follow two demonstrations that cross, or one that passes the same place twice. :class:`Phase`
appends to demonstration :math:`d`'s positions the phase

.. math:: \psi_d(t) = E \left(1 - \frac{t - t_0}{T_d}\right) c_d \in \mathbb{R}^m,

with :math:`E` the positions' extent, :math:`T_d` the demonstration's duration and
:math:`c_d` a unit code of :math:`m` numbers drawn for it. In the state :math:`(x, \psi)` the
demonstrations are apart wherever their phases are not 0, and every one ends at
:math:`(x^*, 0)`. SNDS is trained on these states unchanged, so its guarantee holds for the
joint state: every rollout reaches :math:`(x^*, 0)` (the model's space is
:class:`~snds.spaces.Phased`, whose metrics and plots read the positions).

What a user gives up: a start needs a phase. :func:`start_state` takes the phase of the
nearest demonstrated sample for a start beside the demonstrations, and phase 0 for one away
from them. And a robot that is held should not let its phase run
on (the phase stopping of dynamic movement primitives): :func:`phase_step` advances the phase
by the share of the commanded displacement that the measured positions made, so that on an
unhindered robot it is the policy's own step and on a held one the phase waits.

    demos = Phase(codes=3).apply(snds.load_lasa("Sine"))   # states (x1, x2, psi1..psi3)
    start = start_state(demos, np.array([-40.0, 10.0]))      # (5,)
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from snds.data.demonstrations import DemonstrationSet
from snds.errors import ConfigError, DataError

__all__ = [
    "START_REACH",
    "START_REFERENCES",
    "Phase",
    "PhaseKeeper",
    "StartRule",
    "phase_step",
    "start_rule",
    "start_state",
    "start_states",
]


@dataclass(frozen=True, kw_only=True)
class Phase:
    """How the phase is appended to a task's states.

    Attributes:
        codes: Numbers m of the phase. With 1 the phase is a scalar clock shared by all
            demonstrations; with more, each demonstration gets its own random unit direction.
        seed: Seed of the codes.
        extent: E, the length the phase is scaled by; None: the demonstrations' own extent.
            A refined model (:mod:`snds.refine`) keeps the extent it was first trained with,
            so that demonstrations added beyond it leave the earlier ones' phases as learnt.
    """

    codes: int = 3
    seed: int = 0
    extent: float | None = None

    def __post_init__(self) -> None:
        # bool is an int to Python: only a true integer counts codes.
        if type(self.codes) is not int or not 1 <= self.codes <= 64:
            raise ConfigError(f"phase codes must be an integer in 1..64, got {self.codes!r}")
        if type(self.seed) is not int:
            raise ConfigError(f"the phase seed must be an integer, got {self.seed!r}")
        finite = isinstance(self.extent, int | float) and np.isfinite(self.extent)
        if self.extent is not None and not (finite and self.extent > 0):
            raise ConfigError(f"the phase extent must be a positive number, got {self.extent!r}")

    def codebook(self, count: int) -> np.ndarray:
        """The unit codes c_d of ``count`` demonstrations, shape (count, codes), in order; the
        same for the same seed (a demonstration's code does not depend on how many follow)."""
        if self.codes == 1:
            return np.ones((count, 1))
        rng = np.random.default_rng(self.seed)
        codes = rng.normal(size=(count, self.codes))
        return codes / np.linalg.norm(codes, axis=1, keepdims=True)

    def apply(self, demos: DemonstrationSet) -> DemonstrationSet:
        """The demonstrations with their phases appended: states (T, n + codes) (poses:
        (T, 7 + codes)), velocities their time derivatives, the target (x*, 0),
        ``phase_dim`` = codes.

        Raises:
            DataError: If the demonstrations carry a phase already.
        """
        if demos.phase_dim:
            raise DataError(f"{demos.name or 'the demonstrations'} carry a phase already")
        extent = demos.extent() if self.extent is None else self.extent
        phases = [
            extent * (1.0 - (demo.times - demo.times[0]) / demo.duration)[:, None] * code
            for demo, code in zip(demos, self.codebook(len(demos)), strict=True)
        ]
        return demos.with_phase(phases)

    def record(self) -> dict:
        """The JSON-ready description saved with a model (``model.json``'s ``data.phase``)."""
        extent = {} if self.extent is None else {"extent": self.extent}
        return {"codes": self.codes, "seed": self.seed} | extent

    @classmethod
    def from_record(cls, record: dict) -> Phase:
        """The phase a :meth:`record` describes."""
        if not isinstance(record, dict) or "codes" not in record:
            raise DataError(f"a phase record needs its codes, got {record!r}")
        return cls(codes=record["codes"], seed=record.get("seed", 0), extent=record.get("extent"))


#: How near (in extents) a new start must be to a demonstrated position to take its phase:
#: :func:`start_state`.
START_REACH = 0.05

#: At most this many samples of each demonstration (evenly spaced) lend a new start their
#: phase: the same references for the library and for an exported controller, which stores
#: them.
START_REFERENCES = 200


@dataclass(frozen=True)
class StartRule:
    """How a new start gets its phase: the phase of the nearest reference state (by position)
    if it lies within ``reach``, else 0 (:func:`start_rule`).

    Attributes:
        references: Demonstrated states, shape (K, b + m): a base state (position, or pose)
            then its phase.
        reach: The largest distance (user units of the positions) at which a reference lends
            its phase.
        phase_dim: m.
        position_dim: How many leading numbers of a state are its position.
    """

    references: np.ndarray
    reach: float
    phase_dim: int
    position_dim: int

    def start_states(self, bases: np.ndarray) -> np.ndarray:
        """The start states of base states (B, b), shape (B, b + m)."""
        b = self.references.shape[1] - self.phase_dim
        bases = np.asarray(bases, dtype=np.float64).reshape(-1, b)
        p = self.position_dim
        distance, nearest = cKDTree(self.references[:, :p]).query(bases[:, :p])
        phases = np.where((distance <= self.reach)[:, None], self.references[nearest, b:], 0.0)
        return np.concatenate([bases, phases], axis=1)


def start_rule(demos: DemonstrationSet, *, reach: float = START_REACH) -> StartRule:
    """The rule of :func:`start_state` for ``demos``: up to :data:`START_REFERENCES` samples
    of each demonstration, and ``reach`` extents."""
    references = []
    for demo in demos:
        stride = max(1, -(-len(demo.times) // START_REFERENCES))
        references.append(demo.states[::stride])
    return StartRule(
        np.concatenate(references), reach * demos.extent(), demos.phase_dim, demos.position_dim
    )


def start_state(
    demos: DemonstrationSet, position: np.ndarray, *, reach: float = START_REACH
) -> np.ndarray:
    """A phased start at a base state (a position, or a pose): the phase of the nearest
    demonstrated sample (of :data:`START_REFERENCES` per demonstration) if one lies within
    ``reach`` extents of its position, so that a start on or beside a demonstration retraces
    it from there; else phase 0, so that a start away from the data heads for the target
    instead of for a demonstration (docs/design.md, "A new start's phase").

    Arguments:
        demos: The phased demonstrations of the task.
        position: The start's base state, shape (b,): a position (n,), or a pose (7,).
        reach: The distance in extents within which a demonstrated sample lends its phase.

    Returns:
        The start state, shape (b + m,).
    """
    b = len(demos.target) - demos.phase_dim
    position = np.asarray(position, dtype=np.float64)
    if position.shape != (b,):
        raise DataError(
            f"a start has shape ({b},) (the state without its phase), got {position.shape}"
        )
    return start_states(demos, position[None], reach=reach)[0]


def start_states(
    demos: DemonstrationSet, positions: np.ndarray, *, reach: float = START_REACH
) -> np.ndarray:
    """:func:`start_state` of many base states at once, shape (B, b) -> (B, b + m)."""
    return start_rule(demos, reach=reach).start_states(positions)


def phase_step(
    state: np.ndarray,
    velocity: np.ndarray,
    h: float,
    measured: np.ndarray,
    *,
    position_dim: int,
) -> np.ndarray:
    r"""The state after a commanded step, from the state measured after it.

    The base state (positions, or a pose) is the measured one; the phase advances by the
    policy's phase velocity times :math:`h\,s`, with :math:`s = \mathrm{clip}(\langle \Delta x,
    h v_x \rangle / \|h v_x\|^2, 0, 1)` the share of the commanded displacement of the
    positions :math:`h v_x` that the measured one :math:`\Delta x` made. Unhindered
    (:math:`\Delta x = h v_x`) this is the policy's own Euler step, so the guarantee applies;
    held (:math:`\Delta x = 0`) the phase waits; where no displacement was commanded it runs
    on.

    Arguments:
        state: The states the step was commanded at, shape (*, b + m): a base state of b
            numbers whose first n are positions, then the phase.
        velocity: The velocities commanded there, shape (*, k + m), the positions' first.
        h: The step, seconds.
        measured: The base states measured after it, shape (*, b).
        position_dim: n.

    Returns:
        The next states, shape (*, b + m).
    """
    p = position_dim
    state = np.asarray(state, dtype=np.float64)
    measured = np.asarray(measured, dtype=np.float64)
    b = measured.shape[-1]
    m = state.shape[-1] - b
    commanded = h * np.asarray(velocity, dtype=np.float64)
    made = measured[..., :p] - state[..., :p]
    size = np.einsum("...i,...i->...", commanded[..., :p], commanded[..., :p])
    ratio = np.einsum("...i,...i->...", made, commanded[..., :p]) / np.where(size > 0, size, 1.0)
    share = np.where(size > 0, np.clip(ratio, 0.0, 1.0), 1.0)
    phase = state[..., b:] + share[..., None] * commanded[..., commanded.shape[-1] - m :]
    return np.concatenate([measured, phase], -1)


class PhaseKeeper:
    """The phase a controller keeps for a model with a phase, from the measured base states
    (positions, or poses) a robot reports each period.

    The first state is the one :meth:`start` gave, with the measured base state; without one,
    the start rule's (:class:`StartRule`). Each later one is :func:`phase_step`'s: the measured
    base state, the phase advanced by the share of the last command the positions made, so that
    it waits while the robot is held.

    Arguments:
        position_dim: How many leading numbers of a state are its position.
        start_rule: How a first state without :meth:`start` gets its phase (None: it needs one).
    """

    def __init__(self, *, position_dim: int, start_rule: StartRule | None = None) -> None:
        self.position_dim = position_dim
        self.start_rule = start_rule
        self.state: np.ndarray | None = None
        self.commanded: np.ndarray | None = None

    def start(self, state: np.ndarray) -> None:
        """Starts from a whole state (base state, then phase)."""
        self.state, self.commanded = np.array(state, dtype=np.float64), None

    def step(self, measured: np.ndarray, dt: float) -> np.ndarray:
        """The whole state at a measured base state, ``dt`` seconds after the last command
        (:meth:`command` records it), shape (b + m,).

        Raises:
            ConfigError: For a first state with neither :meth:`start` nor a start rule.
        """
        measured = np.asarray(measured, dtype=np.float64)
        if self.state is None:
            if self.start_rule is None:
                raise ConfigError("a model with a phase needs a start state or a start rule")
            state = self.start_rule.start_states(measured[None])[0]
        elif self.commanded is None:
            state = np.concatenate([measured, self.state[len(measured) :]])
        else:
            state = phase_step(
                self.state, self.commanded, dt, measured, position_dim=self.position_dim
            )
        self.state = state
        return state

    def command(self, velocity: np.ndarray) -> None:
        """Records the velocity commanded at the last :meth:`step`'s state."""
        self.commanded = np.asarray(velocity, dtype=np.float64)
