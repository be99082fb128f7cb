"""``snds simulate``: drives a simulated arm with a saved model (:mod:`snds.sim`)."""

from __future__ import annotations

import argparse
from pathlib import Path

from snds.arrival import PATH_TOLERANCE
from snds.cli._args import data_arguments, obstacle_arguments
from snds.cli._common import data_source, model_and_data, scene_of
from snds.errors import SNDSError
from snds.io import to_jsonable, write_json

__all__ = ["register", "run"]


def register(commands: argparse._SubParsersAction) -> None:
    """Adds ``snds simulate`` to the subcommands."""
    from snds.sim import ROBOTS, SimConfig

    parser = commands.add_parser(
        "simulate", help="drive a simulated robot arm with a model (PyBullet, headless)"
    )
    parser.add_argument("model", type=Path, help="model directory")
    data_arguments(parser, required=False)
    parser.add_argument("--robot", choices=list(ROBOTS), default=SimConfig.robot)
    parser.add_argument(
        "--push",
        type=_push,
        default=None,
        help="STEP,DX,DY,DZ: displace the end effector by (DX, DY, DZ) metres at control step STEP",
    )
    parser.add_argument(
        "--scale",
        type=float,
        default=None,
        help="metres per unit of the task's positions (default: fit the motion into the "
        "robot's reach)",
    )
    parser.add_argument(
        "--start-demo",
        type=int,
        default=0,
        help="start at this demonstration's first state (a pose model: its first pose)",
    )
    parser.add_argument(
        "--control-rate", type=float, default=SimConfig.control_rate, help="control loop, Hz"
    )
    parser.add_argument(
        "--time-limit", type=float, default=SimConfig.time_limit, help="seconds of simulation"
    )
    parser.add_argument(
        "--tolerance",
        type=float,
        default=SimConfig.tolerance,
        help="distance to the target (m) at which the run stops",
    )
    parser.add_argument(
        "--angle-tolerance",
        type=float,
        default=SimConfig.angle_tolerance,
        help="angle to the target orientation (rad) within which a pose model's run stops "
        "(with the distance within --tolerance)",
    )
    parser.add_argument(
        "--frames", type=int, default=6, help="rendered frames in frames.png (0: none)"
    )
    parser.add_argument(
        "--out", type=Path, default=None, help="results folder (default: MODEL/sim-ROBOT)"
    )
    parser.add_argument(
        "--max-speed",
        type=float,
        default=None,
        help="speed limit of the task's positions (user units/s); the guarantee holds under it",
    )
    parser.add_argument(
        "--keep-orientation",
        action="store_true",
        help="a pose model: keep its target orientation at the arm's orientation at rest "
        "(default: turn the task's orientations, if needed, so that the arm follows the "
        "model's path within its joint limits)",
    )
    obstacle_arguments(parser)
    parser.set_defaults(run=run)


def recovery_text(result) -> str:
    """'up to D units (M mm) off its path, back on it (within T units) S s later' of a
    pushed run (:func:`snds.arrival.recovery_time`)."""
    scale = result.placement.scale
    text = (
        f"up to {result.off_path:.3g} units ({1000 * scale * result.off_path:.3g} mm) off its path"
    )
    within = f"within {result.path_tolerance:.3g} units, {100 * PATH_TOLERANCE:g} % of the extent"
    if result.recovery_time is None:
        return f"{text}, not back on it ({within}) by the end"
    return f"{text}, back on it ({within}) {result.recovery_time:.2f} s later"


def _push(text: str):
    from snds.sim import Push

    parts = text.split(",")
    try:
        step, *displacement = (float(part) for part in parts)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected STEP,DX,DY,DZ (a step and metres), got {text!r}"
        ) from None
    if len(parts) != 4 or step != int(step) or step < 0:
        raise argparse.ArgumentTypeError(
            f"expected STEP,DX,DY,DZ with an integer step >= 0, got {text!r}"
        )
    return Push(step=int(step), displacement=tuple(displacement))


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from snds.sim import SimConfig, simulate
    from snds.sim.plots import plot_frames, plot_path, render_frames

    scene = scene_of(args)
    policy, _, demos = model_and_data(args)
    if not 0 <= args.start_demo < len(demos):
        raise SNDSError(f"--start-demo {args.start_demo}: there are {len(demos)} demonstrations")
    if scene is not None:
        space = policy.space
        scene.check(space.position_dim, space.positions(np.asarray(demos.target)))
    config = SimConfig(
        robot=args.robot,
        scale=args.scale,
        control_rate=args.control_rate,
        time_limit=args.time_limit,
        tolerance=args.tolerance,
        angle_tolerance=args.angle_tolerance,
        push=args.push,
        obstacles=scene,
        max_speed=args.max_speed,
        fit_orientation=not args.keep_orientation,
    )
    # A state of the model's space: a position, or for a pose model position and quaternion.
    start = demos[args.start_demo].states[0]
    result = simulate(policy, start, config)
    out = args.out or args.model / f"sim-{config.robot}"
    record = {
        "model": str(Path(args.model).resolve()),
        "data": data_source(args).record() if args.motion or args.data else None,
        "start_demo": args.start_demo,
        **result.to_dict(),
    }
    write_json(out / "sim.json", to_jsonable(record))
    paths = [plot_path(result, demos, out / "path.png")]
    if args.frames > 0:
        frames, steps = render_frames(result, demos, count=args.frames)
        paths.append(plot_frames(result, frames, steps, out / "frames.png"))
    if not args.quiet:
        outcome = (
            f"reached the target in {result.times[-1]:.2f} s"
            if result.reached
            else f"did not reach the target in {result.times[-1]:.2f} s"
        )
        line = f"{out}: {outcome}, final error {1000 * result.final_error:.2f} mm"
        if result.drives_orientation:
            line += f" and {result.final_orientation_error:.4f} rad"
            turn = float(np.linalg.norm(result.orientation_turn))
            if turn > 0:
                line += (
                    f" (the task's orientations turned {turn:.2f} rad from the default, to "
                    "keep the arm within its joint limits; --keep-orientation: not)"
                )
        if result.push_time is not None:
            line += f"; pushed at {result.push_time:.2f} s, {recovery_text(result)}"
        print(line)
    return 0
