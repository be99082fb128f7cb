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
from snds.errors import ConfigError, SNDSError
from snds.models import load_model
from snds.obstacles import Scene, load_scene, parse_obstacle, parse_workspace
from snds.plotting import plot_all, plot_obstacles
from snds.policy import StablePolicy


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


def _model_and_data(args: argparse.Namespace) -> tuple[StablePolicy, dict, Demonstrations]:
    policy, description = load_model(args.model)
    if args.motion is None and args.data is None:
        source = description.get("data", {})
        if "motion" in source:
            demos = _load_data(source["motion"], None, source.get("demos"))
        elif "file" in source:
            demos = _load_data(
                None, Path(source["file"]), source.get("demos"), source.get("max_end_spread")
            )
        else:
            raise SNDSError(f"{args.model}: no data recorded; pass --motion or --data")
    else:
        demos = _load_data(args.motion, args.data, args.demos, args.max_end_spread)
    if demos.dim != policy.dim:
        raise SNDSError(
            f"the data has dimension {demos.dim}, the model in {args.model} {policy.dim}"
        )
    return policy, description, demos


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
    print(
        f"{out}: {timing}velocity MSE {metrics['velocity_mse_paper']:.4f} (paper scale), "
        f"DTW {metrics['dtw_paper']:.4f} (paper scale), "
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


# --- SE(3) pose policies (snds.se3) ------------------------------------------------------------


def _is_pose_file(path: Path) -> bool:
    from snds.data.poses import is_pose_file

    return is_pose_file(path)


def _is_pose_model(directory: Path) -> bool:
    from snds.io import read_description

    return read_description(directory).get("kind") == "se3"


def _pose_data(
    motion: str | None, data: Path | None, demos, seed: int, max_end_spread: float | None = None
):
    """Pose demonstrations: a pose file as it is, or position data (LASA, .mat, ...) lifted
    with synthetic orientations seeded by ``seed`` (see
    :func:`snds.data.poses.with_synthetic_orientations`)."""
    from snds.data.poses import load_poses, with_synthetic_orientations

    if data is not None and _is_pose_file(data):
        select = list(range(demos)) if isinstance(demos, int) else demos
        spread = MAX_END_SPREAD if max_end_spread is None else max_end_spread
        return load_poses(data, select=select, max_end_spread=spread)
    loaded = _load_data(motion, data, demos, max_end_spread)
    return with_synthetic_orientations(loaded, seed=seed)


def _pose_model_and_data(args: argparse.Namespace):
    policy, description = load_model(args.model)
    source = description.get("data", {})
    seed = int(source.get("orientation_seed", 0))
    if args.motion is not None or args.data is not None:
        poses = _pose_data(args.motion, args.data, args.demos, seed, args.max_end_spread)
    elif "motion" in source or "file" in source:
        data = Path(source["file"]) if "file" in source else None
        spread = source.get("max_end_spread")
        poses = _pose_data(source.get("motion"), data, source.get("demos"), seed, spread)
    else:
        raise SNDSError(f"{args.model}: no data recorded; pass --motion or --data")
    return policy, description, poses


def _summarise_se3(out: Path, metrics: dict) -> None:
    stability = metrics["stability"]
    seconds = metrics.get("train_seconds")
    timing = f"trained in {seconds:.1f} s, " if seconds is not None else ""
    print(
        f"{out}: {timing}position DTW {metrics['position_dtw_paper']:.4f} (paper scale), "
        f"orientation error {metrics['orientation_error_along']:.4f} rad along the path, "
        f"{metrics['final_orientation_error']:.4f} rad at the end; converged "
        f"{stability['converged_fraction']:.3f} of {stability['rollouts']} random poses, "
        f"{stability['decrease_violations']} decrease violations in "
        f"{stability['samples_checked']} samples"
    )
