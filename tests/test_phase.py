"""A phase in the state (snds.phase): the appended phase, its space, the guarantee in the joint
state, the phase that waits for a held arm, the record, the CLI and the simulated arm."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

import snds
from snds.cli import main
from snds.data import DataSource, Demonstration, Demonstrations, Normalization, no_split
from snds.errors import ConfigError, DataError
from snds.evaluate import evaluate
from snds.methods import make_policy
from snds.models import load_model, save_model
from snds.phase import (
    START_REFERENCES,
    Phase,
    PhaseKeeper,
    phase_step,
    start_rule,
    start_state,
    start_states,
)
from snds.rollout import rollout_numpy
from snds.spaces import SE3, Euclidean, Phased
from snds.stability import CheckConfig

from conftest import SMALL


@pytest.fixture(scope="module")
def phased(spiral):
    return Phase(codes=3, seed=4).apply(spiral)


def test_the_phase_runs_from_the_extent_along_the_code_to_zero(spiral, phased):
    extent = spiral.extent()
    codes = Phase(codes=3, seed=4).codebook(len(spiral))
    assert phased.dim == 5 and phased.position_dim == 2 and phased.phase_dim == 3
    np.testing.assert_array_equal(phased.target, np.zeros(5))
    for demo, plain, code in zip(phased, spiral, codes, strict=True):
        np.testing.assert_array_equal(demo.positions[:, :2], plain.positions)
        np.testing.assert_allclose(demo.positions[0, 2:], extent * code, rtol=1e-12)
        np.testing.assert_allclose(demo.positions[-1, 2:], 0.0, atol=1e-12)
        # The phase velocity is the phase's time derivative (it is linear in time).
        slope = np.diff(demo.positions[:, 2:], axis=0) / np.diff(demo.times)[:, None]
        np.testing.assert_allclose(slope, demo.velocities[1:, 2:], rtol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(codes, axis=1), 1.0)
    # The extent, top speed and positions are the positions' own: the phase adds no scale.
    assert phased.extent() == spiral.extent() and phased.max_speed() == spiral.max_speed()
    assert phased.positions().shape == spiral.positions().shape
    assert phased.select([1]).phase_dim == 3


def test_the_model_scales_the_whole_state_and_keeps_the_positions_extent(spiral, phased):
    # The phase is scaled with the positions (one length for the state the network sees),
    # while tolerances and scale-free figures stay fractions of the positions' extent.
    norm = Normalization.fit(phased)
    states = np.concatenate([d.states for d in phased])
    assert norm.length == pytest.approx(np.linalg.norm(states, axis=1).max())
    assert norm.extent == spiral.extent() < norm.length
    assert Normalization.from_dict(norm.to_dict()).to_dict() == norm.to_dict()
    old = {k: v for k, v in norm.to_dict().items() if k != "extent"}
    assert Normalization.from_dict(old).extent == norm.length  # a record before the phase
    policy = snds.make_policy(phased, config=SMALL)
    assert policy.extents()[0] == spiral.extent()
    plain = Normalization.fit(spiral)
    assert plain.length == plain.extent == spiral.extent()


def test_codes_are_seeded_and_one_code_is_a_shared_clock():
    a, b = Phase(codes=4, seed=1).codebook(5), Phase(codes=4, seed=1).codebook(5)
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, Phase(codes=4, seed=2).codebook(5))
    np.testing.assert_array_equal(a[:3], Phase(codes=4, seed=1).codebook(3))
    np.testing.assert_array_equal(Phase(codes=1).codebook(3), np.ones((3, 1)))


@pytest.mark.parametrize("codes", [0, 65, 2.0, True])
def test_bad_codes_are_refused(codes):
    with pytest.raises(ConfigError, match="codes"):
        Phase(codes=codes)


def test_a_phase_is_not_appended_twice(phased):
    with pytest.raises(DataError, match="phase already"):
        Phase().apply(phased)


def test_a_phase_follows_a_pose_and_runs_to_zero():
    # GIVEN Sine lifted to poses, with a phase of 2 numbers
    demos = DataSource(motion="Sine", demos=2, poses=True, phase=Phase(codes=2)).load()
    # THEN each state is the pose then the phase, which starts at the extent and ends at 0
    assert demos.phase_dim == 2 and demos.target.shape == (9,)
    np.testing.assert_array_equal(demos.target[7:], 0.0)
    for demo in demos:
        assert demo.states.shape[1] == 9 and demo.velocities.shape[1] == 8
        np.testing.assert_allclose(np.linalg.norm(demo.states[0, 7:]), demos.extent())
        np.testing.assert_allclose(demo.states[-1, 7:], 0.0, atol=1e-12)
        # The phase rate is the constant -extent / duration along the code
        rate = -demos.extent() / demo.duration * demo.states[0, 7:] / demos.extent()
        np.testing.assert_allclose(
            demo.velocities[:, 6:], np.broadcast_to(rate, (len(demo.times), 2))
        )
    # AND a pose policy built on them lives in SE(3) with the phase after the pose
    policy = make_policy(demos, config=SMALL)
    assert policy.space == Phased(SE3(), 2) and policy.dim == 8


def test_start_state_takes_the_nearest_samples_phase_beside_the_data_and_0_away(phased):
    # GIVEN a start a hair beside a sample in the middle of demonstration 1
    position = phased[1].states[300, :2] + 0.001 * phased.extent()
    state = start_state(phased, position)
    # THEN it takes the phase of the reference sample nearest to it (by brute force): up to
    # START_REFERENCES of each demonstration, evenly spaced
    samples = start_rule(phased).references
    assert len(samples) <= START_REFERENCES * len(phased)
    nearest = samples[np.argmin(np.linalg.norm(samples[:, :2] - position, axis=1))]
    np.testing.assert_array_equal(state, np.concatenate([position, nearest[2:]]))
    assert np.linalg.norm(state[2:]) > 0
    # AND a start further than the reach from every sample gets phase 0
    far = phased.target[:2] + 3.0 * phased.extent()
    np.testing.assert_array_equal(start_state(phased, far)[2:], 0.0)
    # AND many starts at once are the same as one at a time
    many = np.stack([position, far])
    np.testing.assert_array_equal(
        start_states(phased, many), np.stack([start_state(phased, x) for x in many])
    )
    with pytest.raises(DataError, match="shape"):
        start_state(phased, np.zeros(3))


def test_the_space_compares_positions_only():
    space = Phased(Euclidean(2), 3)
    assert space.position_dim == 2 and space.velocity_sizes == (2, 3)
    x = torch.tensor([[3.0, 4.0, 9.0, 9.0, 9.0]])
    assert space.errors(x, torch.zeros(5)).item() == pytest.approx(5.0)
    rng = np.random.default_rng(0)
    states = space.uniform(np.zeros(5), 2.0, 100, rng)
    assert states.shape == (100, 5) and np.abs(states).max() <= 2.0
    grid = space.grid(np.zeros(5), 1.0, 9, rng)
    assert grid.shape == (9, 5) and {tuple(r) for r in grid[:, :2]} >= {(-1.0, -1.0), (1.0, 1.0)}


def test_a_phased_pose_moves_on_so3_and_compares_the_pose_only():
    # GIVEN a pose with a phase of 2, and a twist turning about z with a phase rate
    space = Phased(SE3(), 2)
    assert (space.dim, space.tangent_dim, space.position_dim) == (9, 8, 3)
    assert space.velocity_names == ("velocity", "angular_velocity", "phase_rate")
    x = torch.tensor([[1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0, 2.0, -1.0]], dtype=torch.float64)
    v = torch.tensor([[0.5, 0.0, 0.0, 0.0, 0.0, np.pi, -1.0, 1.0]], dtype=torch.float64)
    # WHEN it advances half a second
    y = space.advance(x, torch.tensor([0.5], dtype=torch.float64), v)
    # THEN the position moves, the orientation turns a quarter turn on SO(3), the phase moves
    np.testing.assert_allclose(y[0, :3], [1.25, 0.0, 0.0])
    np.testing.assert_allclose(y[0, 3:7], [0.0, 0.0, np.sin(np.pi / 4), np.cos(np.pi / 4)])
    np.testing.assert_allclose(y[0, 7:], [1.5, -0.5])
    # AND the errors are the pose's (distance, angle), blind to the phase
    np.testing.assert_allclose(space.errors(y, x[0]), [[0.25, np.pi / 2]])
    states = space.uniform(np.asarray(x[0]), 2.0, 100, np.random.default_rng(0))
    assert states.shape == (100, 9)
    np.testing.assert_allclose(np.linalg.norm(states[:, 3:7], axis=1), 1.0)


def test_a_phase_keeper_starts_by_the_rule_and_waits_while_held(phased):
    # GIVEN a keeper with the demonstrations' start rule, and a measured position on the data
    keeper = PhaseKeeper(position_dim=2, start_rule=start_rule(phased))
    measured = phased[0].states[100, :2]
    # WHEN it takes its first state, a command, and the same position again (held)
    first = keeper.step(measured, 0.1)
    np.testing.assert_array_equal(first, start_state(phased, measured))
    keeper.command(np.array([1.0, 0.0, -2.0, 0.5, 0.0]))
    held = keeper.step(measured, 0.1)
    # THEN the phase waited; unhindered, it moves by the commanded rate
    np.testing.assert_array_equal(held, first)
    moved = keeper.step(measured + np.array([0.1, 0.0]), 0.1)
    np.testing.assert_allclose(moved[2:], first[2:] + 0.1 * np.array([-2.0, 0.5, 0.0]))
    # AND without a start or a rule there is no first state
    with pytest.raises(ConfigError, match="start"):
        PhaseKeeper(position_dim=2).step(measured, 0.1)


def test_phase_step_is_euler_unhindered_and_waits_when_held():
    state, velocity, h = np.array([1.0, 2.0, 3.0, -1.0]), np.array([2.0, 0.0, -4.0, 1.0]), 0.1
    euler = state + h * velocity
    np.testing.assert_allclose(phase_step(state, velocity, h, euler[:2], position_dim=2), euler)
    held = phase_step(state, velocity, h, state[:2], position_dim=2)
    np.testing.assert_array_equal(held, state)
    # Half the commanded displacement: half the phase step; backwards: none.
    half = phase_step(state, velocity, h, state[:2] + [0.1, 0.0], position_dim=2)
    np.testing.assert_allclose(half[2:], state[2:] + 0.5 * h * velocity[2:])
    back = phase_step(state, velocity, h, state[:2] - [0.1, 0.0], position_dim=2)
    np.testing.assert_array_equal(back[2:], state[2:])
    # Nothing commanded for the positions: the phase runs on.
    still = np.array([0.0, 0.0, -4.0, 1.0])
    ran = phase_step(state, still, h, state[:2], position_dim=2)
    np.testing.assert_allclose(ran, state + h * still)


def test_the_guarantee_holds_in_the_joint_state(phased):
    # GIVEN an untrained phased policy with scrambled weights, float64
    policy = snds.make_policy(phased, config=SMALL, seed=2).double()
    assert isinstance(policy.space, Phased) and policy.config.phase_dim == 3
    with torch.no_grad():
        for p in policy.parameters():
            p.add_(0.5 * torch.randn_like(p))
    # WHEN evaluated at random and far joint states
    x = torch.cat([torch.randn(5000, 5), 1e3 * torch.randn(5000, 5)]).double()
    v, grad_v = policy.lyapunov.value_and_grad(x)
    pi = policy.field(x)
    # THEN V > 0 away from the target, V(0) = 0 and V decreases at the promised rate
    slack = 1e-9 * (grad_v.norm(dim=-1) * policy.nominal(x).norm(dim=-1) + v)
    assert ((grad_v * pi).sum(-1) <= -policy.decay(v, x) + slack).all() and (v > 0).all()
    assert policy.lyapunov.value_and_grad(torch.zeros(1, 5).double())[0].item() == 0.0


@pytest.fixture(scope="module")
def trained(phased):
    policy = snds.make_policy(phased, config=SMALL, seed=0)
    snds.fit(policy, phased, no_split(phased), snds.TrainConfig(steps=300, seed=0))
    return policy


def test_a_trained_phased_policy_converges_and_is_measured_on_positions(trained, phased):
    check = CheckConfig(rollouts=100, samples=5000, seed=0)
    metrics = evaluate(trained.double(), phased, no_split(phased), check=check).to_dict()
    assert metrics["stability"]["converged_fraction"] == 1.0
    assert metrics["stability"]["decrease_violations"] == 0
    assert np.isfinite(metrics["dtw"]) and "phase_rate_mse" in metrics
    # Rollouts from the starts end at the target, the phase at 0 with them.
    starts = np.stack([d.states[0] for d in phased])
    ends = rollout_numpy(trained, starts, dt=0.05, steps=2000)[:, -1]
    np.testing.assert_allclose(ends, 0.0, atol=0.05 * phased.extent())


def test_save_and_load_keep_the_phase(trained, phased, tmp_path):
    source = DataSource(motion="Sine", demos=2, phase=Phase(codes=2, seed=3))
    save_model(trained, tmp_path, extra={"data": source.record()})
    loaded, description = load_model(tmp_path)
    assert loaded.space == trained.space == Phased(Euclidean(2), 3)
    x = torch.randn(50, 5, dtype=trained.center.dtype)
    torch.testing.assert_close(loaded(x), trained(x))
    again = DataSource.from_record(json.loads(json.dumps(description["data"])))
    assert again.phase == source.phase and again.load().phase_dim == 2


def test_cli_train_evaluate_plot_export_with_a_phase(tmp_path, capsys):
    out = tmp_path / "sine"
    fast = ["--steps", "150", "--rollouts", "50", "--samples", "2000"]
    argv = ["--quiet", "train", "--motion", "Sine", "--demos", "2", "--phase-codes", "2"]
    assert main([*argv, "--out", str(out), *fast]) == 0
    record = json.loads((out / "model.json").read_text())
    assert record["data"]["phase"] == {"codes": 2, "seed": 0}
    assert record["policy"]["phase_dim"] == 2 and record["dim"] == 4
    assert main(["--quiet", "evaluate", str(out), "--rollouts", "50", "--samples", "2000"]) == 0
    assert main(["--quiet", "plot", str(out), "--out", str(tmp_path / "plots")]) == 0
    # The streamlines are the field a new start begins with; V over the plane would hide the
    # phase.
    written = sorted(p.name for p in (tmp_path / "plots").iterdir())
    assert written == ["loss.png", "paths.png", "rollout_lyapunov.png", "streamlines.png"]
    # Obstacles are refused with one line, for every command that takes them.
    sphere = ["--obstacle", "sphere:-20,0,3"]
    assert main(["--quiet", "evaluate", str(out), *sphere]) == 2
    assert main(["--quiet", "export", str(out), *sphere, "--out", str(tmp_path / "o.onnx")]) == 2
    assert "phase" in capsys.readouterr().err and not (tmp_path / "o.onnx").exists()
    pytest.importorskip("onnxruntime", reason="the export needs the export extra")
    assert main(["--quiet", "export", str(out), "--out", str(tmp_path / "m.onnx")]) == 0
    # The file holds the starts a controller takes a new start's phase from, and its graph
    # gives the library's velocity and phase rate there.
    import onnx

    from snds.export import load_onnx

    meta = {p.key: p.value for p in onnx.load(str(tmp_path / "m.onnx")).metadata_props}
    demos = DataSource(motion="Sine", demos=2, phase=Phase(codes=2)).load()
    references = np.array(json.loads(meta["snds.start_references"]))
    rule = start_rule(demos)
    np.testing.assert_array_equal(references, rule.references)
    assert float(meta["snds.start_reach"]) == rule.reach
    state = start_state(demos, demos[0].states[100, :2] + 0.5)
    policy, _ = load_model(out)
    expected = policy.to(torch.float64).predict(state[None])
    np.testing.assert_allclose(
        load_onnx(tmp_path / "m.onnx")(state[None]),
        expected,
        rtol=1e-3,
        atol=1e-4 * np.abs(expected).max(),
    )


@pytest.mark.parametrize("codes", ["-1", "65", "x"])
def test_cli_bad_phase_codes_exit_2(codes, tmp_path, capsys):
    argv = ["--quiet", "train", "--motion", "Sine", "--phase-codes", codes]
    try:
        code = main([*argv, "--out", str(tmp_path / "m")])
    except SystemExit as exit_:
        code = exit_.code
    assert code == 2 and "Traceback" not in capsys.readouterr().err
    assert not (tmp_path / "m").exists()


def test_the_simulated_arm_keeps_the_phase_and_it_waits_while_held(trained, phased):
    from snds.sim.arm import EndEffector
    from snds.sim.robots import get_robot
    from snds.sim.run import PhasedCommander, SimConfig, make_commander

    model = trained.double().eval()
    rest = np.array([0.0, 0.0, 0.0, 1.0])
    commander = make_commander(model, get_robot("iiwa"), rest, SimConfig(robot="iiwa"))
    assert isinstance(commander, PhasedCommander)
    start = phased[0].states[0]
    position, _ = commander.start_pose(start)
    commander.twist(EndEffector(position, rest))
    first = commander.keeper.state.copy()
    np.testing.assert_allclose(first, start, atol=1e-9)
    # Held: the same measured position again, the phase does not move.
    commander.twist(EndEffector(position, rest))
    np.testing.assert_allclose(commander.keeper.state[2:], first[2:], atol=1e-12)
    # Moved as commanded: the phase moves by its own commanded step.
    velocity = commander.keeper.commanded
    dt = 1.0 / commander.config.control_rate
    moved = commander.placement.to_world(first[:2] + dt * velocity[:2])
    commander.twist(EndEffector(moved, rest))
    np.testing.assert_allclose(commander.keeper.state[2:], first[2:] + dt * velocity[2:], rtol=1e-6)
    with pytest.raises(snds.errors.SNDSError, match="shape"):
        commander.start_pose(start[:2])


def test_export_refuses_start_references_of_another_shape(trained, tmp_path):
    pytest.importorskip("onnx", reason="the export needs the export extra")
    from snds.export import ExportError, export_onnx
    from snds.phase import StartRule

    rule = StartRule(np.zeros((2, 4)), 1.0, phase_dim=3, position_dim=2)
    with pytest.raises(ExportError, match=r"shape \(K, 5\); got \(2, 4\)"):
        export_onnx(trained, tmp_path / "m.onnx", start_rule=rule)
    assert not (tmp_path / "m.onnx").exists()


def _loops(count: int = 3) -> Demonstrations:
    """Demonstrations of a loop that crosses itself, ending at 0."""
    rng = np.random.default_rng(0)
    t = np.linspace(0.0, 1.0, 300)
    s = (1.0 - np.cos(np.pi * t)) / 2.0
    turn = 2.0 * np.pi * s
    demos = []
    for _ in range(count):
        x = np.stack([3.0 * s + 1.2 * np.sin(turn), 1.2 * (1.0 - np.cos(turn))], -1)
        x = x * (1.0 + 0.05 * rng.normal())
        x = x - x[-1]
        demos.append(Demonstration(x, np.gradient(x, 4.0 * t, axis=0), 4.0 * t))
    return Demonstrations(tuple(demos), np.zeros(2), "loops")


def _share_pointing_back(policy, phased: Demonstrations) -> float:
    """The share of states pushed sideways off a demonstration (10 % of the extent, the
    phase kept) whose velocity turns back towards it, against the demonstrated one."""
    back = []
    for demo in phased:
        x, v = demo.states[10:-30:5], demo.velocities[10:-30:5, :2]
        side = np.stack([-v[:, 1], v[:, 0]], -1)
        side = side / np.linalg.norm(side, axis=1, keepdims=True)
        for sign in (1.0, -1.0):
            moved = x.copy()
            moved[:, :2] += sign * 0.1 * phased.extent() * side
            pi = policy(torch.as_tensor(moved)).detach().numpy()[:, :2]
            back.append(((pi - v) * (x[:, :2] - moved[:, :2])).sum(-1) > 0)
    return float(np.concatenate(back).mean())


def test_tracking_turns_pushed_states_back_onto_their_demonstration():
    # GIVEN a loop that crosses itself, with a phase, trained with and without tracking
    phased = Phase(codes=2).apply(_loops())
    shares = {}
    for gain in (3.0, 0.0):
        policy = snds.make_policy(phased, config=SMALL, seed=0)
        config = snds.TrainConfig(steps=400, seed=0, tracking_gain=gain)
        snds.fit(policy, phased, no_split(phased), config)
        shares[gain] = _share_pointing_back(policy.double(), phased)
    # THEN with tracking most pushed states head back to the path of their phase; without
    # it, off the data, about as many head away as back
    assert shares[3.0] >= 0.7
    assert shares[3.0] >= shares[0.0] + 0.15
