import math

import torch

from snds.rollout import converged_at, guarded_step, policy_guard, rollout
from snds.steppers import RK4, Dynamics, Euler, GuardedEuler

from conftest import linear_policy, make_policy


def linear(x):
    return -x


def test_euler_and_rk4_orders_on_closed_form():
    # x' = -x has x(t) = x0 exp(-t): Euler's error is O(dt), RK4's O(dt^4).
    x0 = torch.ones(1, 1, dtype=torch.float64)
    errors = {}
    for method, stepper in (("euler", Euler()), ("rk4", RK4())):
        errs = []
        for steps in (20, 40):
            path = rollout(linear, x0, dt=1.0 / steps, steps=steps, stepper=stepper).states
            errs.append(abs(path[-1].item() - math.exp(-1.0)))
        errors[method] = math.log2(errs[0] / errs[1])
    assert 0.9 < errors["euler"] < 1.1
    assert 3.8 < errors["rk4"] < 4.2


def test_guarded_rollout_decreases_v_at_every_step(spiral):
    policy = make_policy(spiral, seed=0)
    with torch.no_grad():
        for p in policy.nominal_net.parameters():
            p.mul_(20.0)  # a fast, wild field: plain Euler overshoots with a big step
    x0 = 3 * spiral.extent() * torch.randn(64, 2, dtype=torch.float64)

    def lyapunov(x):
        return policy.lyapunov(policy.to_model(x))

    dynamics = Dynamics(field=policy, lyapunov=lyapunov)
    result = rollout(dynamics, x0, dt=0.5, steps=40, stepper=GuardedEuler())
    values = torch.stack([lyapunov(s) for s in result.states])
    assert (values[1:] <= values[:-1]).all()
    assert (result.taken <= 0.5).all()


def test_converged_at_finds_the_first_index_that_stays_inside():
    d = torch.tensor([3.0, 0.5, 2.0, 0.4, 0.1]).reshape(5, 1, 1)
    states = torch.cat([d, torch.tensor([5.0, 4, 3, 2, 1.5]).reshape(5, 1, 1)], dim=1)
    idx = converged_at(states, torch.zeros(1), tolerance=1.0)
    assert idx.tolist() == [3, -1]


def test_plain_euler_cycles_where_the_guarded_step_converges():
    # pi = -5 x: plain Euler at h = 0.4 maps x to -x, a 2-cycle at constant V.
    policy = linear_policy(5.0)
    lyapunov, rate = policy_guard(policy)
    x0 = torch.tensor([[1.0, 2.0], [-3.0, 0.5]], dtype=torch.float64)
    plain = rollout(policy, x0, dt=0.4, steps=50, guard=False).states
    torch.testing.assert_close(plain[-1], x0)  # 50 sign flips: back at the start
    guarded = rollout(policy, x0, dt=0.4, steps=50, stepper=GuardedEuler())
    values = torch.stack([lyapunov(s) for s in guarded.states])
    # Armijo: each accepted step h keeps at least half the promised decrease a(x) h.
    promised = 0.5 * guarded.taken * rate(guarded.states[:-1], values[:-1])
    assert (values[1:] <= values[:-1] - promised + 1e-15).all()
    # Every first step is shortened: the nominal 0.4 s leaves V where it was.
    assert (guarded.taken[0] <= 0.2).all()
    assert guarded.states[-1].abs().max() < 1e-12


def test_guarded_step_keeps_a_safe_step_unchanged():
    policy = linear_policy(5.0)
    lyapunov, rate = policy_guard(policy)
    x = torch.randn(100, 2, dtype=torch.float64)
    stepped, h, value = guarded_step(policy, lyapunov, x, dt=0.05, rate=rate)
    assert (h == 0.05).all()
    torch.testing.assert_close(stepped, x + 0.05 * policy(x))
    torch.testing.assert_close(value, lyapunov(stepped))


def test_guarded_step_tests_the_state_its_own_advance_reaches():
    # GIVEN a step map that overshoots outward for long steps (as a curved manifold's map may)
    policy = linear_policy(1.0)
    lyapunov, rate = policy_guard(policy)

    def advance(x, h, velocity):
        return x + h.unsqueeze(-1) * velocity + (4.0 * h * h).unsqueeze(-1) * x

    x = torch.randn(200, 2, dtype=torch.float64)
    value = lyapunov(x)
    # The plain Euler step of 0.5 would be safe: V(x - 0.5 x) = V / 4.
    assert (lyapunov(x + 0.5 * policy(x)) < value).all()
    # WHEN the guarded step uses that map
    stepped, h, new = guarded_step(policy, lyapunov, x, dt=0.5, rate=rate, advance=advance)
    # THEN it is shortened until the decrease holds where the map really goes
    assert (h < 0.5).all()
    torch.testing.assert_close(stepped, advance(x, h, policy(x)))
    torch.testing.assert_close(new, lyapunov(stepped))
    assert (new <= value - 0.5 * h * rate(x, value)).all()


def test_a_guarded_step_from_given_first_candidates_is_the_same_step(spiral):
    # GIVEN a stiff warped policy whose guard shortens some steps, and the full steps' V
    # evaluated by the caller together with the velocity there (as the stability check does)
    policy = make_policy(spiral, seed=0).double()
    with torch.no_grad():
        for p in policy.nominal_net.parameters():
            p.mul_(20.0)
    lyapunov, rate = policy_guard(policy)
    generator = torch.Generator().manual_seed(0)
    x = 3 * spiral.extent() * torch.randn(256, 2, dtype=torch.float64, generator=generator)
    # Half the states with a step short enough to keep, half with one the guard shortens.
    dt = torch.where(torch.arange(256) % 2 == 0, 1e-6, 0.5).double()
    candidate = x + dt.unsqueeze(-1) * policy(x)
    velocity, value = policy.velocity_and_value(candidate)
    torch.testing.assert_close(velocity, policy(candidate), rtol=0, atol=0)
    torch.testing.assert_close(value, lyapunov(candidate), rtol=0, atol=0)
    # WHEN the step starts from them
    given = guarded_step(policy, lyapunov, x, dt=dt, rate=rate, first=(candidate, value))
    # THEN it is the step computed from scratch, shortened where that one is (V up to the
    # last bits, which a matrix product may round differently for another allocation)
    plain = guarded_step(policy, lyapunov, x, dt=dt, rate=rate)
    for a, b in zip(given, plain):
        torch.testing.assert_close(a, b, rtol=1e-13, atol=0)
    assert (given[1] < dt).any() and (given[1] == dt).any()
