"""The contract every method keeps, in every state space it fits.

For each method of :data:`snds.methods.METHODS` and each space (positions, poses, positions
with a phase) it declares it fits (:attr:`~snds.methods.Method.spaces`; the cases are built
from that declaration, so no pair is skipped): it fits tiny demonstrations;
its policy maps states to finite velocities and holds still at the target; a saved and
loaded copy gives the same velocities, bit for bit; its float64 ONNX export computes what
the library computes; and a method with a Lyapunov function decreases it
(:math:`\\nabla V^\\top \\pi < 0`) at random states near the data and far beyond it, in
float64. The settings are tiny (a few optimiser steps, small networks): the contract holds
for any weights, trained or not, so a short fit tests it as well as a long one.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from snds import benchmark, export
from snds.baselines.sdsef import SDSEFConfig
from snds.data import split_samples
from snds.data.poses import with_synthetic_orientations
from snds.errors import SNDSError
from snds.fitting import Fitted
from snds.methods import METHODS, Method
from snds.models import load_model, save_model
from snds.phase import Phase
from snds.policy import PolicyConfig
from snds.spaces import SE3, Euclidean, Phased

from conftest import spiral_demos

#: The spaces of the contract, by name, and the space a policy of each reports.
SPACES = {"positions": Euclidean, "poses": SE3, "phase": Phased}

#: Tiny settings: every method as registered, with small networks or mixtures.
TINY_NETWORK = PolicyConfig(
    hidden=(16, 16), fourier_features=8, lyapunov_hidden=(8, 8), warp_layers=1
)
STEPS = 8


def _tiny(name: str) -> Method:
    method = METHODS[name]
    if name in ("snds", "bc"):
        stable = method.policy_config.stable
        return replace(method, policy_config=replace(TINY_NETWORK, stable=stable))
    if name == "lpvds":
        return replace(method, components=2, lyapunov_starts=1, max_samples=200)
    if name == "seds":
        return replace(method, components=2, max_samples=200)
    if name == "sdsef":
        return replace(method, policy_config=SDSEFConfig(layers=2, features=8, speed_features=8))
    raise AssertionError(f"no tiny setting for the method {name!r}: add one")


def _demos(space: str):
    positions = spiral_demos(count=2, samples=60)
    if space == "poses":
        return with_synthetic_orientations(positions)
    if space == "phase":
        return Phase(codes=2, seed=1).apply(positions)
    return positions


#: Every (method, space) pair the method declares it fits, and only those.
CASES = [
    pytest.param(name, space, id=f"{name}-{space}")
    for name, method in METHODS.items()
    for space, kind in SPACES.items()
    if kind in method.spaces
]


def test_the_cases_cover_every_method_and_every_declared_space() -> None:
    # A space a method declares but the contract does not know would go untested, and a
    # registry that shrank would shrink the contract silently: both fail here instead.
    assert set(METHODS) == {"snds", "bc", "lpvds", "seds", "sdsef"}
    for name, method in METHODS.items():
        assert set(method.spaces) <= set(SPACES.values()), name
        assert Euclidean in method.spaces, f"{name} must fit positions"
    # SNDS and behavioural cloning fit every space; the baselines (mixtures of linear
    # systems, SDS-EF's flow) are defined on R^n only.
    for name in ("snds", "bc"):
        assert set(METHODS[name].spaces) == set(SPACES.values()), name
    # every declared pair is a case
    assert len(CASES) == sum(len(method.spaces) for method in METHODS.values()) == 9


@pytest.mark.parametrize("name", [n for n, m in METHODS.items() if SE3 not in m.spaces])
def test_a_method_is_refused_a_space_it_does_not_fit(name: str) -> None:
    # A pose task for a positions-only method is refused before any work, with one line
    # that names the method, the space and the methods that do fit it.
    with pytest.raises(
        SNDSError,
        match=rf"^{name} does not fit SE3 tasks \(Line-se3\); "
        r"methods that do: snds, bc$",
    ):
        benchmark.make_tasks(["Line"], [name], seeds=1, se3=True)


@pytest.mark.parametrize(
    ("name", "space"),
    [(n, s) for n, m in METHODS.items() for s, kind in SPACES.items() if kind not in m.spaces],
)
def test_a_method_refuses_demonstrations_of_a_space_it_does_not_fit(name: str, space: str) -> None:
    # Handed poses or a phase directly, a positions-only method says so in one line before
    # any work: it must not read a quaternion or a phase as more positions.
    demos = _demos(space)
    split = split_samples(demos, test_fraction=0.2, seed=0)
    what = "poses" if space == "poses" else "positions with a phase"
    with pytest.raises(SNDSError, match=rf"^{name} fits positions only, not {what}"):
        _tiny(name).fit(demos, split, seed=0)


@pytest.fixture(scope="module")
def fitted(request) -> dict[tuple[str, str], Fitted]:
    """The fits, made once per (method, space) the first time a test asks for one."""
    return {}


def _fit(cache: dict, name: str, space: str) -> tuple[Fitted, object]:
    if (name, space) not in cache:
        if name in ("lpvds", "seds"):
            pytest.importorskip("sklearn", reason="LPV-DS and SEDS need the baselines extra")
            pytest.importorskip("cvxpy", reason="LPV-DS and SEDS need the baselines extra")
        torch.set_num_threads(1)
        demos = _demos(space)
        split = split_samples(demos, test_fraction=0.2, seed=0)
        cache[name, space] = (_tiny(name).fit(demos, split, seed=0, steps=STEPS), demos)
    return cache[name, space]


def _user_states(policy, count: int, seed: int) -> torch.Tensor:
    """Random float64 user states from the data's region out to 1000 extents."""
    return torch.as_tensor(export.random_states(policy, count, seed=seed))


@pytest.mark.parametrize(("name", "space"), CASES)
def test_fit_predict_save_and_load(fitted, name: str, space: str, tmp_path: Path) -> None:
    fit, _ = _fit(fitted, name, space)
    policy = fit.policy.double().eval()
    # The fit: the method's policy, in the demonstrations' space, with the time it took.
    assert policy.method == name
    assert isinstance(policy.space, SPACES[space])
    assert fit.seconds > 0
    x = _user_states(policy, 300, seed=1)
    # Predict: finite velocities everywhere, and none at the target (an equilibrium).
    with torch.no_grad():
        velocities = policy(x)
        at_target = policy(torch.tensor(policy.target)[None])
    assert velocities.shape == (300, policy.space.tangent_dim)
    assert torch.isfinite(velocities).all()
    assert at_target.abs().max() <= 1e-9 * _top_speed(policy)
    # Save and load: the same velocities, bit for bit.
    save_model(fit.policy, tmp_path / "model", extra=fit.record)
    loaded, description = load_model(tmp_path / "model")
    assert description["kind"] == fit.policy.kind and type(loaded) is type(fit.policy)
    assert loaded.config == fit.policy.config and loaded.stable == fit.policy.stable
    with torch.no_grad():
        assert torch.equal(loaded.double().eval()(x), velocities)


#: ONNX exports cost 2-6 s of CPU each (the exporter, not the model). BC's pose and phase
#: graphs are SNDS's pose and phase wrappers around BC's network, each exported in the
#: default suite (snds-poses, snds-phase, bc-positions), so those two run with the slow tests.
SLOW_EXPORTS = {("bc", "poses"), ("bc", "phase")}

EXPORT_CASES = [
    pytest.param(*case.values, marks=[pytest.mark.slow], id=case.id)
    if tuple(case.values) in SLOW_EXPORTS
    else case
    for case in CASES
]


@pytest.mark.parametrize(("name", "space"), EXPORT_CASES)
def test_onnx_export_computes_what_the_library_computes(
    fitted, name: str, space: str, tmp_path: Path
) -> None:
    pytest.importorskip("onnxruntime", reason="the ONNX export needs the export extra")
    pytest.importorskip("onnxscript", reason="the ONNX export needs the export extra")
    fit, _ = _fit(fitted, name, space)
    policy = fit.policy.double().eval()
    # GIVEN the float64 export
    path = export.export_onnx(policy, tmp_path / "policy.onnx", dtype=torch.float64)
    # THEN it computes the library's velocities to rounding, from the data out to 1000x
    check = export.verify(path, policy, samples=500, seed=2)
    assert check.passed and check.max_error <= 1e-9, check.summary()
    x = _user_states(policy, 300, seed=1)
    with torch.no_grad():
        velocities = policy(x).numpy()
    np.testing.assert_allclose(
        export.load_onnx(path)(x.numpy()),
        velocities,
        rtol=1e-9,
        atol=1e-9 * _top_speed(policy),
    )


def _top_speed(policy) -> float:
    return float(policy.normalization.length / policy.normalization.time)


@pytest.mark.parametrize(("name", "space"), CASES)
def test_a_method_with_a_lyapunov_function_decreases_it(fitted, name: str, space: str) -> None:
    method = METHODS[name]
    fit, _ = _fit(fitted, name, space)
    policy = fit.policy.double().eval()
    assert policy.stable == method.has_lyapunov
    if not method.has_lyapunov:
        # BC: no V, and so no decrease to check (and nothing it promises).
        assert policy.lyapunov is None or not policy.stable
        return
    # GIVEN float64 model states at 1e-2 to 1e3 model units (the data's extent is 1)
    generator = torch.Generator().manual_seed(3)
    scales = torch.tensor([1e-2, 1e-1, 1.0, 10.0, 1e3], dtype=torch.float64)
    z = torch.randn(5, 400, policy.dim, generator=generator, dtype=torch.float64)
    z = (z * scales[:, None, None]).reshape(-1, policy.dim)
    # WHEN the field and V's gradient are evaluated there
    with torch.no_grad():
        terms = policy.field_terms(z)
    # THEN V strictly decreases along the field at every one of them
    decrease = (terms.grad * terms.field).sum(-1)
    assert torch.isfinite(decrease).all()
    assert (decrease < 0).all(), f"{int((decrease >= 0).sum())} states where V does not decrease"
