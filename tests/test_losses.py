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
