import math

import torch

from snds.rollout import converged_at, guarded_rollout, rollout

from conftest import make_policy


def linear(x):
    return -x


def test_euler_and_rk4_orders_on_closed_form():
    # x' = -x has x(t) = x0 exp(-t): Euler's error is O(dt), RK4's O(dt^4).
    x0 = torch.ones(1, 1, dtype=torch.float64)
    errors = {}
    for method in ("euler", "rk4"):
        errs = []
        for steps in (20, 40):
            path = rollout(linear, x0, dt=1.0 / steps, steps=steps, method=method)
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

    result = guarded_rollout(policy, lyapunov, x0, dt=0.5, steps=40)
    values = torch.stack([lyapunov(s) for s in result.states])
    assert (values[1:] <= values[:-1]).all()
    assert (result.steps_taken <= 0.5).all()


def test_converged_at_finds_the_first_index_that_stays_inside():
    d = torch.tensor([3.0, 0.5, 2.0, 0.4, 0.1]).reshape(5, 1, 1)
    states = torch.cat([d, torch.tensor([5.0, 4, 3, 2, 1.5]).reshape(5, 1, 1)], dim=1)
    idx = converged_at(states, torch.zeros(1), tolerance=1.0)
    assert idx.tolist() == [3, -1]
