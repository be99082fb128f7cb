"""Simulated runs (PyBullet, headless): the arm reaches the target, recovers from a push,
respects its joint limits, and the CLI writes the record and the pictures."""

from __future__ import annotations

import json
from importlib import metadata
from pathlib import Path

import numpy as np
import pytest
import torch
from test_plotting import assert_png

from snds.arrival import PATH_TOLERANCE, distance_to_path
from snds.cli import main
from snds.models import save_model
from snds.policy import PolicyConfig
from snds.sim import Push, SimConfig, simulate
from snds.sim.placement import Placement, default_scale
from snds.sim.recovery import rest_of_path, unpushed_path
from snds.sim.robots import get_robot

from conftest import SMALL, make_policy, spiral_demos

pytest.importorskip("pybullet", reason="the simulation tests need the sim extra")

#: A small untrained policy whose guaranteed decay is fast enough for short runs.
FAST = PolicyConfig(**{**SMALL.to_dict(), "decay_rate": 2.0})


@pytest.fixture(autouse=True, scope="module")
def one_thread():
    # One torch thread, as in the CLI: a control loop evaluates one state at a time, and a
    # second thread only waits for a core at every operation, more so on a busy machine.
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def demos():
    return spiral_demos()


@pytest.fixture(scope="module")
def policy(demos):
    return make_policy(demos, config=FAST, seed=1).eval()


def push_away(robot: str, policy, start: np.ndarray, size: float) -> tuple[float, ...]:
    """A displacement of ``size`` metres from the target towards the start, in the plane."""
    placement = Placement.for_task(
        get_robot(robot), policy.normalization.center, default_scale(get_robot(robot), policy)
    )
    away = placement.to_world(start) - placement.origin
    return tuple(size * away / np.linalg.norm(away))


@pytest.fixture(scope="module")
def pushed_run(policy, demos):
    start = demos[0].positions[0]
    push = Push(step=50, displacement=push_away("iiwa", policy, start, 0.04))
    return simulate(policy, start, SimConfig(robot="iiwa", push=push, time_limit=20.0))


def test_arm_reaches_the_target_after_a_push(pushed_run, policy, demos) -> None:
    run = pushed_run
    config = run.config
    distance = np.linalg.norm(run.positions - run.placement.origin, axis=1)
    # it starts where asked; it stops at the target, as soon as it gets there, well before
    # the time limit
    assert run.start_error < 1e-4
    start = demos[0].positions[0]
    assert np.linalg.norm(run.states[0] - start) * run.placement.scale < 1e-4
    assert run.reached and run.final_error <= config.tolerance <= 0.01
    assert run.times[-1] < config.time_limit
    assert distance[-2] > config.tolerance
    # the push happened where asked and set the arm back
    assert run.push_time == pytest.approx(0.5)
    assert np.linalg.norm(run.push_offset) == pytest.approx(0.04, abs=1e-3)
    pushed = int(np.searchsorted(run.times, run.push_time))
    assert distance[pushed] > distance[pushed - 1] + 0.03
    # and the arm made up for it: back on its unpushed path (snds.arrival), before arrival
    assert run.recovery_time is not None
    assert 0 <= run.recovery_time < run.times[-1] - run.push_time
    path = rest_of_path(unpushed_path(policy, start, dt=0.01, steps=3000), run.states[pushed - 1])
    off = distance_to_path(run.states, path)
    back = pushed + round(run.recovery_time * config.control_rate)
    assert (off[back:] <= run.path_tolerance).all()
    assert run.off_path == pytest.approx(off[pushed:].max())


def test_joint_limits_hold_along_the_joint_path(pushed_run) -> None:
    q = pushed_run.joints
    assert q.shape == (len(pushed_run.times), 7)
    assert np.all(q >= pushed_run.joint_lower) and np.all(q <= pushed_run.joint_upper)


def test_the_end_effector_stays_on_the_work_plane(pushed_run) -> None:
    off = [np.linalg.norm(pushed_run.placement.off_task(p)) for p in pushed_run.positions]
    assert max(off) < 5e-3 and off[-1] < 1e-3


def test_record_is_json_with_the_settings(pushed_run) -> None:
    record = json.loads(json.dumps(pushed_run.to_dict()))
    assert record["settings"]["robot"] == "iiwa"
    assert record["settings"]["push"]["step"] == 50
    assert record["reached"] is True
    assert len(record["joint_path"]) == len(record["time"]) == len(record["end_effector_path"])
    # a position policy does not drive the orientation: the controller held it
    assert record["drives_orientation"] is False and record["placement"]["rotation"] is None
    assert len(record["orientation_path"]) == len(record["time"])
    assert max(record["orientation_error_path_rad"]) < 0.05


@pytest.mark.parametrize("robot", ["panda", "jaco2"])
def test_other_arms_reach_the_target(policy, demos, robot: str) -> None:
    if robot == "jaco2":
        try:
            metadata.distribution("example-robot-data")
        except metadata.PackageNotFoundError:
            pytest.skip("the Jaco2 model needs the jaco2 extra")
    run = simulate(policy, demos[1].positions[0], SimConfig(robot=robot, time_limit=20.0))
    assert run.reached and run.final_error <= run.config.tolerance
    assert np.all(run.joints >= run.joint_lower) and np.all(run.joints <= run.joint_upper)


def test_a_target_out_of_reach_keeps_the_joints_within_limits() -> None:
    from snds.sim.arm import Arm

    with Arm(get_robot("panda")) as arm:
        arm.reset(arm.rest)
        error = arm.move_to(np.array([2.0, 0.0, 0.3]), arm.end_effector().orientation)
        q = arm.joint_positions()
    assert error > 0.8  # it reports how far it stayed, it does not pretend
    assert np.all(q >= arm.lower) and np.all(q <= arm.upper)


def test_frames_and_path_pictures(pushed_run, demos, tmp_path: Path) -> None:
    from snds.sim.plots import plot_frames, plot_path, render_frames

    frames, steps = render_frames(pushed_run, demos, count=3, width=160, height=120)
    assert len(frames) == len(steps) >= 3 and frames[0].shape == (120, 160, 3)
    assert 50 in steps  # the frame right after the push is shown
    assert np.std(frames[-1]) > 5  # not a blank picture
    assert_png(plot_frames(pushed_run, frames, steps, tmp_path / "frames.png"))
    assert_png(plot_path(pushed_run, demos, tmp_path / "path.png"))


@pytest.fixture(scope="module")
def model_dir(policy, demos, tmp_path_factory) -> tuple[Path, Path]:
    root = tmp_path_factory.mktemp("sim-cli")
    save_model(policy.to(torch.float32), root / "model")
    policy.to(torch.float64)
    data = root / "spiral.npz"
    np.savez(
        data,
        pos=np.stack([d.positions for d in demos]),
        vel=np.stack([d.velocities for d in demos]),
        t=demos[0].times,
    )
    return root / "model", data


def test_cli_simulate_writes_record_and_pictures(model_dir, tmp_path: Path, capsys) -> None:
    model, data = model_dir
    out = tmp_path / "out"
    args = ["simulate", str(model), "--data", str(data), "--robot", "iiwa", "--out", str(out)]
    assert main([*args, "--push", "40,0,0.03,0", "--frames", "2", "--time-limit", "20"]) == 0
    record = json.loads((out / "sim.json").read_text())
    assert record["reached"] and record["settings"]["push"]["displacement"] == [0, 0.03, 0]
    assert record["model"] == str(model.resolve())
    assert_png(out / "path.png")
    assert_png(out / "frames.png")
    assert "reached the target" in capsys.readouterr().out


def test_cli_simulate_bad_input_exits_2(model_dir, tmp_path: Path, capsys) -> None:
    model, data = model_dir
    assert main(["simulate", str(tmp_path / "nowhere"), "--data", str(data)]) == 2
    assert main(["simulate", str(model), "--data", str(data), "--start-demo", "9"]) == 2
    with pytest.raises(SystemExit) as exit_:
        main(["simulate", str(model), "--push", "1.5,0,0"])
    assert exit_.value.code == 2
    with pytest.raises(SystemExit) as exit_:
        main(["simulate", str(model), "--robot", "ur5"])
    assert exit_.value.code == 2
    assert "Traceback" not in capsys.readouterr().err


def test_cli_recovery_after_a_sideways_push_is_the_return_to_the_path(
    policy, model_dir, tmp_path: Path, capsys
) -> None:
    # GIVEN a push across the path, of 15 % of the extent, at step 40 (issue 44, item 7: the
    # old "as close to the target as before" called such a push recovered at once)
    model, data = model_dir
    start = spiral_demos()[0].positions[0]
    robot = get_robot("iiwa")
    placement = Placement.for_task(robot, policy.target, default_scale(robot, policy))
    path = unpushed_path(policy, start, dt=0.01, steps=3000)
    along = path[41] - path[40]
    across = np.array([-along[1], along[0]]) / np.linalg.norm(along)
    extent = float(policy.extents()[0])
    push = placement.velocity_to_world(0.15 * extent * across)
    out = tmp_path / "out"
    spec = "40," + ",".join(f"{d:.6f}" for d in push)
    args = ["simulate", str(model), "--data", str(data), "--out", str(out), "--frames", "0"]
    assert main([*args, "--push", spec, "--time-limit", "20"]) == 0
    record = json.loads((out / "sim.json").read_text())
    # THEN recovery is the time from the push until the path is within 5 % of the extent
    states, times = np.array(record["task_path"]), np.array(record["time"])
    pushed = int(np.searchsorted(times, record["push_time_s"]))
    off = distance_to_path(states, rest_of_path(path, states[pushed - 1]))
    assert off[pushed] > 0.1 * extent  # the push took it off the path
    assert record["path_tolerance"] == pytest.approx(PATH_TOLERANCE * extent)
    recovery = record["recovery_time_s"]
    assert recovery is not None and recovery > 0
    back = pushed + round(recovery / 0.01)
    assert (off[back:] <= record["path_tolerance"]).all() and off[back - 1] > record[
        "path_tolerance"
    ]
    # and the line says how far off the path the push took it and when it was back on it
    line = capsys.readouterr().out
    assert f"back on it (within {record['path_tolerance']:.3g} units, 5 % of the extent)" in line
    assert f"{recovery:.2f} s later" in line and f"up to {record['off_path']:.3g} units" in line


def test_a_3d_model_with_a_phase_is_simulated_and_photographed(tmp_path: Path) -> None:
    # GIVEN an untrained 3-D model with a phase of 3 codes (its demonstrations' states are 6
    # numbers: render_frames placed them as 3-D positions and failed, issue 39)
    import snds
    from snds.phase import Phase
    from snds.sim.plots import plot_frames, render_frames

    demos = Phase(codes=3, seed=0).apply(spiral_demos(dim=3))
    policy = snds.make_policy(demos, config=FAST, seed=0).double().eval()
    run = simulate(policy, demos[0].states[0], SimConfig(robot="iiwa", time_limit=0.3))
    # THEN the run's frames show the demonstrations' positions, and the strip is written
    frames, steps = render_frames(run, demos, count=2, width=80, height=60)
    assert len(frames) == 2 and np.std(frames[-1]) > 5
    assert_png(plot_frames(run, frames, steps, tmp_path / "frames.png"))
