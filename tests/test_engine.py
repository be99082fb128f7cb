"""The rollout engine: every stepper on every state shape, one row or a batch."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import snds
from snds.data.poses import with_synthetic_orientations
from snds.phase import Phase
from snds.rollout import Arrival, rollout
from snds.se3 import make_pose_policy
from snds.steppers import RK4, Euler, GuardedEuler

from conftest import SMALL, spiral_demos

STEPPERS = {"euler": Euler(), "rk4": RK4(), "guarded euler": GuardedEuler()}


def _policies() -> dict:
    """Untrained stable policies (stable by construction) of each state shape, float64."""
    spiral = spiral_demos(count=2, samples=200)
    poses = with_synthetic_orientations(
        spiral_demos(count=2, samples=200), target_orientation=(0.0, 0.6, 0.0, 0.8), seed=1
    )
    phased = Phase(codes=3, seed=4).apply(spiral)
    return {
        "positions": (snds.make_policy(spiral, config=SMALL, seed=0), spiral),
        "poses": (make_pose_policy(poses, config=SMALL, seed=0), poses),
        "phase": (snds.make_policy(phased, config=SMALL, seed=2), phased),
    }


@pytest.fixture(scope="module")
def policies() -> dict:
    return {k: (p.double().eval(), d) for k, (p, d) in _policies().items()}


def _starts(demos, batch: bool) -> torch.Tensor:
    starts = torch.as_tensor(np.stack([d.states[0] for d in demos]))
    return starts if batch else starts[:1]


@pytest.mark.parametrize("batch", [False, True], ids=["single", "batch"])
@pytest.mark.parametrize("shape", ["positions", "poses", "phase"])
@pytest.mark.parametrize("name", list(STEPPERS))
def test_every_stepper_on_every_state_shape(policies, name, shape, batch):
    # GIVEN an untrained stable policy of this state shape and its demonstrations' starts
    policy, demos = policies[shape]
    x0 = _starts(demos, batch)
    stepper = STEPPERS[name]
    dt, steps = demos.mean_dt(), 100
    if name == "rk4" and shape != "positions":
        # RK4 adds velocities to states: it refuses a space with its own advance.
        with pytest.raises(ValueError, match="R\\^n only"):
            rollout(policy, x0, dt=dt, steps=steps, stepper=stepper)
        return
    # WHEN rolled out with the engine
    result = rollout(policy, x0, dt=dt, steps=steps, stepper=stepper)
    lyapunov = policy.lyapunov
    values = torch.stack([lyapunov(policy.to_model(s)) for s in result.states])  # (T + 1, B)
    # THEN the shape and clock are the engine's promise, V has fallen by orders of magnitude
    assert result.states.shape == (steps + 1, *x0.shape)
    assert torch.equal(result.final, result.states[-1])
    torch.testing.assert_close(result.final_time, result.taken.sum(0), rtol=1e-12, atol=0)
    assert (values[-1] < 1e-2 * values[0]).all()
    if shape == "poses":
        assert (result.states[..., 3:7].norm(dim=-1) - 1).abs().max() < 1e-12
    if name == "guarded euler":
        # the guarded step never lets V rise, at any step of any row (V below 1e-12 is the
        # target up to rounding, where 30 halvings may not find a decrease)
        above = values[:-1] > 1e-12
        assert (values[1:][above] <= values[:-1][above]).all()
        assert ((result.taken > 0) & (result.taken <= dt)).all()
    else:
        # a plain step is the space's advance along the policy's velocity, as written by hand
        x = x0
        with torch.no_grad():
            for k in range(3):
                x = policy.space.advance(x, torch.full_like(x[:, 0], dt), policy(x))
                if name == "euler":
                    assert torch.equal(result.states[k + 1], x)
        assert (result.taken == dt).all()


@pytest.mark.parametrize("shape", ["positions", "poses", "phase"])
def test_a_row_of_a_batch_is_its_own_rollout_and_stops_after_its_own_steps(policies, shape):
    # GIVEN a batch whose rows take different numbers of steps, each with its own step
    policy, demos = policies[shape]
    x0 = _starts(demos, batch=True)
    dt = torch.tensor([demos.mean_dt(), 0.5 * demos.mean_dt()], dtype=torch.float64)
    steps = torch.tensor([40, 25])
    # WHEN rolled out together, then each row alone
    together = rollout(policy, x0, dt=dt, steps=steps)
    for row in range(2):
        alone = rollout(policy, x0[row : row + 1], dt=float(dt[row]), steps=int(steps[row]))
        k = int(steps[row])
        # THEN the row follows its own rollout (to rounding) and then stays put
        torch.testing.assert_close(
            together.states[: k + 1, row], alone.states[:, 0], rtol=1e-12, atol=1e-12
        )
        assert (together.states[k:, row] == together.states[k, row]).all()
        assert float(together.final_time[row]) == pytest.approx(k * float(dt[row]), rel=1e-12)


def test_until_ends_at_the_first_check_where_every_row_has_arrived(policies):
    # GIVEN positions, an arrival rule and checks every 50 steps
    policy, demos = policies["positions"]
    x0 = _starts(demos, batch=True)
    target = torch.as_tensor(demos.target)
    arrival = Arrival.of(policy.space, target, demos.extent(), tolerance=0.01)
    # WHEN rolled out until every row has arrived, for at most 5,000 steps
    result = rollout(policy, x0, dt=demos.mean_dt(), steps=5000, until=arrival, check_every=50)
    # THEN it stops at a multiple of 50 steps with every row inside, and not at the check before
    assert result.steps % 50 == 0 and result.steps < 5000
    assert arrival(result.final).all()
    assert not arrival(result.states[-51]).all()
    # and each row's arrival step is where it entered the ball for good
    found = arrival.steps(result.states)
    for row, k in enumerate(found):
        assert bool(arrival(result.states[k:, row]).all()) and not bool(
            arrival(result.states[k - 1, row])
        )
