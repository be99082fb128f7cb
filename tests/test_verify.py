"""The step certificate (snds.certify, snds verify): every bound holds on dense samples, bad
models are refuted with concrete states, proven regions hold on a million samples, and the
re-check rejects altered files."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from snds.certify import interval as ia
from snds.certify.bounds import cell_bounds
from snds.certify.certificate import (
    VerifyConfig,
    certified_rate,
    certify,
    read_certificate,
    write_certificate,
)
from snds.certify.model import (
    NotCertifiable,
    PolicyModel,
    f_jet,
    f_quadratic,
    rate_bounds,
    v_forms,
    v_jet,
)
from snds.certify.recheck import recheck
from snds.certify.search import deployed_step
from snds.cli import main
from snds.models import save_model
from snds.policy import PolicyConfig

from conftest import make_policy, spiral_demos

#: A small policy with every part of the default: Fourier features, silu, a warped V, the
#: data kernel's anchors, near and far decay.
TINY = PolicyConfig(
    hidden=(16, 16),
    fourier_features=8,
    fourier_scale=1.0,
    lyapunov_hidden=(8, 8),
    warp_layers=1,
    warp_features=8,
    anchors=16,
)


@pytest.fixture(scope="module")
def tiny():
    demos = spiral_demos()
    policy = make_policy(demos, TINY, seed=3)
    # Anchors on the data, so the kernel's rate drop is active somewhere in the box.
    states = torch.as_tensor(
        np.concatenate([d.positions for d in demos]) / policy.length, dtype=torch.float64
    )
    policy.set_anchors(states)
    return policy


def _samples(lo: np.ndarray, hi: np.ndarray, count: int, rng) -> np.ndarray:
    return lo + (hi - lo) * rng.random((count, *lo.shape))


@pytest.mark.parametrize(
    ("name", "fn", "exact"),
    [
        ("exp", ia.exp, np.exp),
        ("sqrt", ia.sqrt, np.sqrt),
        ("sigmoid", ia.sigmoid, lambda v: 1 / (1 + np.exp(-v))),
        ("silu", ia.silu, lambda v: v / (1 + np.exp(-v))),
        (
            "silu_slope",
            ia.silu_slope,
            lambda v: (s := 1 / (1 + np.exp(-v))) * (1 + v * (1 - s)),
        ),
        ("cos", ia.cos, np.cos),
        ("sin", ia.sin, np.sin),
    ],
)
def test_elementwise_enclosures_hold_every_dense_sample(name, fn, exact):
    # GIVEN intervals of every width, around the functions' turning points too
    rng = np.random.default_rng(0)
    mid = rng.uniform(-8, 8, 400)
    if name == "sqrt":
        mid = np.abs(mid)
    width = 10.0 ** rng.uniform(-6, 1, 400)
    lo, hi = mid - width, mid + width
    if name == "sqrt":
        lo = np.maximum(lo, 0.0)
    box = ia.from_bounds(lo, hi)
    # WHEN each is bounded and sampled densely (ends included)
    x = np.concatenate([_samples(lo, hi, 2000, rng), lo[None], hi[None]])
    # THEN no sample leaves its interval
    values = exact(x)
    assert (values >= box_fn_lo(fn, box)).all() and (values <= fn(box).hi).all()


def box_fn_lo(fn, box):
    return fn(box).lo


def test_smooth_leaky_and_its_derivatives_enclose_samples():
    rng = np.random.default_rng(1)
    mid, width = rng.uniform(-6, 6, 300), 10.0 ** rng.uniform(-5, 0.5, 300)
    lo, hi = mid - width, mid + width
    x = np.concatenate([_samples(lo, hi, 2000, rng), lo[None], hi[None]])
    s = 1 / (1 + np.exp(-x))
    exact = (0.1 * x + 0.9 * np.logaddexp(0, x), 0.1 + 0.9 * s, 0.9 * s * (1 - s))
    for value, bound in zip(exact, ia.smooth_leaky(ia.from_bounds(lo, hi), 0.1), strict=True):
        assert (value >= bound.lo).all() and (value <= bound.hi).all()


def test_arithmetic_encloses_every_combination_of_samples():
    rng = np.random.default_rng(2)
    a_lo, b_lo = rng.normal(size=(50, 6)), rng.normal(size=(50, 6))
    a_hi, b_hi = a_lo + rng.random((50, 6)), b_lo + rng.random((50, 6))
    a, b = ia.from_bounds(a_lo, a_hi), ia.from_bounds(b_lo, b_hi)
    weight = rng.normal(size=(6, 4))
    weight_iv = ia.from_bounds(weight - 0.1, weight + 0.1)
    for _ in range(200):
        x, y = _samples(a_lo, a_hi, 1, rng)[0], _samples(b_lo, b_hi, 1, rng)[0]
        w = weight + rng.uniform(-0.1, 0.1, weight.shape)
        for value, bound in [
            (x + y, a + b),
            (x - y, a - b),
            (x * y, a * b),
            (x * x, a.square()),
            (x @ weight, ia.matmul(a, weight)),
            (x @ w, ia.matmul_iv(a, weight_iv)),
            (x.sum(-1), a.sum(-1)),
        ]:
            assert (value >= bound.lo).all() and (value <= bound.hi).all()


def _autograd_terms(policy, x: np.ndarray):
    """V, grad V, Hessian of V, f and a / V at states (B, n) in model coordinates."""
    z = torch.tensor(x, requires_grad=True)
    v = policy.lyapunov(z)
    g = torch.autograd.grad(v.sum(), z, create_graph=True)[0]
    h = torch.stack(
        [torch.autograd.grad(g[:, i].sum(), z, retain_graph=True)[0] for i in range(2)], 1
    )
    with torch.no_grad():
        f = policy.nominal(z)
        rate = policy.decay(torch.ones_like(v), z)
        pi = policy.field(z)
    return (
        v.detach().numpy(),
        g.detach().numpy(),
        h.detach().numpy(),
        f.numpy(),
        rate.numpy(),
        pi.numpy(),
    )


def test_network_bounds_hold_on_dense_samples_of_their_boxes(tiny):
    # GIVEN boxes of several sizes over the 3x box
    model = PolicyModel.from_policy(tiny)
    rng = np.random.default_rng(3)
    centers = rng.uniform(-3, 3, (40, 2))
    half = np.repeat(10.0 ** rng.uniform(-3, -1, 40)[:, None], 2, 1)
    lo, hi = centers - half, centers + half
    # WHEN V, its gradient and Hessian, f and the decay rate are bounded over each
    bounds = {
        "v": v_jet(model, lo, hi, order=2),
        "forms": v_forms(model, centers, half, order=2),
        "f": f_jet(model, lo, hi).value,
        "fq": f_quadratic(model, centers, half).interval(),
        "rate": rate_bounds(model, lo, hi),
        "cells": cell_bounds(model, lo, hi, step=0.01, eta=1e-6),
    }
    # THEN 500 samples of every box, corners included, fall inside every bound
    for k in range(len(lo)):
        x = _samples(lo[k], hi[k], 500, rng)
        x = np.concatenate([x, [lo[k], hi[k], [lo[k, 0], hi[k, 1]], [hi[k, 0], lo[k, 1]]]])
        v, g, h, f, rate, pi = _autograd_terms(tiny, x)
        for jet in (bounds["v"], bounds["forms"]):
            value, grad = (
                jet.value.interval() if hasattr(jet.value, "interval") else jet.value,
                (jet.grad.interval() if hasattr(jet.grad, "interval") else jet.grad),
            )
            hess = jet.hess.interval() if hasattr(jet.hess, "interval") else jet.hess
            assert (v >= value.lo[k, 0]).all() and (v <= value.hi[k, 0]).all()
            assert (g >= grad.lo[k, :, 0]).all() and (g <= grad.hi[k, :, 0]).all()
            assert (h >= hess.lo[k, :, :, 0]).all() and (h <= hess.hi[k, :, :, 0]).all()
        for enclosure in (bounds["f"], bounds["fq"]):
            assert (f >= enclosure.lo[k]).all() and (f <= enclosure.hi[k]).all()
        assert (rate >= bounds["rate"][0][k]).all() and (rate <= bounds["rate"][1][k]).all()
        cells = bounds["cells"]
        assert (np.linalg.norm(pi, axis=1) <= cells.speed[k]).all()
        assert (np.linalg.norm(g, axis=1) <= cells.grad_hi[k]).all()
        assert (v * rate >= cells.a_lo[k]).all()


def test_the_unconstrained_policy_is_refuted_with_a_concrete_state():
    # GIVEN behavioural cloning: the same networks without the projection
    demos = spiral_demos()
    policy = make_policy(demos, replace(TINY, stable=False, warp_layers=0), seed=1)
    # WHEN it is certified
    certificate = certify(policy, dt=0.05 * policy.time, weights_sha256="x")
    # THEN it is refuted, never proven, and its counterexamples raise V when stepped
    assert certificate["status"] == "refuted" and certificate["counterexamples"]
    assert certificate["proven"] == []
    _check_counterexamples(policy, certificate)


def _check_counterexamples(policy, certificate):
    for example in certificate["counterexamples"]:
        x = torch.tensor([example["state"], example["next"]], dtype=torch.float64)
        before, after = policy.lyapunov(policy.to_model(x)).tolist()
        assert after > before
        stepped = deployed_step(
            policy,
            np.array([example["state"]]),
            dt=certificate["requested_dt"],
            dtype=torch.float64,
        )
        assert np.array_equal(stepped[0], example["next"])


def test_a_step_far_above_the_safe_step_is_refuted(tiny):
    certificate = certify(tiny, dt=50 * tiny.time, weights_sha256="x")
    assert certificate["status"] == "refuted" and certificate["largest_certified_dt"] == 0.0
    _check_counterexamples(tiny, certificate)


@pytest.fixture(scope="module")
def proven(tiny):
    certificate = certify(
        tiny, dt=0.01 * tiny.time, weights_sha256="x", config=VerifyConfig(start_size=1.0)
    )
    assert certificate["status"] == "proven" and certificate["dt"] == 0.01 * tiny.time
    return certificate


def test_a_proven_box_shows_no_rising_step_in_a_million_samples(tiny, proven):
    # GIVEN a million states of the proven box, outside the excluded ball
    rng = np.random.default_rng(4)
    half, radius = proven["box_half_width"], proven["excluded_radius"]
    z = rng.uniform(-half, half, (1_000_000, 2))
    z = z[np.linalg.norm(z, axis=1) > radius]
    x = z * tiny.length + tiny.target
    # WHEN each takes one step of the certified period as the export computes it
    nxt = deployed_step(tiny, x, dt=proven["dt"], dtype=torch.float64)
    with torch.no_grad():
        before = tiny.lyapunov(tiny.to_model(torch.as_tensor(x)))
        after = tiny.lyapunov(tiny.to_model(torch.as_tensor(nxt)))
    # THEN V falls at every one
    assert (after < before).all()


def test_the_recheck_confirms_a_proof_and_rejects_altered_files(tiny, proven, tmp_path):
    path = write_certificate(tmp_path / "certificate.json", proven)
    assert recheck(tiny, read_certificate(path), weights_sha256="x", max_failures=1).ok
    assert certified_rate(path) == pytest.approx(1 / proven["dt"])
    # An edited number (digest left as written).
    data = json.loads(path.read_text())
    data["proven"][0][3] *= 2
    assert not recheck(tiny, data, weights_sha256="x", max_failures=1).ok
    # A 100x longer step, with the digest recomputed: the re-check's own proof fails.
    data = dict(proven)
    data["dt"] = proven["dt"] * 100
    assert not recheck(
        tiny, read_certificate(write_certificate(path, data)), weights_sha256="x", max_failures=1
    ).ok
    # A proven cell removed: the cells no longer tile the box.
    data = dict(proven)
    data["proven"] = proven["proven"][1:]
    assert not recheck(
        tiny, read_certificate(write_certificate(path, data)), weights_sha256="x", max_failures=1
    ).ok
    # Other weights.
    assert not recheck(
        tiny, read_certificate(write_certificate(path, proven)), weights_sha256="y", max_failures=1
    ).ok


def test_models_that_cannot_be_certified_are_never_proven(tiny):
    # Relaxed mode (a = 0): no decrease to prove.
    demos = spiral_demos()
    relaxed = make_policy(
        demos, replace(TINY, decay_rate=0.0, decay_far=0.0, decay_near=0.0), seed=2
    )
    certificate = certify(
        relaxed, dt=0.01 * relaxed.time, weights_sha256="x", config=VerifyConfig(budget=3000)
    )
    assert certificate["status"] != "proven" and certificate["largest_certified_dt"] == 0.0
    # A phase, and affine couplings in the warp: refused with the reason.
    with pytest.raises(NotCertifiable, match="phase"):
        PolicyModel.from_policy(make_policy(demos, replace(TINY, phase_dim=1)))
    with pytest.raises(NotCertifiable, match="rectifier"):
        PolicyModel.from_policy(make_policy(demos, replace(TINY, rectifier="softplus")))


def test_the_cli_writes_and_rechecks_a_certificate(tiny, tmp_path, capsys):
    save_model(tiny.float(), tmp_path / "m")
    out = tmp_path / "m" / "certificate.json"
    dt = 0.005 * tiny.time
    argv = ["--quiet", "verify", str(tmp_path / "m"), "--dt", repr(dt), "--box", "0.5"]
    assert main(argv) == 0
    data = read_certificate(out)
    assert data["status"] == "proven" and math.isclose(data["dt"], dt)
    assert main(["--quiet", "verify", str(tmp_path / "m"), "--check", str(out)]) == 0
    data["dt"] = dt * 1e4
    out.write_text(json.dumps(data))
    assert main(["--quiet", "verify", str(tmp_path / "m"), "--check", str(out)]) == 1
    # No metrics.json and no --dt: one line, exit 2.
    capsys.readouterr()
    assert main(["verify", str(tmp_path / "m")]) == 2
    assert capsys.readouterr().err.count("\n") == 1
