"""Export: the exported graph computes what the library computes, everywhere, in either format."""

from __future__ import annotations

import copy
import json
import runpy
import sys
import zipfile
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from snds import export
from snds.cli import main
from snds.data import Demonstration, Demonstrations
from snds.data.poses import with_synthetic_orientations
from snds.export import onnx_ops
from snds.export.fused import fusable
from snds.export.graph import NUMPY_DTYPES, policy_copy, top_speed
from snds.export.writers import quiet_exporter
from snds.models import save_model
from snds.policy import PolicyConfig
from snds.recipes import RECIPES
from snds.se3 import make_pose_policy

from conftest import SMALL, make_policy, spiral_demos

pytest.importorskip("onnxruntime", reason="the export tests need the export extra")
pytest.importorskip("onnxscript", reason="the export tests need the export extra")

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "onnx_control_loop.py"


@pytest.fixture(autouse=True, scope="module")
def one_thread():
    # One torch thread, as in the CLI: a control loop evaluates one state at a time, and a
    # second thread only waits for a core at every operation, more so on a busy machine.
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def shifted_spiral() -> Demonstrations:
    """The spiral task moved so that its target is off the origin, at (100, -50)."""
    base = spiral_demos()
    shift = np.array([100.0, -50.0])
    moved = tuple(
        Demonstration(positions=d.positions + shift, velocities=d.velocities, times=d.times)
        for d in base
    )
    return Demonstrations(moved, base.target + shift, "spiral")


def _anchored(policy, demos: Demonstrations):
    """The policy with its anchors on the demonstrations, as a fit places them, so that the
    data kernel of its decay rate is in the graph."""
    states = np.concatenate([d.positions for d in demos])
    with torch.no_grad():
        policy.set_anchors(policy.to_model(torch.as_tensor(states).to(policy.center.dtype)))
    return policy


@pytest.fixture(scope="module")
def policy():
    """An untrained float32 stable policy: the export must not depend on training."""
    demos = shifted_spiral()
    return _anchored(make_policy(demos, config=SMALL, seed=3, dtype=torch.float32), demos).eval()


@pytest.fixture(scope="module")
def onnx64(policy, tmp_path_factory) -> Path:
    return export.export_onnx(
        policy, tmp_path_factory.mktemp("onnx") / "policy.onnx", dtype=torch.float64
    )


def test_random_states_reach_far_beyond_the_data(policy) -> None:
    x = export.random_states(policy, 10_000, seed=0)
    distance = np.abs(x - policy.normalization.center).max(axis=1) / policy.normalization.length
    assert x.shape == (10_000, 2)
    assert distance.min() < 0.05 and distance.max() > 900
    assert (distance <= 1).mean() > 0.15  # a fair share near the data
    np.testing.assert_array_equal(x, export.random_states(policy, 10_000, seed=0))


def test_float64_onnx_equals_the_library_on_10000_states(policy, onnx64) -> None:
    # GIVEN a float64 ONNX export, run by onnxruntime, and the library in float64
    import onnxruntime as ort

    session = ort.InferenceSession(str(onnx64), providers=["CPUExecutionProvider"])
    x = export.random_states(policy, 10_000, seed=1)
    # WHEN both evaluate the same 10,000 states, out to 1000x the extent
    exported = session.run(None, {session.get_inputs()[0].name: x})[0]
    with torch.no_grad():
        library = policy.to(torch.float64)(torch.as_tensor(x)).numpy()
    policy.to(torch.float32)
    # THEN they agree to 1e-5 of max(|velocity|, top speed) state by state (in fact ~1e-13)
    scale = np.maximum(np.linalg.norm(library, axis=1), top_speed(policy))
    assert np.all(np.linalg.norm(exported - library, axis=1) / scale <= 1e-5)
    assert np.isfinite(exported).all()


def test_verify_reports_the_check_and_the_metadata(policy, onnx64) -> None:
    check = export.verify(onnx64, policy, samples=10_000, seed=0)
    assert check.passed and check.dtype == "float64" and check.samples == 10_000
    assert check.max_error <= 1e-9
    import onnx

    meta = {p.key: p.value for p in onnx.load(str(onnx64)).metadata_props}
    assert json.loads(meta["snds.target"]) == [100.0, -50.0]
    assert meta["snds.dim"] == "2" and meta["snds.dtype"] == "float64"
    assert float(meta["snds.extent"]) == pytest.approx(policy.normalization.length)


def test_verify_catches_a_model_that_computes_something_else(policy, onnx64) -> None:
    # GIVEN the export of one policy, checked against a policy with other weights
    other = make_policy(shifted_spiral(), config=SMALL, seed=4, dtype=torch.float32)
    check = export.verify(onnx64, other, samples=500)
    # THEN the check fails
    assert not check.passed and check.max_error > 1e-3


def test_float64_onnx_of_a_leaky_relu_network(tmp_path: Path) -> None:
    # onnxruntime has no float64 LeakyRelu kernel: the export writes max(u, slope u) there
    config = PolicyConfig(**{**SMALL.to_dict(), "activation": "leaky_relu"})
    policy = make_policy(shifted_spiral(), config=config, seed=6, dtype=torch.float32).eval()
    path = export.export_onnx(policy, tmp_path / "leaky.onnx", dtype=torch.float64)
    check = export.verify(path, policy, samples=2_000)
    # (the fused graph sums in another order than the library: 3e-12 measured, 1000 extents
    # out, where the Fourier angles reach 1e5 rad)
    assert check.passed and check.max_error <= 1e-10


def test_onnx_runtime_paths_compute_one_function(policy, onnx64, monkeypatch) -> None:
    # GIVEN the one-state path (bound buffers) and the threaded batch path of load_onnx
    monkeypatch.setattr(export, "MIN_ROWS_PER_THREAD", 100)
    x = export.random_states(policy, 1_001, seed=5)
    plain = export.load_onnx(onnx64)
    reference = plain.session.run(None, {plain.input_name: x})[0]
    threaded = export.load_onnx(onnx64, threads=3)
    # THEN a batch split over three threads (of unequal chunks) is the whole batch's result
    np.testing.assert_array_equal(threaded(x), reference)
    # and single states through the reused buffers are each their own row, not the last one
    for i in (0, 7, 0, 1_000):
        single = plain(x[i : i + 1])
        assert single.shape == (1, 2)
        np.testing.assert_array_equal(single, reference[i : i + 1])
    held = plain(x[3:4])
    plain(x[4:5])
    np.testing.assert_array_equal(held, reference[3:4])  # a copy, not the bound buffer
    with pytest.raises(export.ExportError, match="threads"):
        export.load_onnx(onnx64, threads=0)


def test_float32_onnx_agrees_to_float32_rounding(policy, tmp_path: Path) -> None:
    path = export.export_onnx(policy, tmp_path / "p32.onnx", dtype=torch.float32)
    check = export.verify(path, policy, samples=10_000)
    assert check.dtype == "float32" and check.passed
    assert check.max_error <= export.TOLERANCE[torch.float32]
    # Held to no tolerance against the float32 library, it still passes by being as close
    # to the exact policy as that library is; another policy's export does not.
    strict = export.verify(path, policy, samples=2_000, tolerance=1e-12)
    assert strict.max_error > 1e-12 and strict.passed
    assert strict.max_error_float64 <= export.ROUNDING_SLACK * strict.library_error
    other = make_policy(shifted_spiral(), config=SMALL, seed=4, dtype=torch.float32)
    wrong = export.verify(path, other, samples=2_000, tolerance=1e-12)
    assert not wrong.passed and wrong.max_error_float64 > 1e-3


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_onnx_equals_the_library_in_its_own_precision(tmp_path: Path, dtype) -> None:
    # GIVEN the compact architecture (what a batch controller exports), exported in a dtype
    compact = RECIPES["compact"].policy
    config = replace(SMALL, hidden=compact.hidden, fourier_features=compact.fourier_features)
    policy = make_policy(shifted_spiral(), config=config, seed=5, dtype=torch.float32).eval()
    path = export.export_onnx(policy, tmp_path / "policy.onnx", dtype=dtype)
    # WHEN it is checked on 10,000 states against the library in float64 and in its dtype
    check = export.verify(path, policy, samples=10_000, seed=7)
    # THEN it agrees with the library in its own precision within the tolerance, and is no
    # further from the exact (float64) policy than that plus the library's own rounding
    assert check.passed and check.max_error <= export.TOLERANCE[dtype]
    assert check.max_error_float64 <= check.max_error + check.library_error + 1e-12
    if dtype == torch.float64:
        assert check.max_error <= 1e-9 and check.library_error == 0.0
    else:
        assert 0.0 < check.library_error < 1e-3


def test_onnx_graph_has_no_product_with_a_vector(policy, onnx64) -> None:
    # onnxruntime's MatMul with a 1-D operand is a slow path: export writes matrix products
    import onnx

    model = onnx.load(str(onnx64))
    ranks = {i.name: len(i.dims) for i in model.graph.initializer}
    for node in model.graph.node:
        if node.op_type == "MatMul":
            assert all(ranks.get(name, 2) != 1 for name in node.input), node


@pytest.mark.parametrize("dim", [2, 3])
def test_pt2_round_trip_is_exact_and_pickle_free(tmp_path: Path, dim: int) -> None:
    demos = spiral_demos(dim=dim)
    policy = make_policy(demos, config=SMALL, dtype=torch.float64).eval()
    path = export.export_pt2(policy, tmp_path / "policy.pt2", dtype=torch.float64)
    assert export.refused_entries(path) == []
    check = export.verify(path, policy, samples=2_000)
    # (the fused graph sums in another order than the library: 3e-12 measured)
    assert check.passed and check.max_error <= 1e-10
    # a single state (batch of one) runs through the dynamic batch dimension
    run = export.load_pt2(path)
    x = export.random_states(policy, 1, seed=2)
    with torch.no_grad():
        np.testing.assert_allclose(run(x), policy(torch.as_tensor(x)).numpy(), rtol=1e-12)


def test_lyapunov_with_the_target_values_given_is_the_same() -> None:
    # GIVEN a convex V, and g(0) and grad g(0) computed once, as the export does
    config = PolicyConfig(**{**SMALL.to_dict(), "warp_layers": 0})
    policy = make_policy(shifted_spiral(), config=config, seed=3, dtype=torch.float32)
    lyapunov = copy.deepcopy(policy.lyapunov).to(torch.float64)
    x = torch.as_tensor(export.random_states(policy, 1_000, seed=5) - 100.0).reshape(10, 100, 2)
    g0, grad_g0 = lyapunov.icnn.value_and_grad(torch.zeros(1, 2, dtype=torch.float64))
    # THEN V and its gradient are those of the usual call, for any batch shape
    v, grad = lyapunov.value_and_grad(x)
    v_given, grad_given = lyapunov.value_and_grad(x, at_target=(g0[0], grad_g0[0]))
    torch.testing.assert_close(v_given, v, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(grad_given, grad, rtol=1e-12, atol=1e-12)


def test_unconstrained_policy_exports_too(tmp_path: Path) -> None:
    config = PolicyConfig(**{**SMALL.to_dict(), "stable": False})
    policy = make_policy(shifted_spiral(), config=config, dtype=torch.float64).eval()
    path = export.export_pt2(policy, tmp_path / "bc.pt2", dtype=torch.float64)
    check = export.verify(path, policy, samples=2_000)
    assert check.passed and check.max_error <= 1e-12


def _rewritten(good: Path, bad: Path, change) -> Path:
    """A copy of the archive ``good`` whose entries pass through ``change(name, data)``, which
    returns the (name, data) pairs to write instead (none: the entry is dropped)."""
    with zipfile.ZipFile(good) as source, zipfile.ZipFile(bad, "w") as target:
        for item in source.infolist():
            for name, data in change(item.filename, source.read(item)):
                target.writestr(name, data)
    return bad


@pytest.fixture(scope="module")
def good_pt2(tmp_path_factory) -> Path:
    policy = make_policy(spiral_demos(), config=SMALL).eval()
    return export.export_pt2(policy, tmp_path_factory.mktemp("pt2") / "good.pt2")


def test_pt2_with_a_pickled_entry_is_refused(good_pt2: Path, tmp_path: Path) -> None:
    def pickle_inputs(name, data):
        yield name, b"\x80\x04pickled" if name.endswith("sample_inputs/model.pt") else data

    bad = _rewritten(good_pt2, tmp_path / "bad.pt2", pickle_inputs)
    assert export.refused_entries(bad) == ["archive/data/sample_inputs/model.pt"]
    with pytest.raises(export.ExportError, match="sample_inputs/model.pt.*refused"):
        export.load_pt2(bad)


def _config_change(edit):
    """A change of the archive's weights config by ``edit(entry)`` for every tensor."""

    def change(name, data):
        if name.endswith("_weights_config.json"):
            config = json.loads(data)
            for entry in config["config"].values():
                edit(entry)
            data = json.dumps(config).encode()
        yield name, data

    return change


@pytest.mark.parametrize(
    ("case", "change", "refused"),
    [
        # a tensor stored pickled
        (
            "pickled tensor",
            _config_change(lambda entry: entry.update(use_pickle=True)),
            "model_weights_config.json:",
        ),
        # a layout whose config no longer says how tensors are stored: refused, not read
        (
            "no use_pickle key",
            _config_change(lambda entry: entry.pop("use_pickle")),
            "model_weights_config.json:",
        ),
        # an entry of a kind an snds export does not write
        (
            "unknown entry",
            lambda name, data: (
                [(name, data)]
                + ([("archive/data/extra/blob.pkl", b"x")] if name.endswith("byteorder") else [])
            ),
            "archive/data/extra/blob.pkl",
        ),
        # raw bytes that no config names
        (
            "unnamed tensor bytes",
            lambda name, data: (
                [(name, data)]
                + (
                    [("archive/data/weights/weight_999", b"\0" * 8)]
                    if name.endswith("byteorder")
                    else []
                )
            ),
            "archive/data/weights/weight_999",
        ),
    ],
)
def test_pt2_with_anything_an_export_does_not_write_is_refused(
    good_pt2: Path, tmp_path: Path, case: str, change, refused: str
) -> None:
    # GIVEN the archive of an snds export, changed in one way torch.export could store pickles
    # or a future layout could differ
    assert export.refused_entries(good_pt2) == []
    bad = _rewritten(good_pt2, tmp_path / "bad.pt2", change)
    # THEN the check names the entry and loading refuses the file before torch reads it
    assert any(refused in entry for entry in export.refused_entries(bad)), case
    with pytest.raises(export.ExportError, match="refused"):
        export.load_pt2(bad)


def test_a_file_that_is_not_an_archive_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "policy.pt2"
    path.write_bytes(b"not a zip")
    with pytest.raises(export.ExportError, match="not a .pt2 archive"):
        export.load_pt2(path)


def test_cli_export_writes_the_file_and_its_check(tmp_path: Path, capsys) -> None:
    policy = make_policy(spiral_demos(), config=SMALL, dtype=torch.float32)
    save_model(policy, tmp_path / "model")
    code = main(["export", str(tmp_path / "model"), "--format", "pt2", "--samples", "1000"])
    assert code == 0
    check = json.loads((tmp_path / "model" / "policy.pt2.check.json").read_text())
    assert check["passed"] and check["samples"] == 1000
    out = capsys.readouterr().out
    assert "largest difference" in out and "in the data's box" in out


def test_cli_export_bad_model_dirs_exit_2(tmp_path: Path, capsys) -> None:
    assert main(["export", str(tmp_path / "missing")]) == 2
    (tmp_path / "broken").mkdir()
    (tmp_path / "broken" / "model.json").write_text("{not json")
    assert main(["export", str(tmp_path / "broken"), "--format", "pt2"]) == 2
    err = capsys.readouterr().err
    assert err.count("snds: error:") == 2 and "Traceback" not in err


def test_control_loop_example_drives_a_point_to_the_target(onnx64, capsys) -> None:
    # GIVEN the example loop on a simulated clock, at 200 Hz for 40 s of task time
    saved = sys.argv
    sys.argv = [str(EXAMPLE), str(onnx64), "--rate", "200", "--seconds", "40", "--no-sleep"]
    try:
        module = runpy.run_path(str(EXAMPLE), run_name="example")
        summary = module["main"](sys.argv[1:])
    finally:
        sys.argv = saved
    # THEN the point ends near the target, from one extent away
    assert summary["ticks"] == 8000
    assert summary["final_distance"] < 1e-3 * summary["start_distance"]
    assert "missed deadlines" in capsys.readouterr().out


# --- SE(3) pose policies: the exported graph maps poses to twists -------------------------


@pytest.fixture(scope="module")
def pose_policy():
    """An untrained pose policy whose target pose is off the origin and not the identity."""
    base = shifted_spiral()
    demos = with_synthetic_orientations(
        Demonstrations(base.demos, base.target, "spiral"), target_orientation=(0.0, 0.6, 0.0, 0.8)
    )
    policy = make_pose_policy(demos, config=SMALL, seed=3)
    return policy.eval()


@pytest.fixture(scope="module")
def pose_onnx64(pose_policy, tmp_path_factory) -> Path:
    return export.export_onnx(
        pose_policy, tmp_path_factory.mktemp("pose") / "pose.onnx", dtype=torch.float64
    )


def test_random_poses_span_so3_and_reach_far(pose_policy) -> None:
    x = export.random_states(pose_policy, 10_000, seed=0)
    config = pose_policy.config
    offset = np.abs(x[:, :3] - config.target_position).max(axis=1) / config.position_scale
    angles = 2 * np.arccos(np.clip(np.abs(x[:, 3:] @ config.target_orientation), 0, 1))
    assert x.shape == (10_000, 7)
    np.testing.assert_allclose(np.linalg.norm(x[:, 3:], axis=1), 1.0, atol=1e-12)
    assert offset.min() < 0.2 and offset.max() > 900
    assert (offset <= 1).mean() > 0.15  # a fair share near the data
    # uniform on SO(3): angles from the target up to pi, mean pi/2 + 2/pi (Haar measure)
    assert angles.max() > np.pi - 0.05
    assert angles.mean() == pytest.approx(np.pi / 2 + 2 / np.pi, abs=0.03)


def test_float64_pose_onnx_equals_the_library(pose_policy, pose_onnx64) -> None:
    # GIVEN the float64 ONNX export of a pose policy, run by onnxruntime
    run = export.load_onnx(pose_onnx64)
    x = export.random_states(pose_policy, 10_000, seed=1)
    # WHEN it and the library's twist see the same 10,000 random poses
    exported = run(x)
    with torch.no_grad():
        library = copy.deepcopy(pose_policy).double()(torch.as_tensor(x))
    # THEN the twists agree to rounding, linear and angular blocks alike, one pose at a
    # time (bound buffers of 7 in, 6 out) too
    assert exported.shape == (10_000, 6)
    # (a batch of one takes other matrix kernels than one of 10,000: rounding, not bits)
    np.testing.assert_allclose(run(x[5:6]), exported[5:6], rtol=1e-13, atol=1e-13)
    np.testing.assert_allclose(exported, library.numpy(), rtol=1e-10, atol=1e-9)
    check = export.verify(pose_onnx64, pose_policy, samples=10_000)
    assert check.passed and check.max_error <= 1e-9


def test_pose_onnx_is_blind_to_the_quaternion_sign(pose_policy, pose_onnx64) -> None:
    # the graph takes the log map itself: q and -q are one orientation, one twist
    run = export.load_onnx(pose_onnx64)
    x = export.random_states(pose_policy, 2_000, seed=2)
    flipped = np.concatenate([x[:, :3], -x[:, 3:]], axis=1)
    np.testing.assert_allclose(run(flipped), run(x), rtol=1e-10, atol=1e-10)


def test_pose_onnx_metadata_says_pose_in_twist_out(pose_policy, pose_onnx64) -> None:
    import onnx

    meta = {p.key: p.value for p in onnx.load(str(pose_onnx64)).metadata_props}
    target = json.loads(meta["snds.target"])
    np.testing.assert_allclose(target[:3], [100.0, -50.0, 0.0])
    np.testing.assert_allclose(target[3:], [0.0, 0.6, 0.0, 0.8])
    assert meta["snds.input"].startswith("pose") and meta["snds.output"].startswith("twist")
    assert float(meta["snds.extent"]) == pytest.approx(pose_policy.config.position_scale)


def test_float32_pose_onnx_passes_the_check(pose_policy, tmp_path: Path) -> None:
    path = export.export_onnx(pose_policy, tmp_path / "pose32.onnx", dtype=torch.float32)
    check = export.verify(path, pose_policy, samples=10_000)
    assert check.dtype == "float32" and check.passed
    assert check.max_error <= export.TOLERANCE[torch.float32]


def test_pose_pt2_round_trip_is_exact(pose_policy, tmp_path: Path) -> None:
    path = export.export_pt2(pose_policy, tmp_path / "pose.pt2", dtype=torch.float64)
    assert export.refused_entries(path) == []
    check = export.verify(path, pose_policy, samples=2_000)
    assert check.passed and check.max_error <= 1e-12


def test_verify_catches_a_pose_model_with_other_weights(pose_policy, pose_onnx64) -> None:
    other = copy.deepcopy(pose_policy)
    with torch.no_grad():
        for p in other.nominal_net.parameters():
            p.add_(0.1 * torch.randn_like(p))
    check = export.verify(pose_onnx64, other, samples=500)
    assert not check.passed and check.max_error > 1e-3


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_onnx_atan2_equals_torch_in_every_quadrant(tmp_path: Path, dtype) -> None:
    # GIVEN atan2 through the export's translation (onnxruntime has no float64 Atan)
    class Atan2(torch.nn.Module):
        def forward(self, x: torch.Tensor) -> torch.Tensor:
            return torch.atan2(x[:, 0], x[:, 1])

    rng = np.random.default_rng(0)
    special = [0.0, 1.0, -1.0, 1e-30, -1e-30, 1e30, -1e30]
    pairs = np.array([(a, b) for a in special for b in special])
    scales = 10.0 ** rng.uniform(-20, 20, size=(2_000, 1))
    x = np.concatenate([pairs, scales * rng.normal(size=(2_000, 2))]).astype(NUMPY_DTYPES[dtype])
    program = torch.export.export(
        Atan2(), (torch.as_tensor(x[:4]),), dynamic_shapes={"x": {0: torch.export.Dim("b")}}
    )
    with quiet_exporter():
        model = torch.onnx.export(
            program,
            dynamo=True,
            custom_translation_table={torch.ops.aten.atan2.default: onnx_ops.atan2},
        ).model_proto
    import onnx

    onnx.save(model, str(tmp_path / "atan2.onnx"))
    # WHEN it runs on pairs with zeros, signs, and magnitudes from 1e-30 to 1e30
    got = export.load_onnx(tmp_path / "atan2.onnx")(x)
    # THEN it is torch's atan2 to the precision's rounding
    expected = torch.atan2(torch.as_tensor(x[:, 0]), torch.as_tensor(x[:, 1])).numpy()
    ulp = 4e-16 if dtype == torch.float64 else 5e-7
    np.testing.assert_allclose(got, expected, rtol=0, atol=ulp * np.pi)


@pytest.mark.parametrize("fmt", ["onnx", "pt2"])
def test_cli_export_of_a_pose_model(pose_policy, tmp_path: Path, capsys, fmt: str) -> None:
    # A pose has more numbers than its position and no phase: ONNX once refused it as "a
    # model with a phase, but model.json records no phase" (issue 39).
    save_model(pose_policy, tmp_path / "pose")
    code = main(["export", str(tmp_path / "pose"), "--format", fmt, "--samples", "1000"])
    assert code == 0
    check = json.loads((tmp_path / "pose" / f"policy.{fmt}.check.json").read_text())
    assert check["passed"] and check["samples"] == 1000
    out = capsys.readouterr().out
    assert "(B, 7) pose (x, y, z" in out and "(B, 6) twist (vx" in out
    # the differences in the data's box and far out, apart and labelled
    assert "in the data's box" in out and "beyond it, out to 1000x the extent" in out
    assert check["max_abs_diff_near"] <= check["max_abs_diff"]


def _io_names(path: Path) -> list[tuple[str, str]]:
    import onnx

    graph = onnx.load(str(path)).graph
    return [
        (value.name, value.type.tensor_type.shape.dim[0].dim_param)
        for value in [*graph.input, *graph.output]
    ]


def test_onnx_names_its_state_output_and_batch(policy, onnx64, pose_onnx64) -> None:
    assert _io_names(onnx64) == [("state", "batch"), ("velocity", "batch")]
    assert _io_names(pose_onnx64) == [("state", "batch"), ("twist", "batch")]


def _warped_policy():
    # 48 features per layer: an amplitude sqrt(2/48) that float32 does not hold exactly
    config = PolicyConfig(**{**SMALL.to_dict(), "warp_layers": 3, "warp_features": 48})
    policy = make_policy(shifted_spiral(), config=config, seed=6, dtype=torch.float64).eval()
    with torch.no_grad():  # a warp away from the identity, as after training
        for p in policy.lyapunov.warp.parameters():
            p.add_(torch.randn_like(p))
    return policy


@pytest.mark.parametrize("fmt", ["onnx", "pt2"])
def test_a_warped_policy_exports_exactly(tmp_path: Path, fmt: str) -> None:
    policy = _warped_policy()
    write = export.export_onnx if fmt == "onnx" else export.export_pt2
    path = write(policy, tmp_path / f"warped.{fmt}", dtype=torch.float64)
    check = export.verify(path, policy, samples=2_000)
    # (3e-11 measured: 1000 extents out, the Fourier angles reach 1e5 rad, whose last bit
    # differs between the two runtimes' matrix products)
    assert check.passed and check.max_error <= 1e-9


def _default_policy(dim: int = 2):
    """The default architecture (warped V, 4 coupling layers), its warp and V moved away from
    their initial values as training would."""
    demos = shifted_spiral() if dim == 2 else spiral_demos(dim=dim)
    policy = _anchored(make_policy(demos, config=PolicyConfig(), seed=2), demos).eval()
    with torch.no_grad():
        for p in policy.lyapunov.warp.parameters():
            p.add_(0.05 * torch.randn_like(p))
    return policy


@pytest.mark.parametrize("dim", [2, 3])
def test_default_policy_exports_as_the_fused_graph(tmp_path: Path, dim: int) -> None:
    # GIVEN the default architecture, exported in float64 and in float32
    import onnx

    policy = _default_policy(dim)
    assert fusable(policy)
    exact = export.export_onnx(policy, tmp_path / "p64.onnx", dtype=torch.float64)
    rounded = export.export_onnx(policy, tmp_path / "p32.onnx", dtype=torch.float32)
    # THEN the float64 graph is the library to 1e-9 of the top speed on 4,000 states out to
    # 1000 extents (rounding of 1e5-rad Fourier angles: about 2e-11 measured)
    check = export.verify(exact, policy, samples=4_000, seed=3)
    assert check.passed and check.max_error <= 1e-9
    # and the float32 graph is no farther from the exact policy than the float32 library
    # (times ROUNDING_SLACK)
    check = export.verify(rounded, policy, samples=4_000, seed=3)
    assert check.passed
    assert check.max_error_float64 <= export.ROUNDING_SLACK * check.library_error
    # and it is the fused graph: 109 nodes with 4 coupling layers (the library's own code
    # gave 168 with 6, the fused graph 130 with 6 and 114 with 4 before the dot products with
    # a row became products with a column)
    assert len(onnx.load(str(rounded)).graph.node) <= 110


@pytest.mark.parametrize("fmt", ["onnx", "pt2"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_exported_field_is_zero_at_the_target(tmp_path: Path, fmt: str, dtype) -> None:
    # GIVEN the default policy's export, and the target (off the origin, at (100, -50))
    policy = _default_policy()
    write, load = (
        (export.export_onnx, export.load_onnx)
        if fmt == "onnx"
        else (export.export_pt2, export.load_pt2)
    )
    run = load(write(policy, tmp_path / f"p.{fmt}", dtype=dtype))
    target = np.asarray(policy.normalization.center, dtype=np.float64)[None]
    # THEN V is 0 there, and the exported velocity is exactly 0, in a batch too
    with torch.no_grad():
        value, _ = policy_copy(policy, torch.float64).lyapunov.value_and_grad(
            torch.zeros(1, 2, dtype=torch.float64)
        )
    assert float(value[0]) == 0.0
    np.testing.assert_array_equal(run(target), np.zeros((1, 2)))
    batch = np.concatenate([export.random_states(policy, 7, seed=1), target])
    assert np.all(run(batch)[-1] == 0.0) and np.all(run(batch)[:-1] != 0.0)
    # and one extent in 1e6 from it the velocity is of that order (top speed: about 1)
    near = target + 1e-6 * policy.normalization.length
    speed = np.linalg.norm(run(near)) / top_speed(policy)
    assert speed < 1e-3
