"""Shared fixtures: small policies and synthetic demonstrations that train in seconds."""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest
import torch

from snds.data import Demonstration, Demonstrations, Normalization
from snds.data.demonstrations import Split, split_samples
from snds.losses import make_samples
from snds.policy import PolicyConfig, StablePolicy

SHARED_DATA = Path(__file__).resolve().parents[2] / "shared" / "data"

# The test networks are tiny: one thread is faster than two (a 40-step fit took 1.4 s on one
# thread against 47 s on two on a loaded machine), and the CLI already defaults to one.
torch.set_num_threads(1)

SMALL = PolicyConfig(hidden=(32, 32), fourier_features=16, lyapunov_hidden=(16, 16))


def spiral_demos(count: int = 3, samples: int = 400, dim: int = 2) -> Demonstrations:
    """Demonstrations of a stable linear system x' = A x (a decaying spiral), ending at 0."""
    a = -0.5 * np.eye(dim)
    a[0, 1], a[1, 0] = 1.5, -1.5
    demos = []
    rng = np.random.default_rng(0)
    times = np.linspace(0.0, 16.0, samples)
    for _ in range(count):
        x0 = rng.normal(size=dim)
        x0 = 10.0 * x0 / np.linalg.norm(x0)
        # Closed form of the linear system through its eigen-decomposition.
        values, vectors = np.linalg.eig(a)
        coeffs = np.linalg.solve(vectors, x0)
        path = np.real((vectors * coeffs) @ np.exp(np.outer(values, times))).T
        path = path - path[-1]  # a shift of 5e-4: end exactly at the target
        demos.append(Demonstration(positions=path, velocities=path @ a.T, times=times))
    return Demonstrations(tuple(demos), np.zeros(dim), "spiral")


@pytest.fixture(scope="session")
def spiral() -> Demonstrations:
    return spiral_demos()


@pytest.fixture(scope="session")
def spiral_split(spiral: Demonstrations) -> tuple[Demonstrations, Split]:
    """The spiral with the 0.8 / 0.2 sample split of seed 0."""
    return spiral, split_samples(spiral, test_fraction=0.2, seed=0)


def held_out_relative_mse(policy: torch.nn.Module, demos: Demonstrations, split: Split) -> float:
    """A policy's velocity MSE on the test samples over their mean squared speed, in model
    coordinates and float64 (0: exact; 1: as bad as standing still)."""
    test = make_samples(demos, Normalization.fit(demos), Split(split.test()), window=0)
    policy = copy.deepcopy(policy).double()
    with torch.no_grad():
        error = ((policy.field(test.positions) - test.velocities) ** 2).sum(-1).mean()
    return float(error / (test.velocities**2).sum(-1).mean())


def lie_derivative_eigenvalues(policy: torch.nn.Module) -> np.ndarray:
    """For a blend of linear systems A_k with V = x^T P x: the largest eigenvalue of
    A_k^T P + P A_k for every k, shape (K,); all negative is the stability condition."""
    a = policy.matrices.detach().double().numpy()
    p = policy.lyapunov.matrix.detach().double().numpy()
    return np.linalg.eigvalsh(np.swapaxes(a, -1, -2) @ p + p @ a).max(-1)


def make_policy(
    demos: Demonstrations, config: PolicyConfig = SMALL, seed: int = 0, dtype=torch.float64
) -> StablePolicy:
    policy = StablePolicy(
        dim=demos.dim, normalization=Normalization.fit(demos), config=config, seed=seed
    )
    return policy.to(dtype)


@pytest.fixture
def policy64(spiral: Demonstrations) -> StablePolicy:
    """An untrained float64 stable policy: the guarantee must hold before any training."""
    return make_policy(spiral)


def linear_policy(gain: float) -> StablePolicy:
    """A 2-D stable policy that is exactly pi(x) = -gain x with V = d |x|^2 (float64).

    The nominal field is zero and the ICNN's input skips are zero, so g is constant and the
    Bregman form leaves V = d |x|^2; the projection then gives pi = -grad V a / |grad V|^2 =
    -(rho / 2) x with a = rho V. Plain Euler with step h maps x to (1 - gain h) x: it cycles
    at h = 2 / gain, which makes the guard's work checkable by hand.
    """
    config = PolicyConfig(
        hidden=(4,),
        fourier_features=0,
        lyapunov_hidden=(4,),
        decay_rate=2.0 * gain,
        decay_far=0.0,
        decay_near=0.0,
        warp_layers=0,
    )
    normalization = Normalization(center=np.zeros(2), length=1.0, time=1.0)
    policy = StablePolicy(dim=2, normalization=normalization, config=config).double()
    with torch.no_grad():
        for p in policy.nominal_net.parameters():
            p.zero_()
        for skip in policy.lyapunov.icnn.skips:
            skip.weight.zero_()
    return policy
