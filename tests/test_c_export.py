"""The C export (snds.export.c): compiled by the system's gcc as strict C99, it computes what
the library computes, for positions, poses and a phase, and its guarded step is the library's."""

from __future__ import annotations

import copy
import json
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch

import snds
from snds import export
from snds.cli import main
from snds.data import Demonstration, Demonstrations
from snds.data.demonstrations import no_split
from snds.data.poses import with_synthetic_orientations
from snds.export import c as c_export
from snds.export import c_check
from snds.models import save_model
from snds.phase import Phase, start_rule
from snds.rollout import policy_guard, safe_velocity
from snds.se3 import make_pose_policy

from conftest import SMALL, spiral_demos

if c_check.compiler() is None:
    pytest.skip("no C compiler (gcc or cc) to build the C export", allow_module_level=True)

#: The double build against the library in float64, relative to max(|velocity|, top speed),
#: at every distance out to 1000 extents; or, where larger, twice the library's disagreement
#: with itself between a batch and single states (its matrix kernel sums in another order).
DOUBLE = 1e-12


def _train(policy, demos, **options):
    torch.manual_seed(0)
    snds.fit(
        policy,
        demos,
        no_split(demos),
        snds.TrainConfig(steps=60, seed=0, **options),
        progress=False,
    )
    return policy.eval()


def _shifted(dim: int, scale: float, shift) -> Demonstrations:
    base = spiral_demos(dim=dim)
    moved = tuple(
        Demonstration(d.positions * scale + shift, d.velocities * scale, d.times) for d in base
    )
    return Demonstrations(moved, base.target * scale + np.asarray(shift), "spiral")


@pytest.fixture(scope="module")
def models():
    """Tiny trained models: positions (warped V, anchors), a phase, a pose; float32."""
    positions = _shifted(2, 1.0, [100.0, -50.0])
    plain = _train(snds.make_policy(positions, config=SMALL), positions)
    phased = Phase(codes=3).apply(spiral_demos())
    phase = _train(snds.make_policy(phased, config=SMALL), phased)
    poses = with_synthetic_orientations(
        _shifted(3, 0.05, [0.4, -0.1, 0.3]), target_orientation=(0.0, 0.6, 0.0, 0.8)
    )
    pose = _train(
        make_pose_policy(poses, config=SMALL, seed=0),
        poses,
        position_noise=0.0,
        noise_correction=0.0,
        align_weight=0.0,
    )
    return {"positions": plain, "phase": phase, "pose": pose}


@pytest.fixture(scope="module")
def compiled(models, tmp_path_factory):
    folder = tmp_path_factory.mktemp("c")
    out = {}
    for name, policy in models.items():
        header = c_export.export_c(policy, folder / f"{name}.h", prefix=f"p_{name}")
        out[name] = (
            header,
            c_check.load_c(header, policy, folder / f"{name}.so", prefix=f"p_{name}"),
        )
    return out


@pytest.mark.parametrize("name", ["positions", "phase", "pose"])
def test_double_equals_the_library_to_1e_12_out_to_1000_extents(models, compiled, name):
    # GIVEN a trained model's C export and 10,000 random states, from the data to 1000x its
    # extent (poses: orientations uniform on SO(3))
    policy, (_, lib) = models[name], compiled[name]
    states = export.random_states(policy, 5_000, seed=1)
    check = export.compare(
        lambda x: lib.policy(x), policy, path="c", dtype=torch.float64, samples=5_000, seed=1
    )
    # THEN the double build is the library in float64 to 1e-12 of max(|v|, top speed) at
    # every distance, or within twice the library's own batch-versus-single rounding
    assert check.max_error_near <= DOUBLE, check
    kind = export.signature(policy)
    far = states[kind.extents(states) > 100]
    with torch.no_grad():
        batch = kind.library(torch.as_tensor(far)).numpy()
        single = np.concatenate([kind.library(torch.as_tensor(s[None])).numpy() for s in far])
    top_speed = policy.normalization.length / policy.normalization.time
    scale = np.maximum(np.linalg.norm(batch / kind.output_scale(), axis=-1), top_speed)
    itself = np.max(np.linalg.norm((batch - single) / kind.output_scale(), axis=-1) / scale)
    assert check.max_error <= max(DOUBLE, 2 * itself), (check, itself)
    assert np.isfinite(lib.policy(states)).all()


@pytest.mark.parametrize("name", ["positions", "phase", "pose"])
def test_float_is_as_close_to_the_exact_policy_as_the_float32_library(models, compiled, name):
    _, lib = compiled[name]
    single = export.compare(
        lambda x: lib.policy(x, np.float32),
        models[name],
        path="c",
        dtype=torch.float32,
        samples=5_000,
        seed=2,
        tolerance=c_check.FLOAT_TOLERANCE,
    )
    # The stated bound: 3e-4 of max(|v|, top speed) against the float32 library, or no
    # farther from the float64 policy than 2x the float32 library itself.
    assert single.passed and single.dtype == "float32", single
    assert single.max_error_float64 <= max(3e-4, 2 * single.library_error)


@pytest.mark.parametrize("name", ["positions", "phase", "pose"])
@pytest.mark.parametrize("limit", [None, 0.3])
def test_guarded_step_is_the_librarys_and_keeps_the_speed_limit(models, compiled, name, limit):
    # GIVEN states from the data to 100 extents, a period of 20 ms, and a limit of 0.3 of
    # the top speed (or none)
    policy, (_, lib) = models[name], compiled[name]
    exact = copy.deepcopy(policy).double()
    top = float(exact.length / exact.time * exact.chart_scales()[0])
    max_speed = None if limit is None else limit * top
    x = export.random_states(policy, 1_000, seed=3)
    x = x[export.signature(policy).extents(x) <= 100]
    # WHEN the C step and the library's safe_velocity take them
    command, h, reached = lib.step(x, 0.02, max_speed or 0.0)
    reference, h_ref = safe_velocity(exact, torch.as_tensor(x), 0.02, max_speed=max_speed)
    # THEN the steps are the same halvings, the commands the same to rounding
    np.testing.assert_array_equal(h, h_ref.numpy())
    scale = np.maximum(np.linalg.norm(reference.numpy(), axis=1), top)[:, None]
    assert np.abs(command - reference.numpy()).max() <= 1e-11 * scale.max()
    assert np.all(np.abs(command - reference.numpy()) <= 1e-11 * scale)
    # and V falls along every step; under the limit no position moves faster than it
    lyapunov, _ = policy_guard(exact)
    with torch.no_grad():
        before = lyapunov(torch.as_tensor(x)).numpy()
        after = lyapunov(torch.as_tensor(reached)).numpy()
    assert np.all((after < before) | (before == 0))
    np.testing.assert_allclose(lib.lyapunov(x), before, rtol=1e-11, atol=1e-300)
    if max_speed is not None:
        speeds = np.linalg.norm(command[:, : policy.space.position_dim], axis=1)
        assert speeds.max() <= max_speed * (1 + 1e-12)


def test_compiled_controller_reaches_the_target_from_3_extents(models, compiled):
    # GIVEN the position model's C step in a 200 Hz loop of an ideal integrator, from starts
    # 3 extents away, under a speed limit of the top speed
    policy, (_, lib) = models["positions"], compiled["positions"]
    rng = np.random.default_rng(0)
    extent = float(policy.normalization.length)
    x = policy.target + rng.uniform(-3, 3, (4, 2)) * extent
    top = float(policy.length / policy.time)
    peak = 0.0
    for _ in range(6_000):  # 30 s at 200 Hz
        command, _, _ = lib.step(x, 0.005, top)
        peak = max(peak, float(np.linalg.norm(command, axis=1).max()))
        x = x + 0.005 * command
    # THEN every start arrives within 1 % of the extent, never faster than the limit
    assert np.linalg.norm(x - policy.target, axis=1).max() <= 0.01 * extent
    assert peak <= top * (1 + 1e-12)


def test_exactly_at_the_target_the_velocity_is_zero(models, compiled):
    for name in ("positions", "phase"):
        _, lib = compiled[name]
        target = models[name].target[None]
        np.testing.assert_array_equal(lib.policy(target), 0.0)
        assert lib.lyapunov(target)[0] == 0.0
    # A pose's log map at the target rounds to about 1e-17 rad, not 0, and the projection
    # amplifies rounding there: the C twist and the library's are both rounding noise
    # (measured 6e-8 and 2e-8 of the top speed)
    policy, (_, lib) = models["pose"], compiled["pose"]
    with torch.no_grad():
        library = copy.deepcopy(policy).double()(torch.as_tensor(policy.target[None])).numpy()
    top = float(policy.length / policy.time * policy.chart_scales()[0])
    assert np.abs(lib.policy(policy.target[None])).max() <= 1e-6 * top
    assert np.abs(library).max() <= 1e-6 * top


def test_the_files_are_c99_with_math_h_only_and_no_mutable_state(compiled):
    header, _ = compiled["pose"]
    source = header.with_suffix(".c").read_text()
    includes = [line for line in source.splitlines() if line.startswith("#include")]
    assert includes == ["#include <math.h>", "#include <stddef.h>", '#include "pose.h"']
    assert "malloc" not in source and "alloca" not in source
    # every file-scope variable is a static const array
    globals_ = [
        line
        for line in source.splitlines()
        if line.startswith("static ") and "[" in line and "(" not in line
    ]
    assert globals_ and all(g.startswith("static const ") for g in globals_)
    text = header.read_text()
    assert "#define P_POSE_STATE_DIM 7" in text and "#define P_POSE_VELOCITY_DIM 6" in text


def test_cli_export_c_checks_and_reports(models, tmp_path, capsys):
    save_model(models["pose"], tmp_path / "pose")
    code = main(
        [
            "export",
            str(tmp_path / "pose"),
            "--format",
            "c",
            "--samples",
            "2000",
            "--max-speed",
            "0.5",
            "--rate",
            "1000",
        ]
    )
    assert code == 0
    checks = json.loads((tmp_path / "pose" / "policy.h.check.json").read_text())
    assert [c["dtype"] for c in checks] == ["float64", "float32"]
    assert all(c["passed"] for c in checks)
    header = (tmp_path / "pose" / "policy.h").read_text()
    assert "#define SNDS_MAX_SPEED 0.5" in header and "#define SNDS_DT 0.001" in header
    out = capsys.readouterr().out
    assert "in the data's box" in out and "beyond it" in out
    # a C-only option on another format, and a bad limit: one line, exit 2
    assert main(["export", str(tmp_path / "pose"), "--max-speed", "1"]) == 2
    assert main(["export", str(tmp_path / "pose"), "--format", "c", "--max-speed", "-1"]) == 2
    err = capsys.readouterr().err
    assert err.count("snds: error:") == 2 and "Traceback" not in err


def test_unsupported_policies_are_refused_in_one_line(models, tmp_path):
    bc = copy.deepcopy(models["positions"])
    bc.config = type(bc.config)(**{**bc.config.to_dict(), "stable": False})
    with pytest.raises(c_export.CExportError, match="Lyapunov"):
        c_export.export_c(bc, tmp_path / "bc.h")
    with pytest.raises(c_export.CExportError, match="identifier"):
        c_export.export_c(models["positions"], tmp_path / "p.h", prefix="1bad")


def test_a_phase_model_gives_a_new_start_its_phase_as_the_library(models, tmp_path):
    # GIVEN the phase model's export with the library's start rule
    import ctypes

    from snds.phase import start_rule, start_state

    policy = models["phase"]
    demos = Phase(codes=3).apply(spiral_demos())
    rule = start_rule(demos)
    header = c_export.export_c(policy, tmp_path / "phase.h", start_rule=rule)
    assert f"#define SNDS_START_COUNT {len(rule.references)}" in header.read_text()
    library = c_check.compile_shared(header, tmp_path / "phase.so")
    function = ctypes.CDLL(str(library)).snds_start_state
    pointer = ctypes.POINTER(ctypes.c_double)
    function.argtypes = [pointer, pointer]
    # WHEN it starts beside demonstrated samples (within the reach and beyond) and far away
    rng = np.random.default_rng(0)
    samples = np.concatenate([d.states[::37, :2] for d in demos])
    offsets = rng.normal(size=samples.shape) * 0.04 * demos.extent()
    positions = [*(samples + offsets), np.array([50.0, -80.0])]
    phased = 0
    for position in positions:
        state = np.zeros(5)
        function(
            np.ascontiguousarray(position).ctypes.data_as(pointer), state.ctypes.data_as(pointer)
        )
        # THEN it is the library's start state
        np.testing.assert_array_equal(state, start_state(demos, position))
        phased += bool(np.any(state[2:]))
    # AND both branches were taken: a phase lent, and phase 0
    assert 0 < phased < len(positions)
    with pytest.raises(c_export.CExportError, match="phase"):
        c_export.export_c(models["positions"], tmp_path / "p.h", start_rule=rule)


@pytest.mark.parametrize("name", ["phase", "pose"])
def test_the_example_control_loop_compiles_runs_and_arrives(tmp_path, name):
    # GIVEN examples/c/control_loop.c built against the export of a model of motions lasting
    # 0.5 s (a phase model takes its start state from snds_start_state; a pose model's step
    # advances the quaternion)
    base = _shifted(3 if name == "pose" else 2, 1.0, [0.0] * (3 if name == "pose" else 2))
    fast = Demonstrations(
        tuple(Demonstration(d.positions, d.velocities * 32, d.times / 32) for d in base),
        base.target,
        "fast",
    )
    if name == "pose":
        demos = with_synthetic_orientations(fast, target_orientation=(0.0, 0.6, 0.0, 0.8))
        policy = _train(make_pose_policy(demos, config=SMALL, seed=0), demos, align_weight=0.0)
        rule = None
    else:
        demos = Phase(codes=3).apply(fast)
        policy = _train(snds.make_policy(demos, config=SMALL), demos)
        rule = start_rule(demos)
    header = c_export.export_c(policy, tmp_path / "policy.h", rate=1000.0, start_rule=rule)
    example = Path(__file__).resolve().parents[1] / "examples" / "c" / "control_loop.c"
    binary = tmp_path / "loop"
    subprocess.run(
        [
            c_check.compiler(),
            *c_check.CFLAGS,
            f"-I{tmp_path}",
            str(example),
            str(header.with_suffix(".c")),
            "-lm",
            "-o",
            str(binary),
        ],
        check=True,
        capture_output=True,
        text=True,
    )
    # WHEN it runs for 3 s at 1 kHz
    result = subprocess.run([str(binary), "3", "1000"], check=True, capture_output=True, text=True)
    report = json.loads(result.stdout)
    # THEN it reports its periods, and every run from 3 extents away arrived
    assert report["periods"] == 3000
    assert report["runs"] >= 1 and report["arrived"] == report["runs"], report
    assert 0 < report["median_arrival_s"] < 3
