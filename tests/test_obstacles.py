"""Obstacles (snds.obstacles): impenetrability in continuous and discrete time, the identity
far away, the target unchanged, convergence of a linear field around them, and the specs."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from snds.cli import main
from snds.data import Demonstration, Demonstrations, Normalization
from snds.errors import ConfigError
from snds.obstacles import (
    Box,
    Ellipsoid,
    ModulatedPolicy,
    Scene,
    Sphere,
    Workspace,
    check_obstacles,
    load_scene,
    modulate_twist,
    parse_obstacle,
    parse_workspace,
)
from snds.policy import Policy
from snds.rollout import rollout
from snds.stability import CheckConfig
from snds.steppers import Dynamics, GuardedEuler

from conftest import make_policy, spiral_demos

AVOIDING = GuardedEuler(max_halvings=40)


class _Quadratic(torch.nn.Module):
    quadratic = 1.0

    def value_and_grad(self, x):
        return (x * x).sum(-1), 2 * x

    def forward(self, x):
        return (x * x).sum(-1)


class FieldPolicy(Policy):
    """An analytic policy in user units (identity normalisation at the origin): the linear
    field -x with V = |x|^2 by default, or any field without a Lyapunov function."""

    kind = "field"

    def __init__(self, dim: int, field=None) -> None:
        normalization = Normalization(center=np.zeros(dim), length=1.0, time=1.0)
        super().__init__(dim=dim, normalization=normalization)
        self._field = field
        self.lyapunov = _Quadratic() if field is None else None
        self.center = self.center.double()

    def field(self, x):
        return -x if self._field is None else self._field(x)

    def decay(self, v, x):
        return v  # dV/dt = -2V for -x: half of it is promised


def line_demos(dim: int, start) -> Demonstrations:
    t = np.linspace(0.0, 6.0, 300)
    path = np.exp(-t)[:, None] * np.asarray(start, dtype=float)
    path = path - path[-1]
    return Demonstrations(
        (Demonstration(positions=path, velocities=-path, times=t),), np.zeros(dim)
    )


SCENES_2D = {
    "sphere": Scene(obstacles=(Sphere(center=(4.0, 1.0), radius=1.0, margin=0.2),)),
    "ellipse": Scene(
        obstacles=(
            Ellipsoid(center=(-3.0, 3.0), half_sizes=(2.0, 0.6), angles=(30.0,), margin=0.1),
        )
    ),
    "box": Scene(
        obstacles=(Box(center=(2.0, -4.0), half_sizes=(1.5, 0.5), angles=(-20.0,), margin=0.3),)
    ),
    "workspace": Scene(workspace=Workspace(center=(0.0, 0.0), half_sizes=(8.0, 6.0), margin=0.5)),
    "three overlapping": Scene(
        obstacles=(
            Sphere(center=(4.0, 1.0), radius=1.0, margin=0.2),
            Box(center=(5.0, 2.5), half_sizes=(1.0, 0.4), margin=0.1),
            Ellipsoid(center=(-3.0, 3.0), half_sizes=(2.0, 0.6), margin=0.1),
        ),
        workspace=Workspace(center=(0.0, 0.0), half_sizes=(9.0, 9.0), margin=0.5),
    ),
    "three apart": Scene(
        obstacles=(
            Sphere(center=(4.0, 1.0), radius=1.0, margin=0.2),
            Box(center=(2.0, -4.0), half_sizes=(1.5, 0.5), angles=(-20.0,), margin=0.3),
            Ellipsoid(center=(-3.0, 3.0), half_sizes=(2.0, 0.6), angles=(30.0,), margin=0.1),
        ),
        workspace=Workspace(center=(0.0, 0.0), half_sizes=(9.0, 9.0), margin=0.5),
    ),
}
SCENES_3D = {
    "sphere 3d": Scene(obstacles=(Sphere(center=(3.0, 1.0, -1.0), radius=1.0, margin=0.2),)),
    "ellipsoid 3d": Scene(
        obstacles=(
            Ellipsoid(
                center=(-2.0, 2.0, 1.0), half_sizes=(1.5, 0.5, 0.8), angles=(10, 20, 30), margin=0.1
            ),
        )
    ),
    "box 3d": Scene(
        obstacles=(
            Box(center=(2.0, -3.0, 1.0), half_sizes=(1.0, 0.5, 0.7), angles=(0, 0, 45), margin=0.2),
        ),
        workspace=Workspace(center=(0.0, 0.0, 0.0), half_sizes=(7.0, 7.0, 7.0), margin=0.3),
    ),
}
SCENES = {**SCENES_2D, **SCENES_3D}


def near_boundary(scene: Scene, count: int, band: float, seed: int = 0) -> torch.Tensor:
    """Random free states with some Gamma in (1, 1 + band), by bisection along random rays."""
    generator = torch.Generator().manual_seed(seed)
    out = []
    for body in scene.bodies:
        dim = body.dim
        u = torch.randn(count, dim, generator=generator, dtype=torch.float64)
        u = u / u.norm(dim=-1, keepdim=True)
        center = torch.tensor(body.center, dtype=torch.float64)
        wanted = 1.0 + band * torch.rand(count, generator=generator, dtype=torch.float64)
        low = torch.zeros(count, dtype=torch.float64)
        high = torch.full((count,), 100.0, dtype=torch.float64)
        sign = -1.0 if body.free_inside else 1.0
        for _ in range(200):
            middle = 0.5 * (low + high)
            above = sign * (body.gamma(center + middle[:, None] * u) - wanted) > 0
            high, low = torch.where(above, middle, high), torch.where(above, low, middle)
        out.append(center + (high if not body.free_inside else low)[:, None] * u)
    x = torch.cat(out)
    return x[scene.free(x)]


@pytest.mark.parametrize("name", list(SCENES))
def test_no_velocity_enters_an_obstacle_at_its_boundary(name):
    # GIVEN states on the inflated boundaries (Gamma = 1 + 1e-9) and random velocities
    scene = SCENES[name]
    x = near_boundary(scene, 400, 1e-9)
    v = 10 * torch.randn(x.shape, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    # WHEN they are modulated
    out = scene.modulate(x, v)
    # THEN no body's Gamma decreases along the modulated velocity beyond 1e-6 of the speed
    for k, body in enumerate(scene.bodies):
        on = (scene.gammas(x)[:, k] - 1.0).abs() < 1e-6
        _, gradient = body.distance(x[on])
        normal = gradient / gradient.norm(dim=-1, keepdim=True)
        rate = (normal * out[on]).sum(-1)
        assert on.any()
        assert (rate >= -1e-6 * v[on].norm(dim=-1)).all(), float(rate.min())


@pytest.mark.parametrize("name", list(SCENES))
def test_a_guarded_step_never_ends_inside_an_obstacle(name):
    # GIVEN states within 1% of Gamma of a boundary, a field driving straight into every
    # body at 1e3 units/s, and a step of a whole second
    scene = SCENES[name]
    x = near_boundary(scene, 500, 1e-2, seed=2)
    centre = torch.tensor(scene.bodies[0].center, dtype=torch.float64)
    policy = FieldPolicy(
        x.shape[-1], field=lambda s: 1e3 * (centre - s) * (1 - 2 * torch.rand(1).item())
    )
    # WHEN each state takes a guarded step
    nxt = (
        GuardedEuler(max_halvings=40)
        .step(Dynamics.of(policy, scene=scene), x, torch.ones(len(x), dtype=x.dtype))
        .states
    )
    # THEN every state reached is in free space (Gamma > 1), a held state included
    assert bool(scene.free(nxt).all())
    assert bool((scene.clearances(nxt) > torch.tensor([b.margin for b in scene.bodies])).all())


@pytest.mark.parametrize("name", ["three overlapping", "box 3d"])
def test_discrete_rollouts_from_near_the_boundaries_never_penetrate(name):
    # GIVEN the linear field -x (Euler-stable only below dt = 2) and starts by the boundaries
    scene = SCENES[name]
    x0 = near_boundary(scene, 60, 0.05, seed=3)
    policy = FieldPolicy(x0.shape[-1])
    # WHEN rolled out with a coarse step
    states = rollout(policy, x0, dt=0.3, steps=60, stepper=AVOIDING, scene=scene).states
    # THEN no state of any rollout is within any margin
    flat = states.reshape(-1, x0.shape[-1])
    assert bool(scene.free(flat).all())


@pytest.mark.parametrize("name", list(SCENES))
def test_modulation_is_exactly_the_identity_beyond_the_influence(name):
    # GIVEN free states where every Gamma >= 2 (beyond every influence distance)
    scene = SCENES[name]
    dim = scene.dim
    x = (
        12
        * torch.rand(20_000, dim, generator=torch.Generator().manual_seed(4), dtype=torch.float64)
        - 6
    )
    x = x[(scene.gammas(x) >= 2.0).all(dim=-1)]
    v = torch.randn(x.shape, dtype=torch.float64)
    # WHEN modulated  THEN unchanged, bit for bit
    assert len(x) > 100
    assert torch.equal(scene.modulate(x, v), v)


def test_the_target_is_unchanged_and_obstacles_on_it_are_refused():
    # GIVEN a small SNDS policy on a spiral and an obstacle across its demonstrations
    demos = spiral_demos()
    policy = make_policy(demos)
    scene = Scene(obstacles=(Sphere(center=(3.0, 3.0), radius=1.0, margin=0.2),))
    modulated = ModulatedPolicy(policy, scene)
    target = torch.zeros(1, 2, dtype=torch.float64)
    # THEN the target stays an equilibrium of the modulated field, exactly
    with torch.no_grad():
        assert torch.equal(modulated(target), policy(target))
        assert float(modulated(target).abs().max()) == 0.0
    # AND a scene whose margin covers the target is refused
    with pytest.raises(ConfigError, match="not in free space"):
        Scene(obstacles=(Sphere(center=(0.5, 0.0), radius=0.3, margin=0.3),)).check(2, np.zeros(2))


def test_khansari_weights_leave_only_the_touched_obstacle_active():
    # GIVEN two obstacles within each other's influence, and a state on the first's boundary
    scene = Scene(
        obstacles=(
            Sphere(center=(0.0, 3.0), radius=1.0, influence=3.0),
            Sphere(center=(2.5, 3.0), radius=1.0, influence=3.0),
        )
    )
    x = torch.tensor([[0.0, 2.0]], dtype=torch.float64)  # on sphere 0, 1.7 from sphere 1
    v = torch.tensor([[0.3, 1.0]], dtype=torch.float64)  # into sphere 0, towards sphere 1
    out = scene.modulate(x, v)
    # THEN the normal part vanishes and the velocity is sphere 0's tangent, sped up twice
    assert abs(float(out[0, 1])) < 1e-12
    assert float(out[0, 0]) == pytest.approx(2 * 0.3)


def test_linear_field_reaches_the_target_around_obstacles():
    # GIVEN the linear field -x and a 2-D scene across its paths
    demos = line_demos(2, (8.0, 2.0))
    scene = SCENES_2D["three apart"]
    # WHEN the stability report under obstacles runs (random free starts, demo starts)
    report = check_obstacles(FieldPolicy(2), demos, scene, config=CheckConfig(rollouts=300))
    # THEN none penetrates, the clearance keeps the margin, and all but saddle starts arrive
    assert report.random.penetrated == 0 and report.demos.penetrated == 0
    assert report.random.min_clearance >= report.random.margin
    assert report.random.converged_fraction >= 0.99
    for stall in report.random.stall_points:
        assert stall["kind"] == "saddle"  # on a boundary, not a spurious attractor
    assert report.wall_seconds > 0 and report.cpu_seconds > 0


def test_moving_obstacle_is_avoided_at_every_step():
    # GIVEN a ball sweeping across the linear field's path at 2 units/s
    ball = Sphere(center=(4.0, -4.0), radius=1.0, margin=0.2, velocity=(0.0, 2.0))
    scene = Scene(obstacles=(ball,))
    x0 = torch.tensor([[6.0, 0.5], [5.0, -1.0], [7.0, 1.0]], dtype=torch.float64)
    dt, steps = 0.02, 400
    # WHEN rolled out among it
    states = rollout(FieldPolicy(2), x0, dt=dt, steps=steps, stepper=AVOIDING, scene=scene).states
    # THEN every state is outside the ball as it is at that time, and they still arrive
    for k in range(steps + 1):
        assert bool(scene.at(k * dt).free(states[k]).all()), k
    assert float(states[-1].norm(dim=-1).max()) < 0.05


def test_pose_twist_modulates_the_position_part_only():
    scene = SCENES_3D["sphere 3d"]
    position = near_boundary(scene, 50, 1e-9)
    twist = torch.randn(len(position), 6, dtype=torch.float64)
    out = modulate_twist(scene, position, twist)
    assert torch.equal(out[:, 3:], twist[:, 3:])
    assert torch.equal(out[:, :3], scene.modulate(position, twist[:, :3]))


# --- specs -----------------------------------------------------------------------------------


def test_specs_give_the_shapes_they_describe():
    sphere = parse_obstacle("sphere:1,2,0.5,margin=0.1")
    assert sphere == Sphere(center=(1.0, 2.0), radius=0.5, margin=0.1)
    box = parse_obstacle("box:0,0,1,1,2,3,angles=10/20/30,influence=2")
    assert box == Box(
        center=(0.0, 0.0, 1.0), half_sizes=(1.0, 2.0, 3.0), angles=(10.0, 20.0, 30.0), influence=2.0
    )
    ellipse = parse_obstacle("ellipsoid:1,1,2,0.5,angle=45,velocity=0/1")
    assert ellipse.angles == (45.0,) and ellipse.velocity == (0.0, 1.0)
    assert parse_workspace("box:0,0,10,5,margin=1") == Workspace(
        center=(0.0, 0.0), half_sizes=(10.0, 5.0), margin=1.0
    )
    # Distances: the box's is Euclidean, the ellipse's a lower bound exact on its short axis.
    x = torch.tensor([[3.0, 0.0], [0.0, 2.0]], dtype=torch.float64)
    d, _ = Box(center=(0.0, 0.0), half_sizes=(1.0, 1.0)).distance(x)
    assert d.tolist() == [2.0, 1.0]
    d, _ = Ellipsoid(center=(0.0, 0.0), half_sizes=(2.0, 1.0)).distance(x)
    assert d.tolist() == [0.5, 1.0]  # true distances 1.0 and 1.0


BAD_SPECS = {
    "unknown shape": ("--obstacle", "cylinder:0,0,1", "expected SHAPE:NUMBERS"),
    "not a number": ("--obstacle", "sphere:0,x,1", "'x' is not a number"),
    "negative radius": ("--obstacle", "sphere:0,0,-1", "radius must be a number > 0"),
    "odd box numbers": ("--obstacle", "box:0,0,1", "needs CX,CY"),
    "unknown option": ("--obstacle", "sphere:0,0,1,colour=red", "unknown option 'colour'"),
    "negative margin": ("--obstacle", "sphere:0,0,1,margin=-1", "margin must be"),
    "3-D angle in 2-D": ("--obstacle", "box:0,0,1,1,angles=1/2/3", "orientation of a 2-D"),
    "wrong dimension": ("--obstacle", "sphere:5,5,5,1", "a 3-D sphere for a 2-D model"),
    "on the target": ("--obstacle", "sphere:0.5,0,1", "not in free space"),
    "workspace shape": ("--workspace", "sphere:0,0,1", "--workspace 'sphere:0,0,1'"),
}


@pytest.mark.parametrize("case", list(BAD_SPECS))
def test_bad_obstacle_specs_exit_2_with_one_line(case, tmp_path, capsys):
    # GIVEN a saved 2-D model (a spiral, target at the origin) and a bad spec
    from snds.models import save_model

    demos = spiral_demos()
    save_model(make_policy(demos), tmp_path / "m", extra={"data": {}})
    flag, spec, message = BAD_SPECS[case]
    before = sorted(p.name for p in (tmp_path / "m").iterdir())
    # WHEN snds evaluate gets it  THEN exit 2, one line naming the problem, no file written
    code = main(["evaluate", str(tmp_path / "m"), "--motion", "Sine", flag, spec])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert len(err) == 1 and err[0].startswith("snds: error: ") and message in err[0], err
    assert sorted(p.name for p in (tmp_path / "m").iterdir()) == before


def test_scene_files_json_and_yaml(tmp_path):
    scene = SCENES_2D["three overlapping"]
    (tmp_path / "s.json").write_text(json.dumps(scene.to_dict()))
    assert load_scene(tmp_path / "s.json") == scene
    (tmp_path / "s.yaml").write_text(
        "obstacles:\n  - sphere:4,1,1,margin=0.2\n"
        "  - {shape: box, center: [0, 5], half_sizes: [1, 1]}\n"
    )
    loaded = load_scene(tmp_path / "s.yaml")
    assert loaded.obstacles[0] == Sphere(center=(4.0, 1.0), radius=1.0, margin=0.2)
    assert loaded.obstacles[1] == Box(center=(0.0, 5.0), half_sizes=(1.0, 1.0))
    (tmp_path / "bad.json").write_text('{"obstacles": [{"shape": "sphere", "centre": [0, 0]}]}')
    with pytest.raises(ConfigError, match="unknown key 'centre'"):
        load_scene(tmp_path / "bad.json")
    assert math.isfinite(float(loaded.gammas(torch.zeros(1, 2, dtype=torch.float64)).min()))


@pytest.mark.slow
def test_onnx_export_includes_a_fixed_obstacle_set(tmp_path, capsys):
    # GIVEN a saved small model and obstacles across its demonstrations
    pytest.importorskip("onnxruntime")
    from snds.export import load_onnx
    from snds.models import save_model

    demos = spiral_demos()
    save_model(make_policy(demos), tmp_path / "m", extra={"data": {}})
    specs = ["--obstacle", "sphere:3,3,1,margin=0.2", "--obstacle", "box:-3,3,1,0.5,angle=20"]
    # WHEN exported with them (float64; the export checks itself against the library)
    out = tmp_path / "p.onnx"
    args = ["--quiet", "export", str(tmp_path / "m"), "--dtype", "float64", "--out", str(out)]
    args += ["--samples", "500"]
    assert main([*args, *specs]) == 0
    # THEN the file computes the modulated field next to the obstacles too
    from snds.models import load_model
    from snds.obstacles import ModulatedPolicy

    scene = Scene(obstacles=tuple(parse_obstacle(s) for s in specs[1::2]))
    x = near_boundary(scene, 200, 0.5, seed=5)
    policy, _ = load_model(tmp_path / "m")
    with torch.no_grad():
        wanted = ModulatedPolicy(policy.double(), scene)(x).numpy()
    assert np.abs(load_onnx(out)(x.numpy()) - wanted).max() < 1e-9 * np.abs(wanted).max()


def test_export_refuses_moving_obstacles_with_one_line(tmp_path, capsys):
    from snds.models import save_model

    save_model(make_policy(spiral_demos()), tmp_path / "m", extra={"data": {}})
    before = sorted(p.name for p in (tmp_path / "m").iterdir())
    code = main(["export", str(tmp_path / "m"), "--obstacle", "sphere:3,3,1,velocity=1/0"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "moving obstacles" in err[0], err
    assert sorted(p.name for p in (tmp_path / "m").iterdir()) == before


@pytest.mark.slow
def test_simulated_arm_goes_around_a_sphere_without_touching_it():
    # GIVEN the linear field on the iiwa's plane (0.2 m per unit) and a 3 cm ball on its path
    pytest.importorskip("pybullet")
    from snds.sim import SimConfig, simulate

    scene = Scene(obstacles=(Sphere(center=(0.5, 0.02), radius=0.15, margin=0.05),))
    config = SimConfig(robot="iiwa", time_limit=12.0, obstacles=scene)
    # WHEN it runs from behind the ball
    result = simulate(FieldPolicy(2), np.array([1.0, 0.05]), config)
    # THEN it reaches the target, the tool keeps out of the ball and no link touches it
    assert result.reached and result.final_error <= 0.001
    assert result.contact_steps == 0 and result.arm_obstacle_distance > 0
    assert result.obstacle_clearance > 0
    assert bool(scene.clearances(torch.as_tensor(result.states)).min() > 0)


def test_bad_input_doc_lists_every_bad_spec():
    import re
    from pathlib import Path

    doc = (Path(__file__).resolve().parents[1] / "docs" / "bad-input.md").read_text()
    listed = re.findall(r"test_bad_obstacle_specs_exit_2_with_one_line\[(.+?)\]", doc)
    assert sorted(listed) == sorted(BAD_SPECS)
