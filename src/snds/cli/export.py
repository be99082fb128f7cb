"""``snds export``: a saved model as an ONNX file or a ``torch.export`` archive."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from snds.cli._args import _obstacle_arguments
from snds.cli._common import _scene
from snds.data import DataSource
from snds.errors import ConfigError, SNDSError
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
        help="export a model for a real-time controller (ONNX or torch.export); a pose "
        "model's file maps a pose (7 numbers) to a twist (6)",
    )
    parser.add_argument("model", type=Path, help="model directory")
    parser.add_argument("--format", choices=["onnx", "pt2"], default="onnx")
    parser.add_argument(
        "--dtype",
        choices=["float32", "float64"],
        default="float32",
        help="precision of the exported graph",
    )
    parser.add_argument(
        "--out", type=Path, default=None, help="file (default: MODEL/policy.onnx or .pt2)"
    )
    parser.add_argument(
        "--samples", type=int, default=10_000, help="random states of the equality check"
    )
    parser.add_argument("--seed", type=int, default=0, help="seed of those states")
    _obstacle_arguments(parser)
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    from snds import export

    scene = _scene(args)
    policy, description = load_model(args.model)
    if scene is not None:
        policy = _with_obstacles(policy, scene)
    out = args.out or args.model / f"policy.{args.format}"
    dtype = getattr(torch, args.dtype)
    extra = {}
    if args.format == "onnx" and policy.space.dim != policy.space.position_dim:
        # A controller of a model with a phase takes a new start's phase from these.
        extra["starts"] = _start_states(args.model, description)
    path = export.FORMATS[args.format](policy, out, dtype=dtype, **extra)
    check = export.verify(path, policy, samples=args.samples, seed=args.seed)
    write_json(path.with_name(path.name + ".check.json"), to_jsonable(check.to_dict()))
    if not check.passed:
        # A controller must not pick up a model that computes something else.
        path.unlink(missing_ok=True)
        raise export.ExportError(
            f"{path}: outputs differ from the library's by {check.max_error:.2e} "
            f"(relative), more than {check.tolerance:.0e}, and by {check.max_error_float64:.2e} "
            f"from the exact (float64) policy, where the library in {check.dtype} is "
            f"{check.library_error:.2e} from it"
        )
    if not args.quiet:
        print(
            f"{path}: {export.signature(policy).description}; {check.samples} random "
            f"states, largest difference from the library {check.max_error:.2e} (relative; "
            f"{check.max_abs_diff:.2e} absolute)"
        )
    return 0


def _start_states(model: Path, description: dict) -> np.ndarray:
    """The start states (D, n + m) of the demonstrations a model with a phase was trained on."""
    recorded = description.get("data") or {}
    if "phase" not in recorded:
        raise SNDSError(f"{model}: a model with a phase, but model.json records no phase")
    demos = DataSource.from_record(recorded).load()
    return np.stack([demo.states[0] for demo in demos])


def _with_obstacles(policy: Policy, scene) -> Policy:
    """The policy of ``snds export --obstacle``: the modulation in the graph (fixed obstacles,
    position models), or a one-line refusal of what the graph cannot hold."""

    if isinstance(policy.space, SE3):
        raise ConfigError(
            "obstacles cannot be exported with a pose model (its graph maps poses to twists); "
            "modulate the linear part in the controller (snds.obstacles.modulate_twist)"
        )
    if policy.space.dim != policy.space.position_dim:
        raise ConfigError("obstacles cannot be exported with a model that has a phase")
    if scene.moving:
        raise ConfigError(
            "moving obstacles (velocity=) cannot be exported: the graph has no time input"
        )
    scene.check(policy.dim, policy.normalization.center)
    return ModulatedPolicy(policy, scene)
