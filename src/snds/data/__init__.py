"""Demonstrations: loading (LASA, .mat, .csv, .npz, .npy, ROS bags, LeRobot, HDF5), common
target, normalisation, splits."""

from snds.data.demonstrations import (
    Demonstration,
    Demonstrations,
    DemonstrationSet,
    Normalization,
    Split,
    no_split,
    split_demos,
    split_samples,
)
from snds.data.files import load_csv, load_demonstrations, load_mat, load_npz
from snds.data.lasa import LASA_NAMES, load_lasa
from snds.data.options import LENGTH_UNITS, QUATERNION_ORDERS, ReadOptions
from snds.data.recordings import load_recording
from snds.data.source import DataSource
from snds.data.targets import MAX_END_SPREAD, common_target

__all__ = [
    "MAX_END_SPREAD",
    "LASA_NAMES",
    "LENGTH_UNITS",
    "QUATERNION_ORDERS",
    "DataSource",
    "Demonstration",
    "DemonstrationSet",
    "Demonstrations",
    "Normalization",
    "ReadOptions",
    "Split",
    "common_target",
    "load_csv",
    "load_demonstrations",
    "load_lasa",
    "load_mat",
    "load_npz",
    "load_recording",
    "no_split",
    "split_demos",
    "split_samples",
]
