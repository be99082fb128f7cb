"""What several subcommands share: data loading, splits, obstacles, plots and summaries."""

from __future__ import annotations

import argparse
import zipfile
from pathlib import Path

import torch

from snds.data import (
    MAX_END_SPREAD,
    DataSource,
    Demonstrations,
)
from snds.data.options import ReadOptions
from snds.errors import ConfigError, ModelFileError, SNDSError
from snds.models import load_model
from snds.obstacles import Scene, load_scene, parse_obstacle, parse_workspace
from snds.phase import Phase, StartRule, start_rule
from snds.plotting import plot_all, plot_obstacles
from snds.policy import Policy, StablePolicy
from snds.spaces import SE3
from snds.stability import CheckConfig

__all__ = [
    "READING_FIELDS",
    "check_config",
    "data_source",
    "model_and_data",
    "refuse_obstacles",
    "scene_of",
    "start_rule_of",
    "summarise",
    "summary",
    "write_plots",
]

#: The reading options of :class:`~snds.data.DataSource` that flags of the same name set.
READING_FIELDS = tuple(ReadOptions.__dataclass_fields__)


def scene_of(args: argparse.Namespace):
    """The obstacles of ``--scene``, ``--obstacle`` and ``--workspace``; None without any."""
    if not (args.obstacle or args.workspace or args.scene):
        return None
    base = load_scene(args.scene) if args.scene is not None else Scene()
    obstacles = base.obstacles + tuple(parse_obstacle(spec) for spec in args.obstacle)
    workspace = parse_workspace(args.workspace) if args.workspace else base.workspace
    return Scene(obstacles=obstacles, workspace=workspace)


def data_source(
    args: argparse.Namespace, *, poses: bool = False, seed: int = 0, phase: Phase | None = None
) -> DataSource:
    """The demonstrations that ``--motion`` / ``--data``, ``--demos``, ``--max-end-spread``
    and ``--gaps`` name (the library's default gap mode where not given), read with the
    reading flags given (``--rate``, ``--quaternion-order``, ...: :data:`READING_FIELDS`);
    with ``poses`` in SE(3) (synthetic orientations seeded by ``seed`` for position data;
    automatic for a pose file); with ``phase`` appended (:mod:`snds.phase`)."""
    spread = MAX_END_SPREAD if args.max_end_spread is None else args.max_end_spread
    given = {name: getattr(args, name, None) for name in READING_FIELDS}
    return DataSource(
        motion=args.motion,
        file=args.data,
        demos=args.demos,
        max_end_spread=spread,
        poses=poses,
        orientation_seed=seed,
        phase=phase,
        **({"gaps": args.gaps} if args.gaps else {}),
        **{name: value for name, value in given.items() if value is not None},
    )


def _check_sizes(args: argparse.Namespace) -> None:
    """Refuses stability-check sizes that would fail only after training, before any work."""
    if args.rollouts < 1:
        raise ConfigError(f"--rollouts must be >= 1, got {args.rollouts}")
    if args.samples < 0:
        raise ConfigError(f"--samples must be >= 0, got {args.samples}")


def check_config(args: argparse.Namespace) -> CheckConfig:
    """The stability check that ``--rollouts``, ``--samples``, ``--grid`` and ``--seed`` ask
    for (the library's :class:`~snds.stability.CheckConfig` for everything else)."""
    _check_sizes(args)
    return CheckConfig(rollouts=args.rollouts, samples=args.samples, grid=args.grid, seed=args.seed)


def model_and_data(args: argparse.Namespace) -> tuple[Policy, dict, Demonstrations]:
    """A saved model, its record, and the demonstrations it was trained on (or those that
    ``--motion`` / ``--data`` name), in the model's space: poses for a pose model."""
    _refuse_zip(Path(args.model))
    policy, description = load_model(args.model)
    recorded = description.get("data") or {}
    poses = isinstance(policy.space, SE3)
    if args.motion is not None or args.data is not None:
        seed = int(recorded.get("orientation_seed", 0))
        phase = Phase.from_record(recorded["phase"]) if "phase" in recorded else None
        source = data_source(args, poses=poses, seed=seed, phase=phase)
    elif "motion" in recorded or "file" in recorded:
        source = DataSource.from_record(recorded, poses=poses)
    else:
        raise SNDSError(f"{args.model}: no data recorded; pass --motion or --data")
    demos = source.load()
    width = demos[0].states.shape[1]
    if width != policy.space.dim:
        raise SNDSError(
            f"the data has dimension {width}, the model in {args.model} {policy.space.dim}"
        )
    return policy, description, demos


def _refuse_zip(path: Path) -> None:
    """A zipped model folder (the page's Model .zip) is refused with the command that unzips
    it: the commands read and write the folder's files in place."""
    if not (path.is_file() and zipfile.is_zipfile(path)):
        return
    with zipfile.ZipFile(path) as archive:
        folders = {Path(name).parts[0] for name in archive.namelist() if len(Path(name).parts) > 1}
    folder = next(iter(folders)) if len(folders) == 1 else "FOLDER"
    raise ModelFileError(
        f"{path}: a zip archive, not a model folder; unzip it first: unzip {path} -d "
        f"{path.parent} and pass {path.parent / folder}"
    )


def refuse_obstacles(policy: Policy, command: str) -> None:
    """Obstacles are for position models without a phase here (``snds simulate`` takes
    poses too)."""
    space = policy.space
    if space.dim != space.position_dim:
        raise ConfigError(
            f"obstacles: snds {command} takes position models without a phase (simulate: poses too)"
        )


def write_plots(
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


def summarise(out: Path, metrics: dict) -> None:
    """Prints the one-line summary of an evaluation (``snds train``, ``snds evaluate``)."""
    print(f"{out}: {summary(metrics)}")


def summary(metrics: dict) -> str:
    """The one-line summary of an :func:`snds.evaluate.evaluate` record: fit, retracing,
    arrival from the check's starts, the decrease check, stiffness, then its warnings."""
    stability = metrics["stability"]
    seconds = metrics.get("train_seconds")
    parts = [f"trained in {seconds:.3g} s"] if seconds is not None else []
    fit = (
        f"velocity MSE {metrics['velocity_mse_paper']:.3g} (paper scale), "
        f"DTW {metrics['dtw_paper']:.3g} (paper scale)"
    )
    if "angle_error_along" in metrics:
        fit += (
            f", orientation error {metrics['angle_error_along']:.3g} rad along the path, "
            f"{metrics['final_angle_error']:.3g} rad at the end"
        )
    parts.append(fit)
    if "retrace_frechet_max" in metrics:
        parts.append(
            f"from the demonstrations' starts Frechet {100 * metrics['retrace_frechet_max']:.3g} "
            f"% of the extent at worst, {100 * metrics['retrace_frechet_median']:.3g} % median"
        )
    parts.append(_arrival_summary(stability))
    parts.append(
        f"{stability['decrease_violations']} decrease violations in "
        f"{stability['samples_checked']} samples"
    )
    if stability.get("integrator") == "guarded euler":
        parts.append(
            f"largest safe Euler step {stability['largest_safe_dt']:.3g} s "
            f"(data: {stability['dt']:.3g} s), guard shortened steps in "
            f"{100 * stability['shortened_fraction']:.3g} % of rollouts"
        )
    parts += [f"WARNING: {warning}" for warning in metrics.get("warnings", [])]
    return "; ".join(parts)


def _arrival_summary(stability: dict) -> str:
    """'arrived from N of M random starts, median ... s (...x the longest demonstration)'."""
    rollouts = stability["rollouts"]
    arrived = round(stability["converged_fraction"] * rollouts)
    text = f"arrived from {arrived} of {rollouts} random starts"
    median = stability.get("time_to_arrive_median")
    if arrived and median is not None:
        text += (
            f" in {median:.3g} s median ({stability['time_to_arrive_median_durations']:.3g}x "
            f"the longest demonstration), {stability['time_to_arrive_max']:.3g} s at most "
            f"({stability['time_to_arrive_max_durations']:.3g}x)"
        )
    if arrived < rollouts:
        text += f", {stability['still_moving']} still moving at {stability['horizon']:.3g} s"
    return text


def start_rule_of(model: Path, description: dict) -> StartRule:
    """How a new start gets its phase (:func:`snds.phase.start_rule`), from the
    demonstrations a model with a phase was trained on (its ``model.json`` record)."""
    recorded = description.get("data") or {}
    if "phase" not in recorded:
        raise SNDSError(f"{model}: a model with a phase, but model.json records no phase")
    poses = description.get("kind") == "se3"
    return start_rule(DataSource.from_record(recorded, poses=poses).load())
