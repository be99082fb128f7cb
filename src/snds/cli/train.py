"""``snds train``: its arguments, the run (:func:`snds.run.train_run`), and its summary."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

from snds.cli._args import check_arguments, data_arguments, index_list
from snds.cli._common import check_config, data_source, summarise
from snds.cli.refine import add_arguments as add_refine_arguments
from snds.cli.refine import run_refinement
from snds.phase import Phase
from snds.policy import DEFAULT_WARP_LAYERS, PolicyConfig
from snds.recipes import ARCHITECTURES, RECIPES, Recipe
from snds.run import SplitConfig, train_run
from snds.train import TrainConfig

__all__ = ["policy_config", "register", "run"]

#: The preset behind the flags' defaults (:data:`snds.recipes.RECIPES`).
DEFAULT = RECIPES["default"]
#: The preset of SE(3) pose models (their ``--shape-weight`` and ``--position-noise``).
POSE = RECIPES["pose"]


def register(commands: argparse._SubParsersAction) -> None:
    """Adds ``snds train`` to the subcommands."""
    parser = commands.add_parser("train", help="train a stable policy and evaluate it")
    data_arguments(parser, required=True)
    parser.add_argument("--seed", type=int, default=0, help="seed of weights and split")
    parser.add_argument("--out", type=Path, default=None, help="model directory")
    parser.add_argument("--plot", action="store_true", help="also write the plots")
    parser.add_argument("--test-fraction", type=float, default=0.2, help="held-out samples")
    parser.add_argument(
        "--test-demos",
        type=index_list,
        default=None,
        help="hold out these whole demonstrations (I,J,...) instead of random samples",
    )
    parser.add_argument("--steps", type=int, default=DEFAULT.train.steps, help="optimiser steps")
    parser.add_argument("--window", type=int, default=DEFAULT.train.window, help="Euler window Nw")
    parser.add_argument(
        "--velocity-loss", choices=["mse", "srvf"], default=DEFAULT.train.velocity_shape
    )
    parser.add_argument(
        "--nominal-weight",
        type=float,
        default=DEFAULT.train.nominal_weight,
        help="weight of the velocity term on the nominal field before the projection, which "
        "keeps a fit from stalling where the projection hides f's gradient (0: the paper's "
        "loss)",
    )
    parser.add_argument(
        "--position-noise",
        type=float,
        default=None,
        help="standard deviation of noise added to the training states (model coordinates, "
        "the data span about [-1, 1]), for demonstrations that run close together at "
        f"different speeds (default {DEFAULT.train.position_noise:g} for positions, "
        f"{POSE.train.position_noise:g} for SE(3) pose models; 0: off)",
    )
    parser.add_argument(
        "--noise-correction",
        type=float,
        default=None,
        help="gain k (per unit of model time) that pulls states back onto the demonstrated "
        f"paths: a share ({DEFAULT.train.correction_share:g}) of each batch is moved off the "
        f"data (noise {DEFAULT.train.correction_noise:g}) and trained towards the nearest "
        "sample's velocity minus k times its offset across the nearby paths (averaged over "
        f"a width of {DEFAULT.train.correction_width:g}) (default "
        f"{DEFAULT.train.noise_correction:g} for positions, {POSE.train.noise_correction:g} "
        "for SE(3) pose models; 0: off)",
    )
    parser.add_argument(
        "--tracking-gain",
        type=float,
        default=None,
        help="gain k (per unit of model time) that pulls a state with a phase back to where "
        f"its demonstration was at that phase: a share ({DEFAULT.train.tracking_share:g}) of "
        f"each batch is moved in position (noise {DEFAULT.train.tracking_noise:g}), the phase "
        "kept, and trained towards its sample's velocity minus k times the offset, so that a "
        f"pushed rollout returns onto its demonstration (default "
        f"{DEFAULT.train.tracking_gain:g}; only with a phase; 0: off)",
    )
    parser.add_argument(
        "--shape-weight",
        type=float,
        default=None,
        help="weight of the penalty that keeps V's sublevel sets round off the data, against "
        f"stiff fields (default {POSE.train.shape_weight:g} for SE(3) pose models, "
        f"{DEFAULT.train.shape_weight:g} (off) for positions)",
    )
    parser.add_argument(
        "--decay-rate",
        type=float,
        default=DEFAULT.policy.decay_rate,
        help="rho in a(x) = rho V(x); 0 (with --decay-far 0 --decay-near 0) is the paper's "
        "relaxed mode (dV/dt <= 0 only)",
    )
    parser.add_argument(
        "--decay-far",
        type=float,
        default=DEFAULT.policy.decay_far,
        help="extra decay rate per extent beyond the demonstrations' extent (0: off)",
    )
    parser.add_argument(
        "--decay-near",
        type=float,
        default=DEFAULT.policy.decay_near,
        help="extra decay rate at the target, fading out at 0.2 of the extent (0: off)",
    )
    parser.add_argument(
        "--warp-layers",
        type=int,
        default=DEFAULT.policy.warp_layers,
        help="coupling layers of a learned warp inside V, for demonstrations that wind back "
        f"and forth (default {DEFAULT_WARP_LAYERS} for states of dimension >= 2, poses "
        "included, 0 in 1-D; 0: off, V convex, about 1.5x faster training, see "
        "docs/design.md)",
    )
    parser.add_argument(
        "--warp-weight",
        type=float,
        default=DEFAULT.train.warp_weight,
        help="weight of the penalty that keeps the warp's Jacobian near the identity, against "
        f"stiff fields (default {DEFAULT.train.warp_weight:g}; 0: off)",
    )
    parser.add_argument(
        "--smooth-weight",
        type=float,
        default=DEFAULT.train.smooth_weight,
        help="weight of the penalty on the second difference of the nominal field's positions "
        "off the data, against ripples in streamlines and in rollouts from new starts "
        f"(default {DEFAULT.train.smooth_weight:g}: off; 3e-6 damps them, at a cost measured "
        "in docs/design.md)",
    )
    parser.add_argument("--unconstrained", action="store_true", help="behavioural cloning")
    parser.add_argument(
        "--architecture",
        choices=list(ARCHITECTURES),
        default="default",
        help="network sizes: default, or compact (hidden 64-64, 64 Fourier features: "
        "faster batches; measured in benchmarks/README.md)",
    )
    parser.add_argument("--device", default="cpu", help="torch device (cpu, cuda, ...)")
    parser.add_argument(
        "--resume",
        action="store_true",
        help="continue an interrupted run from OUT/checkpoint.safetensors (same arguments)",
    )
    parser.add_argument(
        "--checkpoint-every", type=int, default=200, help="steps between checkpoints"
    )
    add_refine_arguments(parser)
    check_arguments(parser)
    parser.add_argument(
        "--se3",
        action="store_true",
        help="learn a pose policy (position + orientation); automatic for pose files (CSV "
        "with columns qx,qy,qz,qw, NPZ with 'quat', poses in .npy/.mat/bags/datasets: "
        "docs/data.md); position data get synthetic orientations",
    )
    parser.add_argument(
        "--phase-codes",
        type=int,
        metavar="M",
        default=DEFAULT.phase.codes if DEFAULT.phase else 0,
        help="numbers M of the phase appended to the state, a code per demonstration, so "
        "that rollouts retrace demonstrations that cross or wind (default "
        f"{DEFAULT.phase.codes if DEFAULT.phase else 0}; 0: none, a field of the positions "
        "alone; see docs/data.md); a start then needs a phase",
    )
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    if args.init is not None:
        return run_refinement(args)
    phase = Phase(codes=args.phase_codes) if args.phase_codes else None
    train = _train_config(args, DEFAULT.train)
    recipe = Recipe(policy=policy_config(args), train=train, phase=phase)
    split = SplitConfig(
        test_fraction=args.test_fraction,
        test_demos=tuple(args.test_demos) if args.test_demos is not None else None,
    )
    result = train_run(
        data_source(args, poses=args.se3, seed=args.seed, phase=phase),
        args.out,
        recipe=recipe,
        seed=args.seed,
        split=split,
        check=check_config(args),
        plots=args.plot,
        resume=args.resume,
        checkpoint_every=args.checkpoint_every,
        progress=not args.quiet,
        threads=args.threads,
    )
    if not args.quiet:
        summarise(result.folder.path, result.metrics.to_dict())
    return 0


def _train_config(args: argparse.Namespace, base: TrainConfig) -> TrainConfig:
    """The optimisation settings of ``snds train``'s arguments, on ``base`` (the recipe of
    this kind of model), which gives ``--position-noise`` and ``--shape-weight`` their
    defaults; the seed is the run's."""
    return dataclasses.replace(
        base,
        steps=args.steps,
        window=args.window,
        velocity_shape=args.velocity_loss,
        nominal_weight=args.nominal_weight,
        position_noise=base.position_noise if args.position_noise is None else args.position_noise,
        noise_correction=(
            base.noise_correction if args.noise_correction is None else args.noise_correction
        ),
        tracking_gain=base.tracking_gain if args.tracking_gain is None else args.tracking_gain,
        shape_weight=base.shape_weight if args.shape_weight is None else args.shape_weight,
        warp_weight=args.warp_weight,
        smooth_weight=args.smooth_weight,
        device=args.device,
    )


def policy_config(args: argparse.Namespace) -> PolicyConfig:
    """The architecture that ``snds train``'s flags ask for, for positions and poses alike:
    the ``--architecture`` recipe's, with the flags' decay terms and warp."""
    return dataclasses.replace(
        RECIPES[args.architecture].policy,
        decay_rate=args.decay_rate,
        decay_far=args.decay_far,
        decay_near=args.decay_near,
        warp_layers=args.warp_layers,
        stable=not args.unconstrained,
    )
