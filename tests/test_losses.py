import numpy as np
import torch

from snds.data import Demonstration, Demonstrations, Normalization, no_split, split_samples
from snds.losses import Samples, align_loss, make_samples, srvf, velocity_loss, window_loss


def _line() -> Demonstrations:
    t = np.linspace(0, 1, 11)
    x = np.stack([1 - t, np.zeros_like(t)], axis=1)
    v = np.tile([-1.0, 0.0], (11, 1))
    return Demonstrations((Demonstration(positions=x, velocities=v, times=t),), np.zeros(2))


def test_windows_only_cover_training_samples():
    demos = _line()
    split = split_samples(demos, test_fraction=0.3, seed=0)
    samples = make_samples(demos, Normalization.fit(demos), split, window=2)
    train = set(
        np.round(
            Normalization.fit(demos).positions_to_model(demos[0].positions[split.train[0]])[:, 0], 9
        )
    )
    for start, targets in zip(samples.window_starts, samples.window_targets):
        assert round(float(start[0]), 9) in train
        assert all(round(float(t[0]), 9) in train for t in targets)


def test_window_loss_is_zero_for_the_exact_field_and_mean_velocity_scaled():
    demos = _line()
    norm = Normalization.fit(demos)
    s = make_samples(demos, norm, no_split(demos), window=2)
    exact = lambda x: torch.tensor([-1.0, 0.0], dtype=x.dtype).expand_as(x)  # noqa: E731
    assert window_loss(exact, s.window_starts, s.window_targets, s.window_steps).item() < 1e-20
    # A field off by 0.1 in velocity gives (1/2 + 1/4) * 0.01 whatever the step.
    off = lambda x: torch.tensor([-0.9, 0.0], dtype=x.dtype).expand_as(x)  # noqa: E731
    value = window_loss(off, s.window_starts, s.window_targets, s.window_steps).item()
    assert abs(value - 0.75 * 0.01) < 1e-9


def test_velocity_loss_values():
    pred = torch.tensor([[1.0, 0.0], [0.0, 0.0]])
    true = torch.zeros(2, 2)
    assert velocity_loss(pred, true, "mse").item() == 0.5
    q = srvf(torch.tensor([[4.0, 0.0]]), eps=0.0)
    torch.testing.assert_close(q, torch.tensor([[2.0, 0.0]]))


def test_align_loss_values_by_hand():
    # -grad V along the velocity (cos 1), across it (cos 0) and against it (cos -1), at
    # speeds 2, 1 and 1: weights 1, 0.5, 0.5; hinge at c = 0.5: 0, 0.5, 1.5.
    grad = torch.tensor([[-3.0, 0.0], [0.0, 1.0], [1.0, 0.0]], dtype=torch.float64)
    velocity = torch.tensor([[2.0, 0.0], [1.0, 0.0], [1.0, 0.0]], dtype=torch.float64)
    expected = (1.0 * 0.0 + 0.5 * 0.5 + 0.5 * 1.5) / 3
    assert abs(float(align_loss(grad, velocity, 0.5)) - expected) < 1e-12
    # Scaling grad V changes nothing; c = -1 never binds.
    assert abs(float(align_loss(7.0 * grad, velocity, 0.5)) - expected) < 1e-12
    assert float(align_loss(grad, velocity, -1.0)) == 0.0


def test_align_loss_has_a_finite_gradient_where_grad_v_vanishes():
    # At the target grad V = 0: the term's gradient must be finite there (0 / 0 otherwise).
    grad = torch.zeros(3, 2, dtype=torch.float64, requires_grad=True)
    velocity = torch.tensor([[1.0, 0.0], [0.0, 0.0], [0.5, 0.5]], dtype=torch.float64)
    align_loss(grad, velocity, 0.5).backward()
    assert torch.isfinite(grad.grad).all()


def test_nearest_sample_matches_brute_force_and_survives_a_dtype_change():
    # GIVEN float32 samples in 3-D and queries near and far from them
    generator = torch.Generator().manual_seed(0)
    positions = torch.randn(3000, 3, generator=generator, dtype=torch.float32)
    empty = torch.zeros(0, 3)
    samples = Samples(positions, -positions, empty, torch.zeros(0, 1, 3), torch.zeros(0, 1))
    states = torch.cat([positions[:200] + 0.01 * torch.randn(200, 3), 5 * torch.randn(50, 3)])
    # WHEN searching with the tree
    found = samples.nearest(states)
    # THEN it finds the sample at the smallest distance (ties aside, which random data lack)
    squared = ((states.double()[:, None] - positions.double()[None]) ** 2).sum(-1)
    assert found.dtype == torch.int64 and found.shape == (250,)
    torch.testing.assert_close(squared[torch.arange(250), found], squared.min(dim=1).values)
    # AND the tree cached by the search is not carried into a converted copy as a field
    converted = samples.to(torch.float64)
    assert converted.positions.dtype == torch.float64
    torch.testing.assert_close(converted.nearest(states.double()), found)


def _unit(v: torch.Tensor) -> torch.Tensor:
    return v / v.norm() if v.norm() > 0 else torch.zeros_like(v)


def _brute_force_pull(
    states: torch.Tensor, samples: Samples, width: float, heading: torch.Tensor
) -> torch.Tensor:
    """sum_j w_j (x - x_j) across v_j, one state and one sample at a time (float64)."""
    rows = []
    for x, h in zip(states.double(), heading.double()):
        offsets = x - samples.positions.double()
        cosines = torch.stack([_unit(h) @ _unit(v) for v in samples.velocities.double()])
        weights = torch.exp(-(offsets**2).sum(-1) / (2 * width**2)) * cosines.clamp_min(1e-6)
        weights = weights / weights.sum()
        total = torch.zeros_like(x)
        for w, offset, v in zip(weights, offsets, samples.velocities.double()):
            u = _unit(v)
            total += w * (offset - (offset @ u) * u)
        rows.append(total)
    return torch.stack(rows)


def test_pull_matches_its_definition_sample_by_sample():
    # GIVEN samples in 3-D with some zero velocities, and states near them
    generator = torch.Generator().manual_seed(1)
    positions = torch.randn(300, 3, generator=generator, dtype=torch.float64)
    velocities = torch.randn(300, 3, generator=generator, dtype=torch.float64)
    velocities[::7] = 0.0
    empty = torch.zeros(0, 3)
    samples = Samples(positions, velocities, empty, torch.zeros(0, 1, 3), torch.zeros(0, 1))
    states = positions[:40] + 0.3 * torch.randn(40, 3, generator=generator, dtype=torch.float64)
    heading = velocities[:40] + 0.5 * torch.randn(40, 3, generator=generator, dtype=torch.float64)
    heading[::5] = 0.0
    # THEN the closed form equals the weighted sum of the offsets across each direction
    for width in (0.2, 1.0):
        expected = _brute_force_pull(states, samples, width, heading)
        torch.testing.assert_close(samples.pull(states, width, heading), expected)


def _two_lanes(gap: float) -> Samples:
    """Two straight parallel paths along x, at y = 0 and y = gap, densely sampled."""
    x = torch.linspace(-1.0, 1.0, 401, dtype=torch.float64)
    lanes = [torch.stack([x, torch.full_like(x, y)], 1) for y in (0.0, gap)]
    positions = torch.cat(lanes)
    velocities = torch.tensor([1.0, 0.0], dtype=torch.float64).expand_as(positions).clone()
    empty = torch.zeros(0, 2)
    return Samples(positions, velocities, empty, torch.zeros(0, 1, 2), torch.zeros(0, 1))


def test_pull_points_to_the_middle_of_close_paths_and_to_the_nearest_of_far_ones():
    states = torch.tensor([[0.1, 0.01], [0.2, 0.018], [0.0, -0.03]], dtype=torch.float64)
    # GIVEN two paths 0.02 apart and a width of 0.02: the pull is towards y = 0.01, across
    # the direction of travel only
    heading = torch.tensor([[1.0, 0.0]], dtype=torch.float64).expand(3, 2)
    close = _two_lanes(0.02).pull(states, 0.02, heading)
    torch.testing.assert_close(close[:, 0], torch.zeros(3, dtype=torch.float64))
    assert abs(close[0, 1]) < 1e-6  # on the middle line: no pull
    # Above the middle: pulled down towards it (the nearest path, y = 0.02, would pull up)
    assert 0 < close[1, 1] < 0.008
    # Below both paths: pulled up
    assert close[2, 1] < 0
    # GIVEN the same paths 1.0 apart: the offset from the nearest path, as without a width
    far = _two_lanes(1.0).pull(states, 0.02, heading)
    torch.testing.assert_close(far[:, 1], states[:, 1], atol=1e-9, rtol=0)


def test_pull_ignores_a_path_that_crosses_heading_elsewhere():
    # GIVEN a path along x and one along y crossing it at the origin
    t = torch.linspace(-1.0, 1.0, 401, dtype=torch.float64)
    zero = torch.zeros_like(t)
    positions = torch.cat([torch.stack([t, zero], 1), torch.stack([zero, t], 1)])
    velocities = torch.cat([torch.tensor([[1.0, 0.0]]), torch.tensor([[0.0, 1.0]])])
    velocities = velocities.double().repeat_interleave(401, dim=0)
    empty = torch.zeros(0, 2)
    samples = Samples(positions, velocities, empty, torch.zeros(0, 1, 2), torch.zeros(0, 1))
    states = torch.tensor([[0.01, 0.015], [-0.02, -0.01]], dtype=torch.float64)
    # THEN a state heading along x is pulled onto the x path only (its y offset), and one
    # heading along y onto the y path only
    along_x = samples.pull(states, 0.04, torch.tensor([[1.0, 0.0]]).double().expand(2, 2))
    torch.testing.assert_close(along_x, torch.stack([zero[:2], states[:, 1]], 1), atol=1e-4, rtol=0)
    along_y = samples.pull(states, 0.04, torch.tensor([[0.0, 1.0]]).double().expand(2, 2))
    torch.testing.assert_close(along_y, torch.stack([states[:, 0], zero[:2]], 1), atol=1e-4, rtol=0)
