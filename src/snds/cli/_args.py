"""Argument types and argument groups that several subcommands share."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from snds.data.gaps import GAP_MODES
from snds.data.options import LENGTH_UNITS, QUATERNION_ORDERS
from snds.stability import ROLLOUTS, SAMPLES

__all__ = ["check_arguments", "data_arguments", "index_list", "obstacle_arguments"]


def index_list(text: str) -> list[int]:
    try:
        return [int(part) for part in text.split(",") if part.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected comma-separated indices, got {text!r}"
        ) from None


def _demo_choice(text: str) -> int | list[int]:
    return index_list(text) if "," in text else index_list(text)[0]


def _end_spread(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not (math.isfinite(value) and value >= 0):
        raise argparse.ArgumentTypeError(f"expected a number >= 0, got {text!r}")
    return value


def data_arguments(parser: argparse.ArgumentParser, *, required: bool) -> None:
    source = parser.add_mutually_exclusive_group(required=required)
    source.add_argument("--motion", help="a LASA handwriting motion, e.g. Sine")
    source.add_argument(
        "--data",
        type=Path,
        help="demonstrations: .mat, .csv, .npz, .npy, a ROS bag (.mcap, .db3, rosbag2 folder, "
        ".bag) or a folder of bags, a LeRobot dataset folder, an HDF5 file (docs/data.md)",
    )
    parser.add_argument(
        "--demos",
        type=_demo_choice,
        default=None,
        help="K: the first K demonstrations; I,J,...: these demonstrations (0-based)",
    )
    parser.add_argument(
        "--max-end-spread",
        type=_end_spread,
        default=None,
        help="largest distance of a file's demonstration end from their common target, in "
        "extents (default 0.25; a model records the value it was trained with)",
    )
    parser.add_argument(
        "--gaps",
        choices=GAP_MODES,
        default=None,
        help="a .mat file's recording gaps: fill puts the dropped samples back (default), "
        "retime only gives the jump its time, as files were read before; a model records it",
    )
    _reading_arguments(parser)


def _positive(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"expected a number > 0, got {text!r}")
    return value


def _fraction(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not (math.isfinite(value) and 0 <= value < 1):
        raise argparse.ArgumentTypeError(f"expected a fraction in [0, 1), got {text!r}")
    return value


def _names(text: str) -> list[str]:
    return [part.strip() for part in text.split(",") if part.strip()]


def _reading_arguments(parser: argparse.ArgumentParser) -> None:
    """How a file is read (snds.data.ReadOptions; a model records what it was trained with)."""
    group = parser.add_argument_group("reading a recording (docs/data.md)")
    group.add_argument(
        "--rate",
        type=_positive,
        default=None,
        metavar="HZ",
        help="sampling rate of a file that stores no time stamps (.npy, .mat matrix, HDF5)",
    )
    group.add_argument(
        "--quaternion-order",
        choices=QUATERNION_ORDERS,
        default=None,
        help="order of a quaternion's numbers in unnamed columns (.npy, .mat, HDF5, LeRobot)",
    )
    group.add_argument(
        "--length-unit",
        choices=list(LENGTH_UNITS),
        default=None,
        help="unit of the file's positions, converted to metres (default: kept as stored)",
    )
    group.add_argument(
        "--trim-idle",
        type=_fraction,
        default=None,
        metavar="F",
        help="drop each demonstration's idle start and end, below F of its top speed "
        "(e.g. 0.01; default 0: keep every sample)",
    )
    group.add_argument("--topic", default=None, help="the ROS bag topic to read")
    group.add_argument("--frame", default=None, help="/tf: the transform's parent frame")
    group.add_argument("--child-frame", default=None, help="/tf: the transform's child frame")
    group.add_argument(
        "--columns",
        type=_names,
        default=None,
        metavar="C1[,C2...]",
        help="LeRobot state columns (default observation.state)",
    )
    group.add_argument(
        "--key",
        default=None,
        help="HDF5 obs key(s) K1[,K2], or a .mat pose matrix VARIABLE[.FIELD]",
    )
    group.add_argument(
        "--split-rests",
        type=_positive,
        default=None,
        metavar="SECONDS",
        help="split one long recording into demonstrations at rests this long",
    )


def check_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--rollouts", type=int, default=ROLLOUTS, help="random starts of the stability check"
    )
    parser.add_argument(
        "--samples", type=int, default=SAMPLES, help="states of the decrease-condition check"
    )
    parser.add_argument(
        "--grid", action="store_true", help="stability rollouts from a grid, not random starts"
    )


def obstacle_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--obstacle",
        action="append",
        default=[],
        metavar="SPEC",
        help="an obstacle (repeatable): sphere:CX,CY[,CZ],R, ellipsoid:CX,CY[,CZ],A1,A2[,A3] "
        "(semi-axes) or box:CX,CY[,CZ],H1,H2[,H3] (half-widths), then options margin=M, "
        "influence=D, angle=DEG (2-D) or angles=A/B/C (3-D), velocity=V1/V2[/V3]; "
        "docs/obstacles.md",
    )
    parser.add_argument(
        "--workspace",
        default=None,
        metavar="SPEC",
        help="box:CX,CY[,CZ],H1,H2[,H3][,margin=M]: the box the motion must stay in",
    )
    parser.add_argument(
        "--scene", type=Path, default=None, help="obstacles and workspace from a .json/.yaml file"
    )
