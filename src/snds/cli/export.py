"""``snds export``: a saved model as an ONNX file, a ``torch.export`` archive or C99 source."""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from snds import export
from snds.cli._args import obstacle_arguments
from snds.cli._common import scene_of, start_rule_of
from snds.errors import ConfigError
from snds.export import c_check
from snds.export.c import export_c
from snds.io import to_jsonable, write_json
from snds.models import load_model
from snds.obstacles import ModulatedPolicy
from snds.policy import Policy
from snds.spaces import SE3

__all__ = ["register", "run"]


def register(commands: argparse._SubParsersAction) -> None:
    """Adds ``snds export`` to the subcommands."""
    parser = commands.add_parser(
        "export",
        help="export a model for a real-time controller (ONNX, torch.export or C99); a pose "
        "model's file maps a pose (7 numbers) to a twist (6)",
    )
    parser.add_argument("model", type=Path, help="model directory")
    parser.add_argument(
        "--format",
        choices=["onnx", "pt2", "c"],
        default="onnx",
        help="c: a dependency-free C99 header and source (double and float functions)",
    )
    parser.add_argument(
        "--dtype",
        choices=["float32", "float64"],
        default="float32",
        help="precision of the exported graph (onnx, pt2; c writes both)",
    )
    parser.add_argument(
        "--out",
        type=Path,
        default=None,
        help="file (default: MODEL/policy.onnx, .pt2, or policy.h with policy.c beside it)",
    )
    parser.add_argument(
        "--max-speed",
        type=float,
        default=None,
        help="c: the speed limit written into the header (user units of the positions per "
        "second); the guarded step scales the velocity down to it",
    )
    parser.add_argument(
        "--rate",
        type=float,
        default=None,
        help="c: the control rate (Hz) whose period the header gives as SNDS_DT (default 500)",
    )
    parser.add_argument(
        "--samples", type=int, default=10_000, help="random states of the equality check"
    )
    parser.add_argument("--seed", type=int, default=0, help="seed of those states")
    obstacle_arguments(parser)
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    scene = scene_of(args)
    policy, description = load_model(args.model)
    if scene is not None:
        policy = _with_obstacles(policy, scene)
    if args.format == "c":
        return _run_c(args, policy, description)
    if args.max_speed is not None or args.rate is not None:
        raise ConfigError("--max-speed and --rate are options of --format c")
    out = args.out or args.model / f"policy.{args.format}"
    dtype = getattr(torch, args.dtype)
    extra = {}
    if args.format == "onnx" and policy.space.phase_dim:
        # A controller of a model with a phase takes a new start's phase from these.
        extra["start_rule"] = start_rule_of(args.model, description)
    path = export.FORMATS[args.format](policy, out, dtype=dtype, **extra)
    check = export.verify(path, policy, samples=args.samples, seed=args.seed)
    _report(path, [check], policy, quiet=args.quiet)
    return 0


def _run_c(args: argparse.Namespace, policy: Policy, description: dict) -> int:
    out = args.out or args.model / "policy.h"
    options = {"max_speed": args.max_speed}
    if policy.space.phase_dim:
        # A controller of a model with a phase takes a new start's phase from these.
        options["start_rule"] = start_rule_of(args.model, description)
    if args.rate is not None:
        options["rate"] = args.rate
    path = export_c(policy, out, **options)
    if c_check.compiler() is None:
        if not args.quiet:
            print(f"{path} (+ {path.with_suffix('.c').name}): not checked, no C compiler found")
        return 0
    checks = c_check.verify_c(path, policy, samples=args.samples, seed=args.seed)
    _report(path, checks, policy, quiet=args.quiet, also=[path.with_suffix(".c")])
    return 0


def _report(path: Path, checks: list, policy: Policy, *, quiet: bool, also=()) -> None:
    """Writes the checks beside the file, removes a file that fails one, prints the result."""
    write_json(
        path.with_name(path.name + ".check.json"),
        to_jsonable([c.to_dict() for c in checks] if len(checks) > 1 else checks[0].to_dict()),
    )
    for check in checks:
        if not check.passed:
            # A controller must not pick up a model that computes something else.
            for written in (path, *also):
                written.unlink(missing_ok=True)
            raise export.ExportError(
                f"{path}: outputs ({check.dtype}) differ from the library's by "
                f"{check.max_error:.2e} (relative), more than {check.tolerance:.0e}, and by "
                f"{check.max_error_float64:.2e} from the exact (float64) policy, where the "
                f"library in {check.dtype} is {check.library_error:.2e} from it"
            )
    if not quiet:
        print(f"{path}: {export.signature(policy).description}")
        for check in checks:
            print(f"  {check.summary()}")


def _with_obstacles(policy: Policy, scene) -> Policy:
    """The policy of ``snds export --obstacle``: the modulation in the graph (fixed obstacles,
    position models), or a one-line refusal of what the graph cannot hold."""

    if isinstance(policy.space, SE3):
        raise ConfigError(
            "obstacles cannot be exported with a pose model (its graph maps poses to twists); "
            "modulate the linear part in the controller (snds.obstacles.modulate_twist)"
        )
    if policy.space.phase_dim:
        raise ConfigError("obstacles cannot be exported with a model that has a phase")
    if scene.moving:
        raise ConfigError(
            "moving obstacles (velocity=) cannot be exported: the graph has no time input"
        )
    scene.check(policy.dim, policy.normalization.center)
    return ModulatedPolicy(policy, scene)
