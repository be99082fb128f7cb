"""Property-based tests: random bytes, text, JSON and demonstrations at the loaders and at fit.

The property is always the same: the call returns something valid, or raises the library's
own error for the input (a DataError, ModelFileError, ...), never anything else.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, assume, example, given, settings
from hypothesis import strategies as st

from snds.data import (
    Demonstration,
    Demonstrations,
    Normalization,
    load_demonstrations,
    no_split,
)
from snds.errors import DataError, ModelFileError, SNDSError
from snds.models import load_model, save_model
from snds.policy import StablePolicy
from snds.train import TrainConfig, fit

from conftest import SMALL, make_policy, spiral_demos

FUZZ = settings(deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


@pytest.fixture(autouse=True, scope="module")
def one_thread():
    """One torch thread, as the CLI uses: two threads on a busy 2-core machine crawl."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def check_demonstrations(demos: Demonstrations) -> None:
    """What every loader promises of what it returns."""
    assert len(demos) >= 1
    for demo in demos:
        assert demo.positions.shape == demo.velocities.shape and demo.dim == demos.dim
        assert np.isfinite(demo.positions).all() and np.isfinite(demo.velocities).all()
        assert (np.diff(demo.times) > 0).all()
        assert np.array_equal(demo.positions[-1], demos.target)


# Loaders.


@settings(FUZZ, max_examples=150)
@given(data=st.binary(max_size=600), suffix=st.sampled_from([".csv", ".mat", ".npz"]))
def test_random_bytes_are_demonstrations_or_a_data_error(data, suffix, tmp_path_factory):
    path = tmp_path_factory.getbasetemp() / f"random{suffix}"
    path.write_bytes(data)
    try:
        demos = load_demonstrations(path, max_end_spread=1e9)
    except DataError as error:
        assert path.name in str(error) and "\n" not in str(error)
        return
    check_demonstrations(demos)


NAMES = st.sampled_from(["demo", "t", "x1", "x2", "x3", "v1", "v2", "v3", "dmeo", "time", ""])
FIELDS = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.floats(-1e3, 1e3).map(lambda v: f"{v:.6g}"),
    st.integers(-5, 5).map(str),
    st.sampled_from(["", " ", "a", "nan", "-inf", "1e400", "0x10", "1,5", '"2"']),
)


@st.composite
def csv_files(draw) -> str:
    """Mostly well-formed CSV text: a header that is often right, rows that are often valid."""
    n = draw(st.integers(1, 3))
    header = ["demo", "t", *(f"x{i}" for i in range(1, n + 1))]
    if draw(st.booleans()):
        header += [f"v{i}" for i in range(1, n + 1)]
    if draw(st.integers(0, 4)) == 0:
        header = draw(st.lists(NAMES, min_size=0, max_size=8))
    lines = [",".join(header)]
    for label in range(draw(st.integers(0, 3))):
        time = 0.0
        for _ in range(draw(st.integers(0, 6))):
            time += draw(st.sampled_from([0.01, 0.1, 1.0, 0.0, -0.1]))
            values = [str(label), repr(time)]
            values += [draw(FIELDS) for _ in range(len(header) - 2)]
            if draw(st.integers(0, 9)) == 0:
                values = values[: draw(st.integers(0, len(values)))]
            lines.append(",".join(values))
    return "\n".join(lines) + draw(st.sampled_from(["\n", "", "\n\n"]))


@settings(FUZZ, max_examples=200)
@given(text=csv_files())
def test_random_csv_is_demonstrations_or_a_data_error(text, tmp_path_factory):
    path = tmp_path_factory.getbasetemp() / "random.csv"
    path.write_text(text)
    try:
        demos = load_demonstrations(path, max_end_spread=1e9)
    except DataError as error:
        assert "random.csv" in str(error) and "\n" not in str(error)
        return
    check_demonstrations(demos)


# Model files.

JSON = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(-(2**40), 2**40)
    | st.floats(allow_nan=True, allow_infinity=True)
    | st.text(max_size=5),
    lambda children: (
        st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=8), children, max_size=4)
    ),
    max_leaves=10,
)


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    directory = tmp_path_factory.mktemp("fuzz") / "model"
    save_model(make_policy(spiral_demos(count=1, samples=50), seed=1), directory)
    return directory, json.loads((directory / "model.json").read_text())


def paths(record, prefix=()):
    """Every key path into a nested JSON record."""
    yield prefix
    if isinstance(record, dict):
        for key, value in record.items():
            yield from paths(value, (*prefix, key))


@settings(FUZZ, max_examples=120)
@given(data=st.data())
def test_a_tampered_model_json_loads_or_is_a_model_file_error(saved, data):
    # GIVEN a saved model whose description has one field replaced by any JSON value
    directory, original = saved
    record = json.loads(json.dumps(original))
    where = data.draw(st.sampled_from(list(paths(record))[1:]))
    value = data.draw(JSON)
    target = record
    for key in where[:-1]:
        target = target[key]
    target[where[-1]] = value
    (directory / "model.json").write_text(json.dumps(record))
    try:
        # WHEN it is loaded THEN it loads, or a ModelFileError says why not
        try:
            policy, _ = load_model(directory)
        except ModelFileError as error:
            assert "\n" not in str(error)
            return
        assert isinstance(policy, StablePolicy)
    finally:
        (directory / "model.json").write_text(json.dumps(original))


@settings(FUZZ, max_examples=80)
@given(flips=st.lists(st.tuples(st.integers(0, 10**6), st.integers(1, 255)), max_size=4))
def test_damaged_weights_are_a_model_file_error(saved, flips):
    # GIVEN a model whose weights file has a few bytes changed (its hash no longer matches)
    directory, _ = saved
    weights = directory / "model.safetensors"
    original = weights.read_bytes()
    damaged = bytearray(original)
    for where, mask in flips:
        damaged[where % len(damaged)] ^= mask
    assume(bytes(damaged) != original)
    weights.write_bytes(bytes(damaged))
    try:
        with pytest.raises(ModelFileError):
            load_model(directory)
    finally:
        weights.write_bytes(original)


# fit.

MAGNITUDES = st.sampled_from([1e-6, 1e-3, 1.0, 1e3, 1e6])


@st.composite
def demonstration_sets(draw) -> Demonstrations:
    """Random motions of any size and scale, ending at a common target (or raising)."""
    dim, count = draw(st.integers(1, 3)), draw(st.integers(1, 3))
    scale = draw(MAGNITUDES)
    values = st.floats(-10, 10, allow_nan=False, allow_infinity=False)
    demos = []
    for _ in range(count):
        length = draw(st.integers(2, 12))
        positions = np.array(draw(st.lists(values, min_size=length * dim, max_size=length * dim)))
        positions = positions.reshape(length, dim) * scale
        positions[-1] = 0.0
        velocities = np.array(draw(st.lists(values, min_size=length * dim, max_size=length * dim)))
        steps = np.array(draw(st.lists(st.floats(1e-3, 1.0), min_size=length, max_size=length)))
        demos.append(
            Demonstration(positions, velocities.reshape(length, dim) * scale, np.cumsum(steps))
        )
    return Demonstrations(tuple(demos), np.zeros(dim), "random")


#: Found by the test: an extent that rounds to 0 in a float32 policy made every state NaN.
BELOW_FLOAT32 = Demonstrations(
    (
        Demonstration(
            np.array([[6.7e-118], [0.0]]), np.array([[0.0], [1e-6]]), np.array([1.0, 2.0])
        ),
    ),
    np.zeros(1),
    "random",
)


@settings(FUZZ, max_examples=30)
@given(
    demos=demonstration_sets(),
    window=st.integers(0, 2),
    dtype=st.sampled_from(["float32", "float64"]),
)
@example(demos=BELOW_FLOAT32, window=0, dtype="float32")
def test_fit_on_random_demonstrations_is_finite_or_a_data_error(demos, window, dtype):
    # GIVEN any demonstrations, of any scale
    try:
        normalization = Normalization.fit(demos)
    except DataError:
        return  # motionless: refused with a message (docs/bad-input.md)
    policy = StablePolicy(dim=demos.dim, normalization=normalization, config=SMALL)
    config = TrainConfig(steps=3, window=window, dtype=dtype, batch_size=8, window_batch_size=4)
    # WHEN a policy is fitted THEN the loss is finite and so is the policy everywhere near
    try:
        result = fit(policy, demos, no_split(demos), config, progress=False)
    except SNDSError:
        return
    assert all(math.isfinite(value) for value in result.history)
    x = torch.as_tensor(np.concatenate([d.positions for d in demos]) * 3.0)
    with torch.no_grad():
        assert torch.isfinite(policy(x)).all()
