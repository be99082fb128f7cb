"""Many fits at once: a stacked fit must give what separate fits give.

Batched matrix products round differently from single ones (an ulp here and there), and
training amplifies such differences: a separate float64 fit whose first layer is scaled by
1 + 1e-15 differs from the unscaled one by 1e-7 in its loss after 30 steps at lr 1e-2 with
the warped V. The comparisons here therefore train at lr 1e-3 with the warp, or lr 1e-2 with
the convex V, where 30 steps keep the two within 1e-9.

Weights are compared relative to the policy's largest weight, not each to itself: a few
parameters cancel in exact arithmetic (the output bias of f in f(x) - f(0), the ICNN's linear
term in the Bregman form), so their gradient is rounding noise and only their absolute size
means anything.
"""

from __future__ import annotations

from dataclasses import replace

import pytest
import torch

from snds import batched
from snds import train as train_module
from snds.batched import fit_many
from snds.data import split_samples
from snds.errors import ConfigError, SNDSError
from snds.train import TrainConfig, fit

from conftest import SMALL, make_policy, spiral_demos

WARPED = TrainConfig(
    steps=30, lr=1e-3, batch_size=64, window=2, window_batch_size=16, shape_weight=0.1
)


@pytest.fixture(scope="module")
def motions():
    """Three motions with different numbers of training samples (320, 360 and 240)."""
    demos = [
        spiral_demos(count=2, samples=200),
        spiral_demos(count=3, samples=150),
        spiral_demos(count=1, samples=300),
    ]
    return demos, [split_samples(d, test_fraction=0.2, seed=k) for k, d in enumerate(demos)]


def both(motions, architecture, config, dtype=torch.float64):
    """Separate fits and one batched fit of seeds 0, 1, 2 on the three motions."""
    demos, splits = motions
    configs = [replace(config, seed=seed, dtype=str(dtype)[6:]) for seed in range(3)]

    def policies():
        return [
            make_policy(d, architecture, seed=c.seed, dtype=dtype) for d, c in zip(demos, configs)
        ]

    alone = policies()
    expected = [fit(*args, progress=False) for args in zip(alone, demos, splits, configs)]
    stacked = policies()
    results = fit_many(stacked, demos, splits, configs, progress=False)
    return alone, expected, stacked, results


def weight_error(a, b) -> float:
    """Largest weight difference over the largest weight of ``a``."""
    scale = max(p.abs().max().item() for p in a.parameters())
    return max((p - q).abs().max().item() for p, q in zip(a.parameters(), b.parameters())) / scale


def history_error(a, b) -> float:
    assert len(a.history) == len(b.history)
    return max(abs(x - y) / abs(x) for x, y in zip(a.history, b.history))


@pytest.mark.parametrize(
    ("architecture", "config"),
    [
        # Every term on: noise, nominal term, windows, shape and warp penalties.
        (SMALL, WARPED),
        # Full batches of three sizes: three groups of one.
        (replace(SMALL, warp_layers=0), TrainConfig(steps=30, lr=1e-2, batch_size=0)),
        (replace(SMALL, stable=False), TrainConfig(steps=30, lr=1e-2, batch_size=64)),
    ],
    ids=["snds-warped", "snds-convex-full-batch", "bc"],
)
def test_batched_fits_equal_separate_fits_float64(motions, architecture, config):
    # GIVEN three seeds on three motions of different sizes, fitted separately and stacked
    alone, expected, stacked, results = both(motions, architecture, config)
    # THEN every weight and every step's loss agree to 1e-9
    for a, b, x, y in zip(alone, stacked, expected, results):
        assert (
            (y.steps, y.restarts, y.stopped) == (x.steps, x.restarts, x.stopped) == (30, 0, "steps")
        )
        assert weight_error(a, b) < 1e-9
        assert history_error(x, y) < 1e-9


def test_batched_fits_equal_separate_fits_float32(motions):
    alone, expected, stacked, results = both(motions, SMALL, WARPED, torch.float32)
    demos, _ = motions
    for a, b, x, y, d in zip(alone, stacked, expected, results, demos):
        # float32 rounding, amplified as in float64. Measured: loss 2e-4 relative, weights
        # 1.4e-3 of the largest (the noise-driven ones; the others 1e-4), velocities along a
        # demonstration 0.8% of its top speed.
        assert history_error(x, y) < 1e-3
        assert weight_error(a, b) < 1e-2
        states = torch.tensor(d[0].positions, dtype=torch.float32)
        with torch.no_grad():
            assert (a(states) - b(states)).abs().max() < 2e-2 * a(states).abs().max()


def test_a_diverging_fit_restarts_alone_as_it_would_separately(motions, monkeypatch):
    # GIVEN a fit whose step 7 gives a NaN loss (its states made NaN), separately and stacked
    demos, splits = motions
    configs = [replace(WARPED, seed=seed, dtype="float64") for seed in range(3)]
    victims: set[int] = set()
    real = train_module.draw_step
    calls: dict[tuple[int, int], int] = {}

    def draw(policy, samples, config, generator, *step):
        inputs = real(policy, samples, config, generator, *step)
        # Counted per generator: fit_many also draws once from a copy of each fit's.
        key = (id(policy), id(generator))
        calls[key] = calls.get(key, 0) + 1
        if id(policy) in victims and calls[key] == 8:
            inputs = replace(inputs, positions=inputs.positions * float("nan"))
        return inputs

    monkeypatch.setattr(train_module, "draw_step", draw)
    monkeypatch.setattr(batched, "draw_step", draw)
    alone = [make_policy(d, SMALL, seed=c.seed) for d, c in zip(demos, configs)]
    stacked = [make_policy(d, SMALL, seed=c.seed) for d, c in zip(demos, configs)]
    victims |= {id(alone[1]), id(stacked[1])}
    expected = [fit(*args, progress=False) for args in zip(alone, demos, splits, configs)]
    results = fit_many(stacked, demos, splits, configs, progress=False)
    # THEN only that fit restarts (and loses a step), the others go on, and all agree
    assert [r.restarts for r in results] == [r.restarts for r in expected] == [0, 1, 0]
    assert [r.steps for r in results] == [30, 29, 30]
    for a, b, x, y in zip(alone, stacked, expected, results):
        assert weight_error(a, b) < 1e-9 and history_error(x, y) < 1e-9


def test_fits_that_stop_early_leave_the_stack(motions):
    config = replace(WARPED, patience=4, min_improvement=0.02)
    _, expected, _, results = both(motions, SMALL, config)
    assert [r.stopped for r in results] == [r.stopped for r in expected]
    assert [r.steps for r in results] == [r.steps for r in expected]
    assert len({r.steps for r in results}) > 1, "the test needs fits that stop at other steps"


def test_only_the_seed_may_differ(motions):
    demos, splits = motions
    policies = [make_policy(d) for d in demos[:2]]
    with pytest.raises(ConfigError, match="lr"):
        fit_many(policies, demos[:2], splits[:2], [TrainConfig(), TrainConfig(lr=1e-3)])
    other = [policies[0], make_policy(demos[1], replace(SMALL, hidden=(16, 16)))]
    with pytest.raises(ConfigError, match="architecture"):
        fit_many(other, demos[:2], splits[:2], [TrainConfig(), TrainConfig(seed=1)])
    with pytest.raises(ConfigError, match="twice"):
        fit_many([policies[0]] * 2, demos[:2], splits[:2], [TrainConfig(), TrainConfig(seed=1)])
    with pytest.raises(ConfigError, match="as many"):
        fit_many(policies, demos, splits, [TrainConfig()] * 3)


def test_benchmark_fits_seeds_together_into_the_usual_run_folders(tmp_path, monkeypatch):
    # GIVEN a sweep of two seeds of Line/snds with --batch-fits 2 (a short stability check)
    import importlib

    from snds import benchmark
    from snds.benchmark import sweep
    from snds.models import load_model

    # The module (import_module: no attribute lookup on the package).
    evaluate = importlib.import_module("snds.evaluate")
    check_stability = evaluate.check_stability

    def short_check(policy, demos, config=None):
        config = evaluate.CheckConfig() if config is None else config
        return check_stability(policy, demos, replace(config, horizon_factor=0.2))

    monkeypatch.setattr(evaluate, "check_stability", short_check)
    tasks = benchmark.make_tasks(["Line"], ["snds"], seeds=2, demos=2)
    settings = benchmark.SweepSettings(steps=20, rollouts=5, samples=100, batch_fits=2)

    def alone(task, settings):
        pytest.fail("a seed was fitted alone")

    monkeypatch.setattr(sweep, "run_task", alone)
    rows = benchmark.run_sweep(tasks, out=tmp_path, settings=settings, jobs=1, progress=False)
    # THEN both runs are stored where a sweep of separate fits puts them, with their record
    assert [(r["seed"], r["decrease_violations"]) for r in rows] == [(0, 0), (1, 0)]
    for task in tasks:
        _, description = load_model(tmp_path / task.model_dir)
        assert description["batched"] == 2 and description["train"]["seed"] == task.seed
    assert '"batch_fits": 2' in (tmp_path / benchmark.SETTINGS_FILE).read_text()
    # AND a rerun finds them done; one of other settings is refused
    assert benchmark.run_sweep(tasks, out=tmp_path, settings=settings, jobs=1, progress=False)
    with pytest.raises(SNDSError, match="another --out"):
        benchmark.run_sweep(tasks, out=tmp_path, settings=replace(settings, batch_fits=1))
