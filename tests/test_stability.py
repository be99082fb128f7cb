import dataclasses

import numpy as np
import pytest
import torch

from snds.data import Demonstration, Demonstrations
from snds.spaces import Euclidean
from snds.stability import CheckConfig, check_stability, decrease_violations, settle_level

from conftest import SMALL, make_policy


def test_untrained_stable_policy_reaches_the_target_from_everywhere(spiral):
    # The guarantee needs no training: random weights still converge (a = rho V > 0).
    policy = make_policy(spiral, dataclasses.replace(SMALL, decay_rate=1.0), seed=3)
    report = check_stability(policy, spiral, CheckConfig(rollouts=200, samples=20_000, seed=0))
    assert report.converged_fraction == 1.0
    assert report.decrease_violations == 0
    assert report.samples_checked == 20_000
    assert report.max_final_distance <= report.tolerance


def test_decrease_violations_are_detected_for_an_unprojected_field(spiral):
    x = torch.as_tensor(np.random.default_rng(0).normal(size=(5000, 2)) * 10)
    # A warped V, given explicitly: behavioural cloning would otherwise drop the unused warp.
    config = dataclasses.replace(SMALL, warp_layers=3)
    stable = make_policy(spiral, config, seed=0)
    # The same networks without the projection: the nominal field ignores V.
    unprojected = make_policy(spiral, dataclasses.replace(config, stable=False), seed=0)
    unprojected.load_state_dict(stable.state_dict())
    assert decrease_violations(stable, x) == 0
    assert decrease_violations(unprojected, x) > 0


def test_a_field_that_stops_short_is_reported_as_not_converged():
    t = np.linspace(0, 1, 50)
    x = np.stack([1 - t, 0 * t], axis=1)
    demos = Demonstrations(
        (Demonstration(positions=x, velocities=np.tile([-1.0, 0], (50, 1)), times=t),),
        np.zeros(2),
    )

    class Stuck(torch.nn.Module):
        stable = False
        space = Euclidean(2)

        def forward(self, x):
            return torch.zeros_like(x)

    report = check_stability(Stuck(), demos, CheckConfig(rollouts=50, samples=0, seed=0))
    assert report.converged_fraction < 0.05
    assert report.decrease_violations == 0 and report.samples_checked == 0


def test_largest_safe_step_is_exact_for_a_quadratic():
    # V = d |x|^2 and pi = -k x: a step h decreases V iff |1 - k h| < 1, i.e. h < 2 / k.
    from snds.stability import largest_safe_step

    from conftest import linear_policy

    policy = linear_policy(0.5)
    x = torch.randn(1000, 2, dtype=torch.float64)
    torch.testing.assert_close(policy(x), -0.5 * x)
    h = largest_safe_step(policy, x, upper=100.0)
    assert abs(h - 4.0) < 1e-6


@pytest.mark.parametrize("warp_layers", [0, 3])
def test_largest_safe_step_is_safe_at_every_state_and_tight(spiral, warp_layers):
    # GIVEN a policy whose V is convex (0 layers) or warped away from the identity (3), and
    # 2,000 states up to 10 extents out
    from snds.stability import largest_safe_step

    config = dataclasses.replace(SMALL, warp_layers=warp_layers)
    policy = make_policy(spiral, config, seed=4)
    with torch.no_grad():
        for p in policy.lyapunov.parameters() if warp_layers else ():
            p.add_(0.3 * torch.randn_like(p))
    x = policy.center + policy.length * 10 * (torch.rand(2000, 2, dtype=torch.float64) - 0.5)
    # WHEN the largest step safe at all of them is searched
    h = largest_safe_step(policy, x, upper=10.0)
    # THEN every state's V does not rise at that step (up to V's rounding allowance), and a
    # step 1e-5 longer raises V at some state: the bound is the smallest state's, found to
    # the bisection's precision
    with torch.no_grad():
        xm = policy.to_model(x)
        value, velocity = policy.lyapunov(xm), policy.field(xm)

        def rises(step: float) -> torch.Tensor:
            moved = policy.lyapunov(xm + step / policy.time * velocity)
            return moved > value + 1e-7 * value + 1e-12

    assert 0 < h < 10.0
    assert not rises(h).any()
    assert rises(h * (1 + 1e-5)).any()


def test_report_includes_a_safe_step_above_the_rollout_step(spiral):
    policy = make_policy(spiral, dataclasses.replace(SMALL, decay_rate=1.0), seed=3)
    report = check_stability(policy, spiral, CheckConfig(rollouts=50, samples=5000, seed=0))
    assert report.largest_safe_dt > 0
    assert report.converged_fraction == 1.0


def test_spurious_attractors_are_found_and_clustered():
    # A field with a second equilibrium at (0.5, 0.5): starts with x1 > 0.25 go there.
    t = np.linspace(0, 1, 50)
    x = np.stack([1 - t, 0 * t], axis=1)
    demos = Demonstrations(
        (Demonstration(positions=x, velocities=np.tile([-1.0, 0], (50, 1)), times=t),),
        np.zeros(2),
    )
    trap = torch.tensor([0.5, 0.5], dtype=torch.float64)

    class TwoWells(torch.nn.Module):
        stable = False
        space = Euclidean(2)

        def forward(self, x):
            return torch.where(x[:, :1] > 0.25, trap - x, -x)

    report = check_stability(TwoWells(), demos, CheckConfig(rollouts=200, samples=0, seed=0))
    assert 0.2 < report.converged_fraction < 0.8
    assert len(report.spurious_attractors) == 1
    center = np.array(report.spurious_attractors[0]["center"])
    assert np.linalg.norm(center - trap.numpy()) < 0.01
    assert report.spurious_attractors[0]["count"] == round(200 * (1 - report.converged_fraction))
    assert report.still_moving == 0


def test_grid_starts_cover_the_box_corners(spiral):
    policy = make_policy(spiral, dataclasses.replace(SMALL, decay_rate=1.0), seed=3)
    report = check_stability(policy, spiral, CheckConfig(rollouts=50, grid=True, samples=0, seed=0))
    assert report.rollouts == 64  # 8 x 8 >= 50
    assert report.converged_fraction == 1.0
    points = Euclidean(2).grid(np.array([1.0, -2.0]), 3.0, 9, np.random.default_rng(0))
    assert points.shape == (9, 2)
    assert {tuple(p) for p in points} >= {(-2.0, -5.0), (4.0, 1.0), (1.0, -2.0)}


def _line_demo(dt: float) -> Demonstrations:
    t = np.arange(0.0, 4.0, dt)
    x = np.stack([1 - t / t[-1], 0 * t], axis=1)
    v = np.tile([-1.0 / t[-1], 0.0], (len(t), 1))
    return Demonstrations((Demonstration(positions=x, velocities=v, times=t),), np.zeros(2))


def test_report_shows_where_plain_euler_would_cycle():
    # pi = -5 x: Euler steps longer than 2/5 s do not decrease V; the data's step is 0.4 s.
    from conftest import linear_policy

    report = check_stability(
        linear_policy(5.0), _line_demo(0.4), CheckConfig(rollouts=40, samples=2000)
    )
    assert report.integrator == "guarded euler"
    assert report.converged_fraction == 1.0
    assert report.shortened_fraction == 1.0
    assert abs(report.largest_safe_dt_on_rollouts - 0.4) < 1e-6
    assert abs(report.largest_safe_dt - 0.4) < 1e-6


def test_report_shows_no_shortened_steps_where_euler_is_safe():
    from conftest import linear_policy

    report = check_stability(
        linear_policy(5.0), _line_demo(0.05), CheckConfig(rollouts=40, samples=2000)
    )
    assert report.converged_fraction == 1.0
    assert report.shortened_fraction == 0.0
    assert report.largest_safe_dt > 0.05


class _Anisotropic(torch.nn.Module):
    """V = x1^2 + 9 x2^2 (+ x3^2): no floor declared, so the level must come from the sphere."""

    quadratic = 0.0

    def forward(self, x):
        weights = torch.ones(x.shape[-1], dtype=x.dtype)
        weights[1] = 9.0
        return (weights * x * x).sum(-1)


def test_settle_level_keeps_its_sublevel_set_inside_the_ball():
    radius = 0.3
    for dim in (2, 3):
        level = settle_level(_Anisotropic(), radius, dim=dim)
        # The smallest V on the sphere is radius^2 (along x1), and the level is half of it.
        assert np.isclose(level, 0.5 * radius**2, rtol=1e-3)
        x = torch.as_tensor(np.random.default_rng(dim).normal(size=(100_000, dim)))
        inside = _Anisotropic()(x) < level
        assert inside.sum() > 0 and bool((x[inside].norm(dim=-1) < radius).all())
    # With a quadratic floor d the exact level d r^2 is used.
    floor = _Anisotropic()
    floor.quadratic = 1.0
    assert settle_level(floor, radius, dim=2) == radius**2


def test_adaptive_rollouts_arrive_when_the_exact_flow_does():
    # pi = -x from uniform starts: |x(t)| = |x0| e^-t enters the tolerance ball at
    # t* = log(|x0| / tol). The check's steps grow far beyond the data's 0.05 s here.
    from conftest import linear_policy

    demos = _line_demo(0.05)
    report = check_stability(linear_policy(1.0), demos, CheckConfig(rollouts=41, samples=0, seed=0))
    starts = np.random.default_rng(0).uniform(-3.0, 3.0, size=(41, 2))
    exact = np.median(np.log(np.linalg.norm(starts, axis=1) / report.tolerance))
    assert report.converged_fraction == 1.0
    assert abs(report.median_time_to_converge - exact) < 0.03 * exact


def test_a_diverging_field_without_v_ends_at_the_horizon():
    # GIVEN a field that blows up to inf and NaN: the adaptive steps must still end
    class Away(torch.nn.Module):
        stable = False
        space = Euclidean(2)

        def forward(self, x):
            return 50.0 * x * x.norm(dim=-1, keepdim=True)

    report = check_stability(Away(), _line_demo(0.05), CheckConfig(rollouts=20, samples=0, seed=0))
    assert report.converged_fraction == 0.0


def test_a_field_the_guard_shortens_at_every_step_ends_within_the_step_budget():
    # pi = -1e6 x with the data's 0.4 s: every step is halved ~20 times, so the integrated
    # time barely moves; the check still ends after horizon / dt steps, and the guarded
    # steps still contract to the target.
    from conftest import linear_policy

    report = check_stability(
        linear_policy(1e6), _line_demo(0.4), CheckConfig(rollouts=5, samples=0)
    )
    assert report.converged_fraction == 1.0
    assert report.shortened_fraction == 1.0


def test_coarse_data_do_not_cut_rollouts_short_of_the_cap():
    # GIVEN data sampled every 2 s (as coarse as the README's strokes of 3 points) and pi = -x:
    # the check's step budget used to be horizon / dt = 10 steps of at most 0.4 s, which ended
    # every rollout at 4 s of its 20 s cap, "still moving"
    from conftest import linear_policy

    demos = _line_demo(2.0)
    report = check_stability(linear_policy(1.0), demos, CheckConfig(rollouts=41, samples=0, seed=0))
    # THEN every start arrives, when the exact flow does: t* = log(|x0| / tol)
    starts = np.random.default_rng(0).uniform(-3.0, 3.0, size=(41, 2))
    exact = np.log(np.linalg.norm(starts, axis=1) / report.tolerance)
    assert report.converged_fraction == 1.0 and report.out_of_steps == 0
    assert report.horizon == 20.0 and report.duration == 2.0
    assert abs(report.time_to_arrive_max - exact.max()) < 0.05 * exact.max()
    assert abs(report.time_to_arrive_median - np.median(exact)) < 0.05 * np.median(exact)
    # and the times are also given in longest-demonstration durations
    assert report.time_to_arrive_max_durations == report.time_to_arrive_max / 2.0
    assert report.time_to_arrive_median_durations == report.time_to_arrive_median / 2.0
