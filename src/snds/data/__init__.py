"""Demonstrations: loading (LASA, .mat, .csv, .npz), common target, normalisation, splits."""

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
from snds.data.source import DataSource
from snds.data.targets import MAX_END_SPREAD, common_target

__all__ = [
    "MAX_END_SPREAD",
    "LASA_NAMES",
    "DataSource",
    "Demonstration",
    "DemonstrationSet",
    "Demonstrations",
    "Normalization",
    "Split",
    "common_target",
    "load_csv",
    "load_demonstrations",
    "load_lasa",
    "load_mat",
    "load_npz",
    "no_split",
    "split_demos",
    "split_samples",
]
