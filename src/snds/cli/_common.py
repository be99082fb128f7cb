"""What several subcommands share: data loading, splits, obstacles, plots and summaries."""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from snds.data import (
    MAX_END_SPREAD,
    Demonstrations,
    Split,
    load_demonstrations,
    load_lasa,
    no_split,
    split_demos,
    split_samples,
)
from snds.data.poses import is_pose_file, load_poses, with_synthetic_orientations
from snds.errors import ConfigError, SNDSError
from snds.models import load_model
from snds.obstacles import Scene, load_scene, parse_obstacle, parse_workspace
from snds.plotting import plot_all, plot_obstacles
from snds.policy import Policy, StablePolicy
from snds.spaces import SE3, Euclidean
from snds.stability import CheckConfig


def _scene(args: argparse.Namespace):
    """The obstacles of ``--scene``, ``--obstacle`` and ``--workspace``; None without any."""
    if not (args.obstacle or args.workspace or args.scene):
        return None
    base = load_scene(args.scene) if args.scene is not None else Scene()
    obstacles = base.obstacles + tuple(parse_obstacle(spec) for spec in args.obstacle)
    workspace = parse_workspace(args.workspace) if args.workspace else base.workspace
    return Scene(obstacles=obstacles, workspace=workspace)


def _load_data(
    motion: str | None,
    data: Path | None,
    demos: int | list[int] | None,
    max_end_spread: float | None = None,
) -> Demonstrations:
    spread = MAX_END_SPREAD if max_end_spread is None else max_end_spread
    if motion is None and demos is not None:
        # Selected before the target is chosen: a file may end at several places.
        select = list(range(demos)) if isinstance(demos, int) else demos
        return load_demonstrations(data, select=select, max_end_spread=spread)
    if motion is not None:
        loaded = load_lasa(motion)
    else:
        loaded = load_demonstrations(data, max_end_spread=spread)
    if demos is None:
        return loaded
    return loaded.first(demos) if isinstance(demos, int) else loaded.select(demos)


def _make_split(demos: Demonstrations, record: dict) -> Split:
    """The split described by a ``split`` record of model.json."""
    if record.get("test_demos"):
        return split_demos(demos, test_demos=record["test_demos"])
    fraction = float(record.get("test_fraction", 0.0))
    if fraction <= 0:
        return no_split(demos)
    return split_samples(demos, test_fraction=fraction, seed=int(record.get("seed", 0)))


def _source(args: argparse.Namespace) -> dict:
    if args.motion is not None:
        return {"motion": args.motion, "demos": args.demos}
    spread = MAX_END_SPREAD if args.max_end_spread is None else args.max_end_spread
    return {"file": str(Path(args.data).resolve()), "demos": args.demos, "max_end_spread": spread}


def _check_sizes(args: argparse.Namespace) -> None:
    """Refuses stability-check sizes that would fail only after training, before any work."""
    if args.rollouts < 1:
        raise ConfigError(f"--rollouts must be >= 1, got {args.rollouts}")
    if args.samples < 0:
        raise ConfigError(f"--samples must be >= 0, got {args.samples}")


def _check_config(args: argparse.Namespace) -> CheckConfig:
    """The stability check that ``--rollouts``, ``--samples``, ``--grid`` and ``--seed`` ask
    for (the library's :class:`~snds.stability.CheckConfig` for everything else)."""
    _check_sizes(args)
    return CheckConfig(rollouts=args.rollouts, samples=args.samples, grid=args.grid, seed=args.seed)


def _model_and_data(args: argparse.Namespace) -> tuple[Policy, dict, Demonstrations]:
    """A saved model, its record, and the demonstrations it was trained on (or those that
    ``--motion`` / ``--data`` name), in the model's space: poses for a pose model."""
    policy, description = load_model(args.model)
    source = description.get("data", {})
    poses = isinstance(policy.space, SE3)
    seed = int(source.get("orientation_seed", 0))
    if args.motion is not None or args.data is not None:
        demos = _task_data(
            args.motion, args.data, args.demos, args.max_end_spread, poses=poses, seed=seed
        )
    elif "motion" in source or "file" in source:
        data = Path(source["file"]) if "file" in source else None
        spread = source.get("max_end_spread")
        demos = _task_data(
            source.get("motion"), data, source.get("demos"), spread, poses=poses, seed=seed
        )
    else:
        raise SNDSError(f"{args.model}: no data recorded; pass --motion or --data")
    width = demos[0].states.shape[1]
    if width != policy.space.dim:
        raise SNDSError(
            f"the data has dimension {width}, the model in {args.model} {policy.space.dim}"
        )
    return policy, description, demos


def _refuse_obstacles(policy: Policy, command: str) -> None:
    """Obstacles are for position models here (``snds simulate`` takes both)."""
    if not isinstance(policy.space, Euclidean):
        raise ConfigError(f"obstacles: snds {command} takes position models (simulate: both)")


def _task_data(
    motion: str | None,
    data: Path | None,
    demos: int | list[int] | None,
    max_end_spread: float | None,
    *,
    poses: bool,
    seed: int,
):
    """Positions (:func:`_load_data`), or with ``poses`` pose demonstrations
    (:func:`_pose_data`, synthetic orientations seeded by ``seed``)."""
    if poses:
        return _pose_data(motion, data, demos, seed, max_end_spread)
    return _load_data(motion, data, demos, max_end_spread)


def _write_plots(
    policy: StablePolicy,
    demos: Demonstrations,
    out: Path,
    history: list[float] | None,
    scene=None,
) -> list[Path]:
    policy = policy.to(torch.float64).eval()
    if scene is not None:
        return [plot_obstacles(policy, demos, scene, out / "obstacles.png")]
    return plot_all(policy, demos, out, history=history)


def _summarise(out: Path, metrics: dict) -> None:
    stability = metrics["stability"]
    seconds = metrics.get("train_seconds")
    timing = f"trained in {seconds:.1f} s, " if seconds is not None else ""
    angles = (
        f"orientation error {metrics['angle_error_along']:.4f} rad along the path, "
        f"{metrics['final_angle_error']:.4f} rad at the end, "
        if "angle_error_along" in metrics
        else ""
    )
    print(
        f"{out}: {timing}velocity MSE {metrics['velocity_mse_paper']:.4f} (paper scale), "
        f"DTW {metrics['dtw_paper']:.4f} (paper scale), {angles}"
        f"converged {stability['converged_fraction']:.3f} of {stability['rollouts']} rollouts, "
        f"{stability['decrease_violations']} decrease violations in "
        f"{stability['samples_checked']} samples" + _guard_summary(stability)
    )


def _guard_summary(stability: dict) -> str:
    if stability.get("integrator") != "guarded euler":
        return ""
    return (
        f"; largest safe Euler step {stability['largest_safe_dt']:.3g} s "
        f"(data: {stability['dt']:.3g} s), guard shortened steps in "
        f"{stability['shortened_fraction']:.0%} of rollouts"
    )


def _is_pose_file(path: Path) -> bool:
    return is_pose_file(path)


def _pose_data(
    motion: str | None, data: Path | None, demos, seed: int, max_end_spread: float | None = None
):
    """Pose demonstrations: a pose file as it is, or position data (LASA, .mat, ...) lifted
    with synthetic orientations seeded by ``seed`` (see
    :func:`snds.data.poses.with_synthetic_orientations`)."""
    if data is not None and _is_pose_file(data):
        select = list(range(demos)) if isinstance(demos, int) else demos
        spread = MAX_END_SPREAD if max_end_spread is None else max_end_spread
        return load_poses(data, select=select, max_end_spread=spread)
    loaded = _load_data(motion, data, demos, max_end_spread)
    return with_synthetic_orientations(loaded, seed=seed)
