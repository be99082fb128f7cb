import dataclasses

import numpy as np
import pytest
import torch

import snds
import snds.batches as batches
import snds.losses as losses_module
import snds.train as train_module
from snds.data import DataSource, Demonstration, Demonstrations, no_split, split_samples
from snds.decrease import decrease_violations
from snds.evaluate import accuracy
from snds.losses import AT_TARGET, make_samples
from snds.phase import Phase
from snds.spaces import Euclidean
from snds.train import (
    TrainConfig,
    TrainingError,
    fit,
    held_parameters,
    trained_parameters,
    training_samples,
)

from conftest import SMALL, make_policy, spiral_demos

FAST = TrainConfig(steps=400, batch_size=256, window_batch_size=64, lr=1e-2)


def test_fit_learns_a_linear_system_and_stays_stable(spiral):
    policy = make_policy(spiral, dtype=torch.float32)
    split = split_samples(spiral, test_fraction=0.2, seed=0)
    result = fit(policy, spiral, split, FAST, progress=False)
    assert result.steps == FAST.steps and result.restarts == 0
    assert np.mean(result.history[-20:]) < 0.1 * np.mean(result.history[:20])
    metrics = accuracy(policy.double(), spiral, split)
    assert metrics["velocity_mse_paper"] < 5e-3
    assert metrics["final_distance"] < 0.05 * spiral.extent()
    # By hand: the MSE over the mean squared speed of the same (test) samples.
    velocities = np.concatenate([d.velocities[m] for d, m in zip(spiral, split.test())])
    energy = np.mean(velocities**2)
    assert metrics["velocity_error_relative"] == pytest.approx(metrics["velocity_mse"] / energy)
    assert 0 < metrics["velocity_error_relative"] < 0.05


def test_same_seed_same_result(spiral):
    config = dataclasses.replace(FAST, steps=30)
    runs = []
    for _ in range(2):
        policy = make_policy(spiral, dtype=torch.float32)
        runs.append(fit(policy, spiral, no_split(spiral), config, progress=False).history)
    assert runs[0] == runs[1]


def test_recovers_from_a_nan_loss_without_a_rerun(spiral, monkeypatch):
    real_loss = train_module.step_loss
    calls = {"n": 0}

    def flaky(*args):
        calls["n"] += 1
        loss = real_loss(*args)
        return loss * float("nan") if calls["n"] == 10 else loss

    monkeypatch.setattr(train_module, "step_loss", flaky)
    policy = make_policy(spiral, dtype=torch.float32)
    result = fit(
        policy, spiral, no_split(spiral), dataclasses.replace(FAST, steps=50), progress=False
    )
    assert result.restarts == 1
    assert all(np.isfinite(result.history))
    assert all(torch.isfinite(p).all() for p in policy.parameters())


def test_gives_up_with_a_clear_error_after_repeated_divergence(spiral, monkeypatch):
    monkeypatch.setattr(
        train_module, "step_loss", lambda *args: torch.tensor(float("nan"), requires_grad=True)
    )
    policy = make_policy(spiral, dtype=torch.float32)
    with pytest.raises(TrainingError, match="diverged"):
        fit(policy, spiral, no_split(spiral), FAST, progress=False)


def test_early_stopping_on_plateau(spiral):
    policy = make_policy(spiral, dtype=torch.float32)
    config = dataclasses.replace(FAST, steps=5000, patience=50, lr=1e-5, min_improvement=0.5)
    result = fit(policy, spiral, no_split(spiral), config, progress=False)
    assert result.stopped == "plateau" and result.steps < 5000


@pytest.mark.parametrize("shape", ["mse", "srvf"])
def test_velocity_losses_and_window_train(spiral, shape):
    policy = make_policy(spiral, SMALL, dtype=torch.float32)
    config = dataclasses.replace(FAST, steps=100, velocity_shape=shape, window=2)
    result = fit(policy, spiral, no_split(spiral), config, progress=False)
    assert result.history[-1] < result.history[0]


class _QuadraticV(torch.nn.Module):
    """A stand-in policy whose V = (A x) . (A x): round when A is a multiple of the identity."""

    stable = True

    def __init__(self, matrix):
        super().__init__()
        self.matrix = torch.nn.Parameter(torch.as_tensor(matrix, dtype=torch.float64))

    def lyapunov(self, x):
        return ((x @ self.matrix.T) ** 2).sum(-1)


def test_shape_penalty_is_zero_for_round_v_and_blind_to_its_scale():
    with torch.no_grad():
        generator = torch.Generator().manual_seed(0)
        round_v = losses_module.shape_penalty(_QuadraticV(3.0 * np.eye(2)), 2, generator)
        assert float(round_v) < 1e-24
        state = generator.get_state()
        skewed = losses_module.shape_penalty(_QuadraticV(np.diag([1.0, 10.0])), 2, generator)
        generator.set_state(state)
        scaled = losses_module.shape_penalty(_QuadraticV(np.diag([7.0, 70.0])), 2, generator)
        assert float(skewed) > 0.1
        # The projection does not change when V is scaled, and neither does the penalty.
        assert float(scaled) == pytest.approx(float(skewed), rel=1e-9)


def test_shape_weight_rounds_v_and_keeps_the_fit(spiral):
    split = split_samples(spiral, test_fraction=0.2, seed=0)
    penalties = {}
    for weight in (0.0, 1.0):
        policy = make_policy(spiral, dtype=torch.float32)
        config = dataclasses.replace(FAST, shape_weight=weight)
        fit(policy, spiral, split, config, progress=False)
        assert accuracy(policy.double(), spiral, split)["velocity_mse_paper"] < 5e-3
        generator = torch.Generator().manual_seed(1)
        with torch.no_grad():
            penalty = losses_module.shape_penalty(policy.double(), 2, generator)
        penalties[weight] = float(penalty)
    assert penalties[1.0] < 0.5 * penalties[0.0]


def _brute_force_nearest(states: torch.Tensor, references: torch.Tensor) -> torch.Tensor:
    """The index of each state's nearest reference, from every squared distance."""
    return ((states[:, None, :] - references[None, :, :]) ** 2).sum(-1).argmin(dim=1)


def _nominal_gradient(policy, samples, weight: float) -> tuple[torch.Tensor, torch.Tensor]:
    """d loss / d f at the training states (full batch), and grad V there."""
    captured = {}

    def keep(module, inputs, output):
        output.retain_grad()
        captured["out"] = output

    handle = policy.nominal_net.register_forward_hook(keep)
    # Noise-free: the gradients are compared at the very states of the batch; no smoothness
    # penalty, whose own pass over f would be the one the hook keeps.
    config = TrainConfig(
        batch_size=0,
        nominal_weight=weight,
        position_noise=0.0,
        noise_correction=0.0,
        smooth_weight=0.0,
        dtype="float64",
    )
    loss = losses_module.step_loss(
        policy, config, batches.draw_step(policy, samples, config, torch.Generator().manual_seed(0))
    )
    loss.backward()
    handle.remove()
    # The nominal field is out[:-1] - out[-1] (the last row is the target), so d loss / d f
    # is the gradient at the first rows.
    grad_f = captured["out"].grad[:-1]
    _, grad_v = policy.lyapunov.value_and_grad(samples.positions)
    return grad_f, grad_v.detach()


def test_nominal_term_reaches_what_the_projection_hides(spiral):
    """Where the projection is active, the velocity term gives f's component along grad V no
    gradient (the stall behind Leaf_2 seed 0's plateau); the nominal term gives it exactly
    beta times the gradient of the velocity loss of f itself."""
    from snds.losses import make_samples, velocity_loss

    policy = make_policy(spiral)
    samples = make_samples(spiral, policy.normalization, no_split(spiral), window=0).to(
        torch.float64
    )
    with torch.no_grad():
        pi, f = policy.field_and_nominal(samples.positions)
        value, grad_v = policy.lyapunov.value_and_grad(samples.positions)
        active = (grad_v * f).sum(-1) + policy.decay(value, samples.positions) > 0
    assert 10 < int(active.sum()) < len(active)  # both kinds of states are tested
    along = {}
    for weight in (0.0, 0.25):
        policy.zero_grad()
        grad_f, grad_v = _nominal_gradient(policy, samples, weight)
        along[weight] = (grad_f * grad_v).sum(-1)[active]
    assert float(along[0.0].abs().max()) < 1e-12 * float(along[0.25].abs().max())
    f_leaf = f.clone().requires_grad_(True)
    (expected,) = torch.autograd.grad(velocity_loss(f_leaf, samples.velocities, "mse"), f_leaf)
    expected_along = 0.25 * (expected * grad_v).sum(-1)[active]
    torch.testing.assert_close(along[0.25], expected_along, rtol=1e-9, atol=1e-14)


def test_position_noise_perturbs_the_states_only(spiral):
    from snds.losses import make_samples

    policy = make_policy(spiral)
    samples = make_samples(spiral, policy.normalization, no_split(spiral), window=0).to(
        torch.float64
    )
    seen = []
    handle = policy.nominal_net.register_forward_hook(lambda m, i, o: seen.append(i[0][:-1]))
    for noise in (0.0, 0.05):
        config = TrainConfig(
            batch_size=0,
            position_noise=noise,
            noise_correction=0.0,
            smooth_weight=0.0,
            dtype="float64",
        )
        losses_module.step_loss(
            policy,
            config,
            batches.draw_step(policy, samples, config, torch.Generator().manual_seed(0)),
        )
    handle.remove()
    assert torch.equal(seen[0], samples.positions)
    offsets = seen[1] - samples.positions
    assert float(offsets.std()) == pytest.approx(0.05, rel=0.05)
    assert abs(float(offsets.mean())) < 0.005


@pytest.mark.parametrize(
    "name",
    [
        "nominal_weight",
        "position_noise",
        "noise_correction",
        "correction_noise",
        "shape_weight",
        "warp_weight",
    ],
)
@pytest.mark.parametrize("value", [-0.1, float("nan"), float("inf")])
def test_loss_weights_must_be_finite_and_non_negative(name, value):
    with pytest.raises(train_module.ConfigError, match=name):
        TrainConfig(**{name: value})


def test_warp_penalty_is_the_jacobians_distance_from_the_identity(spiral):
    config = dataclasses.replace(SMALL, warp_layers=3)
    policy = make_policy(spiral, config, seed=5)
    warp = policy.lyapunov.warp
    generator = torch.Generator().manual_seed(0)
    # The warp starts as the identity: no penalty.
    assert losses_module.warp_penalty(warp, 2, generator).item() == 0.0
    with torch.no_grad():
        for p in warp.parameters():
            p.add_(torch.randn_like(p))
    # THEN with its own states and probes it is mean |(J - I) u|^2, J from autograd ...
    penalty = losses_module.warp_penalty(warp, 2, torch.Generator().manual_seed(1))
    replay = torch.Generator().manual_seed(1)
    x = torch.rand(256, 2, generator=replay).double() * 4 - 2
    u = torch.randn(256, 2, generator=replay).double()
    jacobian = torch.autograd.functional.jacobian(lambda y: warp(y).sum(0), x).permute(1, 0, 2)
    eye = torch.eye(2, dtype=torch.float64)
    expected = ((((jacobian - eye) @ u.unsqueeze(-1)).squeeze(-1)) ** 2).sum(-1).mean()
    torch.testing.assert_close(penalty, expected, rtol=1e-10, atol=0.0)
    # ... an unbiased estimate of E |J - I|_F^2 (mean of 200 draws within 5 standard errors)
    draws = torch.stack(
        [losses_module.warp_penalty(warp, 2, torch.Generator().manual_seed(k)) for k in range(200)]
    ).detach()
    x = torch.rand(100_000, 2, generator=torch.Generator().manual_seed(7)).double() * 4 - 2
    _, caches = warp.forward_with_caches(x)
    with torch.no_grad():
        columns = [warp.jvp(caches, e.expand_as(x)) for e in eye]
        frobenius = ((torch.stack(columns, -1) - eye) ** 2).sum((-2, -1)).mean()
    assert abs(draws.mean() - frobenius) < 5 * draws.std() / 200**0.5
    penalty.backward()
    # (a layer's bias only translates, so it does not enter J)
    assert all(layer.weight.grad.abs().sum() > 0 for layer in warp.layers)


def test_penalties_come_every_kth_step_with_k_times_their_weight(spiral):
    from snds.losses import make_samples

    config = dataclasses.replace(SMALL, warp_layers=3)
    policy = make_policy(spiral, config, seed=5)
    with torch.no_grad():
        for p in policy.lyapunov.warp.parameters():
            p.add_(torch.randn_like(p))
    samples = make_samples(spiral, policy.normalization, no_split(spiral), window=0).to(
        torch.float64
    )

    def loss(step: int, **settings) -> float:
        weights = {"warp_weight": 0.5, "shape_weight": 0.2, "smooth_weight": 1e-4} | settings
        train = TrainConfig(position_noise=0.0, noise_correction=0.0, dtype="float64", **weights)
        generator = torch.Generator().manual_seed(3)
        return float(
            losses_module.step_loss(
                policy, train, batches.draw_step(policy, samples, train, generator, step)
            ).detach()
        )

    bare = loss(0, warp_weight=0.0, shape_weight=0.0, smooth_weight=0.0)
    once = loss(0, penalty_every=1)
    # THEN at a multiple of k the penalties enter k times, and between them not at all
    assert once > bare
    assert loss(8, penalty_every=4) - bare == pytest.approx(4 * (once - bare), rel=1e-9)
    assert loss(9, penalty_every=4) == bare


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_direct_adam_and_clipping_are_torchs_bit_for_bit(spiral, monkeypatch, dtype):
    # clip_gradients and adam_step skip torch's per-call bookkeeping, not its arithmetic: a
    # fit with them equals one through clip_grad_norm_ and Adam.step to the last bit. A low
    # clip bound makes the clipping act.
    config = dataclasses.replace(FAST, steps=40, grad_clip=0.05, dtype=dtype)
    runs = []
    for reference in (False, True):
        if reference:

            def clip(parameters, max_norm):
                return torch.nn.utils.clip_grad_norm_(parameters, max_norm, foreach=True)

            def step(optimizer, lr):
                for group in optimizer.param_groups:
                    group["lr"] = lr
                optimizer.step()

            monkeypatch.setattr(train_module, "clip_gradients", clip)
            monkeypatch.setattr(train_module, "adam_step", step)
        policy = make_policy(spiral, dtype=torch.float32)
        history = fit(policy, spiral, no_split(spiral), config, progress=False).history
        runs.append((history, [p.detach().clone() for p in policy.parameters()]))
    assert runs[0][0] == runs[1][0]
    assert all(torch.equal(a, b) for a, b in zip(runs[0][1], runs[1][1], strict=True))


@pytest.mark.parametrize("steps", [10, 30, 150, 1500, 5000])
def test_warm_up_is_long_enough_for_short_fits(steps):
    from snds.train import MIN_WARMUP_STEPS, _learning_rate

    config = TrainConfig(steps=steps)
    rates = [_learning_rate(k, config) for k in range(steps)]
    peak = rates.index(max(rates))
    # The rate climbs linearly to lr over the warm-up: a fraction of the fit, but never fewer
    # than MIN_WARMUP_STEPS steps (or a fifth of a shorter fit), then only falls.
    expected = max(1, int(config.warmup * steps), min(MIN_WARMUP_STEPS, steps // 5))
    assert peak == expected - 1 and rates[peak] == pytest.approx(config.lr)
    assert all(a < b for a, b in zip(rates[:peak], rates[1 : peak + 1]))
    assert all(a >= b for a, b in zip(rates[peak:], rates[peak + 1 :]))


def test_the_part_of_an_offset_across_the_direction_of_travel():
    offsets = torch.tensor([[1.0, 1.0], [3.0, -2.0], [0.5, 0.25]], dtype=torch.float64)
    velocities = torch.tensor([[2.0, 0.0], [0.0, -5.0], [0.0, 0.0]], dtype=torch.float64)
    across = batches.across(offsets, velocities)
    # Along x, along y, and all of the offset where the velocity is 0 (no direction).
    expected = torch.tensor([[0.0, 1.0], [3.0, 0.0], [0.5, 0.25]], dtype=torch.float64)
    torch.testing.assert_close(across, expected)


def test_corrective_noise_trains_moved_states_towards_the_nearest_sample(spiral):
    # GIVEN the full batch of training samples, no position noise, a correction share, and
    # the offset from the nearest sample alone (no width)
    policy = make_policy(spiral, seed=0)
    samples = train_module.make_samples(spiral, policy.normalization, no_split(spiral), window=0)
    samples = samples.to(torch.float64)
    config = TrainConfig(
        batch_size=0,
        position_noise=0.0,
        noise_correction=4.0,
        correction_noise=0.05,
        correction_share=0.3,
        correction_width=0.0,
        seed=0,
    )
    draw = batches.draw_step(policy, samples, config, torch.Generator().manual_seed(3))
    # THEN about that share of the states moved, by about that noise; the rest are as
    # demonstrated, with their demonstrated velocities
    moved = (draw.positions != samples.positions).any(-1)
    assert 0.25 < float(moved.double().mean()) < 0.35
    kept = ~moved
    torch.testing.assert_close(draw.positions[kept], samples.positions[kept], rtol=0, atol=0)
    torch.testing.assert_close(draw.velocities[kept], samples.velocities[kept], rtol=0, atol=0)
    offsets = draw.positions[moved] - samples.positions[moved]
    assert float(offsets.std()) == pytest.approx(0.05, rel=0.1)
    # AND each moved state is trained towards the nearest sample's velocity minus k times
    # the offset from that sample across it (found here by brute force)
    x = draw.positions[moved]
    nearest = _brute_force_nearest(x, samples.positions)
    anchor, velocity = samples.positions[nearest], samples.velocities[nearest]
    direction = velocity / velocity.norm(dim=-1, keepdim=True)
    offset = x - anchor
    across = offset - (offset * direction).sum(-1, keepdim=True) * direction
    torch.testing.assert_close(draw.velocities[moved], velocity - 4.0 * across)
    assert float(across.norm(dim=-1).mean()) > 0.01
    # The nearest sample is not always the one a state was moved from: then the state
    # learns its neighbour's velocity, not a correction towards its own sample.
    source = torch.nonzero(moved)[:, 0]
    assert (nearest != source).any()


def test_corrective_noise_searches_a_bounded_set_of_samples(spiral, monkeypatch):
    # GIVEN more samples than the search's bound
    monkeypatch.setattr(losses_module, "NEAREST_REFERENCES", 100)
    policy = make_policy(spiral, seed=0)
    samples = train_module.make_samples(spiral, policy.normalization, no_split(spiral), window=0)
    samples = samples.to(torch.float64)
    assert len(samples.positions) > 1000
    config = TrainConfig(
        batch_size=0,
        position_noise=0.0,
        noise_correction=10.0,
        correction_noise=0.05,
        correction_share=1.0,
        correction_width=0.0,
    )
    draw = batches.draw_step(policy, samples, config, torch.Generator().manual_seed(3))
    # THEN every target is the velocity of one of the evenly spaced references, corrected
    stride = -(-len(samples.positions) // 100)
    references = samples.positions[::stride]
    assert len(references) <= 100
    nearest = _brute_force_nearest(draw.positions, references) * stride
    velocity = samples.velocities[nearest]
    offset = draw.positions - samples.positions[nearest]
    expected = velocity - config.noise_correction * batches.across(offset, velocity)
    torch.testing.assert_close(draw.velocities, expected)


def test_no_correction_leaves_the_batch_and_the_random_stream_alone(spiral):
    policy = make_policy(spiral, seed=0)
    samples = train_module.make_samples(spiral, policy.normalization, no_split(spiral), window=0)
    samples = samples.to(torch.float64)
    off = TrainConfig(batch_size=64, noise_correction=0.0)
    generator = torch.Generator().manual_seed(3)
    # (a step without the penalties, whose random states come after)
    draw = batches.draw_step(policy, samples, off, generator, step=1)
    after = torch.rand(1, generator=generator)
    # The same draws as position noise alone: a batch index, then its noise.
    generator = torch.Generator().manual_seed(3)
    index = torch.randint(len(samples.positions), (64,), generator=generator)
    noise = off.position_noise * torch.randn((64, 2), generator=generator).double()
    torch.testing.assert_close(draw.positions, samples.positions[index] + noise)
    torch.testing.assert_close(draw.velocities, samples.velocities[index], rtol=0, atol=0)
    assert torch.equal(after, torch.rand(1, generator=generator))


@pytest.mark.parametrize("share", [-0.1, 1.5, float("nan")])
def test_correction_share_must_be_a_fraction(share):
    with pytest.raises(train_module.ConfigError, match="correction_share"):
        TrainConfig(correction_share=share)


def test_a_correction_width_pulls_towards_the_weighted_paths(spiral):
    # GIVEN every state of a batch moved off the data, with a correction width
    policy = make_policy(spiral, seed=0)
    samples = train_module.make_samples(spiral, policy.normalization, no_split(spiral), window=0)
    samples = samples.to(torch.float64)
    config = TrainConfig(
        batch_size=0, position_noise=0.0, correction_share=1.0, correction_width=0.05
    )
    draw = batches.draw_step(policy, samples, config, torch.Generator().manual_seed(3))
    # THEN each target is the nearest sample's velocity minus k times the averaged pull
    nearest = samples.nearest(draw.positions)
    velocity = samples.velocities[nearest]
    pull = samples.pull(draw.positions, config.correction_width, velocity)
    expected = velocity - config.noise_correction * pull
    torch.testing.assert_close(draw.velocities, expected)


def test_training_samples_drop_only_the_states_at_the_target(spiral):
    # GIVEN samples with one state exactly at the target and one a hair away
    policy = make_policy(spiral)
    noiseless = TrainConfig(position_noise=0.0)
    samples = training_samples(spiral, policy, no_split(spiral), noiseless)
    everything = make_samples(spiral, policy.normalization, no_split(spiral), window=2)
    at_target = (everything.positions.norm(dim=-1) <= AT_TARGET).sum().item()
    # THEN without noise those at the target go (pi = 0 there for any weights), the rest stay
    assert at_target >= 1
    assert len(samples.positions) == len(everything.positions) - at_target
    assert (samples.positions.norm(dim=-1) > AT_TARGET).all()
    # AND with noise every velocity sample stays: noise moves it off the target
    noisy = training_samples(spiral, policy, no_split(spiral), TrainConfig())
    assert len(noisy.positions) == len(everything.positions)
    assert (noisy.window_starts.norm(dim=-1) > AT_TARGET).all()


def test_a_noiseless_fit_with_samples_a_hair_from_the_target_does_not_diverge():
    # GIVEN demonstrations whose last samples lie 1e-19 from the target (as a pose chart's
    # log map leaves them), trained in float32 without position noise
    base = spiral_demos(count=2, samples=200)
    demos = []
    for demo in base:
        positions = demo.positions.copy()
        positions[-1] = base.target + np.array([3e-19, -2e-19])
        demos.append(Demonstration(positions, demo.velocities, demo.times))
    demos = Demonstrations(tuple(demos), base.target, "hair")
    policy = make_policy(demos, dtype=torch.float32)
    config = TrainConfig(steps=100, seed=0, position_noise=0.0, max_restarts=0)
    # WHEN it trains with no restart allowed
    result = fit(policy, demos, no_split(demos), config, progress=False)
    # THEN no step diverged (there |grad V|^2 ~ 1e-38 and the projection's derivative overflowed)
    assert result.restarts == 0
    assert all(torch.isfinite(p).all() for p in policy.parameters())


def _phased_samples(demos, codes: int = 2):
    phased = Phase(codes=codes).apply(demos)
    policy = snds.make_policy(phased, config=SMALL, seed=0).double()
    config = TrainConfig(position_noise=0.0, dtype="float64")
    return policy, train_module.training_samples(phased, policy, no_split(phased), config)


def test_tracking_moves_positions_only_and_trains_them_back(spiral):
    # GIVEN a phase model's full batch, no other noise, tracking half of it
    policy, samples = _phased_samples(spiral)
    assert samples.tracked == 2 and samples.positions.shape[-1] == 4
    config = TrainConfig(
        batch_size=0,
        position_noise=0.0,
        noise_correction=0.0,
        tracking_gain=3.0,
        tracking_noise=0.05,
        tracking_share=0.5,
    )
    draw = batches.draw_step(policy, samples, config, torch.Generator().manual_seed(3))
    moved = (draw.positions != samples.positions).any(-1)
    # THEN about that share moved, in position only, by about that noise; the phase is kept
    assert 0.45 < float(moved.double().mean()) < 0.55
    torch.testing.assert_close(draw.positions[:, 2:], samples.positions[:, 2:], rtol=0, atol=0)
    offsets = draw.positions - samples.positions
    assert float(offsets[moved, :2].std()) == pytest.approx(0.05, rel=0.1)
    # AND each state is trained towards its own sample's velocity minus k times its offset
    torch.testing.assert_close(draw.velocities, samples.velocities - 3.0 * offsets)
    torch.testing.assert_close(draw.velocities[:, 2:], samples.velocities[:, 2:], rtol=0, atol=0)


def test_tracking_needs_a_phase(spiral):
    # GIVEN positions alone: nothing names which demonstration a state follows
    policy = make_policy(spiral, seed=0)
    samples = train_module.training_samples(spiral, policy, no_split(spiral), TrainConfig())
    assert samples.tracked == 0
    # THEN tracking leaves the batch and the random stream as without it
    draws = []
    for gain in (3.0, 0.0):
        generator = torch.Generator().manual_seed(3)
        config = TrainConfig(batch_size=64, tracking_gain=gain, tracking_share=1.0)
        draws.append((batches.draw_step(policy, samples, config, generator, step=1), generator))
    (on, after_on), (off, after_off) = draws
    assert torch.equal(on.positions, off.positions) and torch.equal(on.velocities, off.velocities)
    assert torch.equal(torch.rand(1, generator=after_on), torch.rand(1, generator=after_off))


def test_tracking_moves_a_pose_position_not_its_rotation():
    # GIVEN a pose model with a phase: its training state is position (3), rotation vector
    # (3), phase (2)
    demos = DataSource(motion="Sine", demos=2, poses=True, phase=Phase(codes=2)).load()
    policy = snds.make_policy(demos, config=SMALL)
    chart = policy.training_demonstrations(demos)
    samples = train_module.training_samples(chart, policy, no_split(chart), TrainConfig())
    # THEN tracking moves the position only: an offset of the rotation would be trained as an
    # orientation to turn back from, which the orientation error showed to cost
    assert samples.positions.shape[-1] == 8 and samples.tracked == 3


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("tracking_share", 1.5),
        ("tracking_share", -0.1),
        ("tracking_gain", -1.0),
        ("tracking_noise", float("nan")),
    ],
)
def test_tracking_settings_are_checked(field, value):
    with pytest.raises(train_module.ConfigError, match=field):
        TrainConfig(**{field: value})


class _Field(torch.nn.Module):
    """A stand-in policy whose nominal field is a given function of the state."""

    def __init__(self, field, position_dim: int):
        super().__init__()
        self.weight = torch.nn.Parameter(torch.zeros(()))
        self.field = field
        self.space = Euclidean(position_dim)

    def nominal(self, x: torch.Tensor) -> torch.Tensor:
        return self.field(x)


def test_smooth_penalty_is_zero_for_an_affine_field_and_the_curvature_for_a_quadratic():
    generator = torch.Generator().manual_seed(0)
    x = torch.rand(64, 3, generator=generator, dtype=torch.float64) * 4 - 2
    e = 0.1 * torch.randn(64, 3, generator=generator, dtype=torch.float64)
    weight = torch.rand(64, generator=generator, dtype=torch.float64)
    a = torch.randn(3, 3, generator=generator, dtype=torch.float64)
    affine = _Field(lambda s: s @ a.T + 1.5, 3)
    assert float(losses_module.smooth_penalty_at(affine, x, e, weight)) < 1e-20
    # f(x) = (x1^2, 0, x2 x3): its second difference along e is (2 e1^2, 0, 2 e2 e3), so the
    # penalty is the mean of w (4 e1^4 + 4 e2^2 e3^2) / |e|^4
    field = lambda s: torch.stack([s[:, 0] ** 2, 0 * s[:, 0], s[:, 1] * s[:, 2]], -1)  # noqa: E731
    expected = weight * 4 * (e[:, 0] ** 4 + e[:, 1] ** 2 * e[:, 2] ** 2) / (e * e).sum(-1) ** 2
    got = losses_module.smooth_penalty_at(_Field(field, 3), x, e, weight)
    assert float(got) == pytest.approx(float(expected.mean()), rel=1e-9)
    # AND only the positions' part of f counts (here the first two outputs)
    expected = weight * 4 * e[:, 0] ** 4 / (e * e).sum(-1) ** 2
    got = losses_module.smooth_penalty_at(_Field(field, 2), x, e, weight)
    assert float(got) == pytest.approx(float(expected.mean()), rel=1e-9)


def test_smooth_draws_fade_on_the_data_and_keep_a_phase_on_its_slices(spiral):
    # GIVEN a phase model's training samples (positions 2, phase 2)
    policy, samples = _phased_samples(spiral)
    like = next(policy.parameters())
    x, e, weight = batches.smooth_draws(
        samples, 2, torch.Generator().manual_seed(1), like, 0.1, 0.1
    )
    # THEN the positions are uniform in [-2, 2]; half the states carry a training sample's
    # phase and half phase 0, the slices a rollout visits
    assert x.shape == e.shape == (256, 4) and weight.shape == (256,)
    assert float(x[:, :2].abs().max()) <= 2.0 and float(x[:, :2].std()) > 0.9
    assert torch.equal(x[128:, 2:], torch.zeros(128, 2, dtype=x.dtype))
    phases = samples.positions[:, 2:]
    gap = (x[:128, None, 2:] - phases[None]).abs().sum(-1).min(dim=1).values
    assert float(gap.max()) == 0.0
    # AND each step has the asked length, in the positions only; each weight is
    # 1 - exp(-d^2 / 2 r^2) from the nearest training sample: 0 on the data, 1 far from it
    torch.testing.assert_close(e.norm(dim=-1), torch.full((256,), 0.1, dtype=e.dtype))
    assert torch.equal(e[:, 2:], torch.zeros(256, 2, dtype=e.dtype))
    d = (x[:, None] - samples.positions[None]).norm(dim=-1).min(dim=1).values
    torch.testing.assert_close(weight, 1 - torch.exp(-(d**2) / (2 * 0.1**2)), rtol=0, atol=1e-12)


def test_smooth_penalty_lowers_the_curvature_of_f_off_the_data(spiral):
    # GIVEN the same short fit with and without the penalty
    config = dataclasses.replace(FAST, steps=200, penalty_every=1)
    curvature = {}
    for weight in (0.0, 1e-4):
        policy = make_policy(spiral, seed=0)
        split = no_split(spiral)
        fit(
            policy, spiral, split, dataclasses.replace(config, smooth_weight=weight), progress=False
        )
        samples = training_samples(spiral, policy, split, config)
        with torch.no_grad():
            value = losses_module.smooth_penalty(
                policy, samples, torch.Generator().manual_seed(9), step=0.1, radius=0.1
            )
        curvature[weight] = float(value)
    # THEN f bends less off the data
    assert curvature[1e-4] < 0.5 * curvature[0.0]


def test_a_fit_that_keeps_v_moves_only_the_nominal_field_and_stays_stable(spiral):
    policy = make_policy(spiral, dtype=torch.float32)
    config = dataclasses.replace(FAST, steps=40, fit_lyapunov=False)
    held = held_parameters(policy, config)
    assert held and len(held) + len(trained_parameters(policy, config)) == len(
        list(policy.parameters())
    )
    assert held_parameters(policy, FAST) == [] and len(trained_parameters(policy, FAST)) == len(
        list(policy.parameters())
    )
    v_before = {k: v.clone() for k, v in policy.lyapunov.state_dict().items()}
    f_before = {k: v.clone() for k, v in policy.nominal_net.state_dict().items()}
    # WHEN it fits with V kept
    result = fit(policy, spiral, no_split(spiral), config, progress=False)
    # THEN V's weights are the same bits, the nominal field's have moved and learnt
    assert all(torch.equal(v_before[k], v) for k, v in policy.lyapunov.state_dict().items())
    assert not all(torch.equal(f_before[k], v) for k, v in policy.nominal_net.state_dict().items())
    assert np.mean(result.history[-5:]) < np.mean(result.history[:5])
    # and every parameter takes gradients again afterwards
    assert all(p.requires_grad for p in policy.parameters())
    # and the guarantee holds at random and far states (float64)
    generator = torch.Generator().manual_seed(0)
    extent = spiral.extent()
    x = (torch.rand(4000, 2, generator=generator, dtype=torch.float64) - 0.5) * 6 * extent
    far = torch.randn(500, 2, generator=generator, dtype=torch.float64) * 1e3 * extent
    policy64 = policy.double()
    assert decrease_violations(policy64, x) == 0 and decrease_violations(policy64, far) == 0
