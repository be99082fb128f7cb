"""Loaders of user files: the shared LPV-DS files, round trips, and every kind of bad input."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
import scipy.io
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from snds.data import (
    Demonstration,
    Demonstrations,
    load_csv,
    load_demonstrations,
    load_mat,
    load_npz,
)
from snds.data.files import DEFAULT_DT, LOADERS
from snds.errors import DataError

SHARED = Path(__file__).resolve().parents[2].parent / "shared" / "data"


def shared_file(name: str) -> Path:
    path = SHARED / name
    if not path.is_file():
        pytest.skip(
            f"shared demonstration file {path} is absent (the project reads ../shared/data)"
        )
    return path


def quadratic_demos(
    count: int = 3, length: int = 40, dim: int = 2, *, seed: int = 0, uneven: bool = True
) -> list[Demonstration]:
    """Demos x(t) = x* + c (T - t)^2 with exact velocities, all ending exactly at x* = 1."""
    rng = np.random.default_rng(seed)
    demos = []
    for _ in range(count):
        steps = rng.uniform(0.5, 1.5, size=length - 1) if uneven else np.ones(length - 1)
        times = np.concatenate([[0.0], np.cumsum(0.01 * steps)])
        left = times[-1] - times
        c = rng.normal(size=dim) * 50
        positions = 1.0 + c * left[:, None] ** 2
        demos.append(Demonstration(positions, -2 * c * left[:, None], times))
    return demos


def write_csv(
    path: Path,
    demos: list[Demonstration],
    *,
    velocities: bool = True,
    labels: list[str] | None = None,
) -> Path:
    """Writes ``demos`` in the CSV layout, with exact (repr) numbers."""
    n = demos[0].dim
    names = ["demo", "t", *(f"x{i}" for i in range(1, n + 1))]
    names += [f"v{i}" for i in range(1, n + 1)] if velocities else []
    lines = [",".join(names)]
    for label, demo in zip(labels or range(len(demos)), demos, strict=True):
        for t, x, v in zip(demo.times, demo.positions, demo.velocities, strict=True):
            numbers = [t, *x, *(v if velocities else [])]
            lines.append(",".join([str(label), *(repr(float(value)) for value in numbers)]))
    path.write_text("\n".join(lines) + "\n")
    return path


def assert_same_demos(loaded: Demonstrations, demos: list[Demonstration]) -> None:
    assert len(loaded) == len(demos)
    for got, want in zip(loaded, demos, strict=True):
        np.testing.assert_array_equal(got.positions, want.positions)
        np.testing.assert_array_equal(got.velocities, want.velocities)
        # dt * arange (a .mat with dt) and a cumulative sum of steps differ by rounding only.
        np.testing.assert_allclose(got.times, want.times, rtol=1e-12, atol=0)


# The shared LPV-DS files.


def test_messy_snake_is_cut_after_each_zero_velocity_sample():
    path = shared_file("Messy_snake.mat")
    raw = scipy.io.loadmat(path)["Data"]
    demos = load_mat(path)
    assert [len(demo.times) for demo in demos] == [637, 504, 451]
    np.testing.assert_array_equal(demos.target, [0.0, 0.0])
    blocks = np.split(raw, [637, 637 + 504], axis=1)
    for demo, block in zip(demos, blocks, strict=True):
        # Already at the common target: the recorded samples come back untouched.
        np.testing.assert_array_equal(demo.positions, block[:2].T)
        np.testing.assert_array_equal(demo.velocities, block[2:].T)
        np.testing.assert_array_equal(demo.velocities[-1], [0.0, 0.0])


def test_messy_snake_times_make_velocities_agree_with_positions():
    # The file has no dt: each demonstration's step is the one that best fits its velocities.
    demos = load_mat(shared_file("Messy_snake.mat"))
    for demo in demos:
        steps = np.diff(demo.positions, axis=0)
        mean_velocities = (demo.velocities[1:] + demo.velocities[:-1]) / 2

        def misfit(scale: float, demo=demo, steps=steps, v=mean_velocities) -> float:
            return float(np.sum((steps - scale * demo.dt[:, None] * v) ** 2))

        assert misfit(1.0) < min(misfit(0.97), misfit(1.03))
        assert misfit(1.0) < 0.01 * np.sum(steps**2)


def test_cshape_top_ends_exactly_at_the_mean_end():
    path = shared_file("3D_Cshape_top.mat")
    cells = list(scipy.io.loadmat(path)["data"].ravel())
    demos = load_mat(path)
    assert len(demos) == 12 and demos.dim == 3
    np.testing.assert_allclose(demos.target, np.mean([cell[:3, -1] for cell in cells], axis=0))
    for demo, cell in zip(demos, cells, strict=True):
        assert np.array_equal(demo.positions[-1], demos.target)
        np.testing.assert_array_equal(demo.positions[0], cell[:3, 0])


@pytest.mark.parametrize("name", ["3D_viapoint_1.mat", "3D-pick-box.mat", "3D_sink.mat"])
def test_stored_dt_is_used_and_the_estimate_recovers_it(name, tmp_path):
    path = shared_file(name)
    contents = scipy.io.loadmat(path)
    dt = contents["dt"].item()
    for demo in load_mat(path, max_end_spread=0.5, gaps="retime"):
        # Every step is the stored one but where samples are missing (see retime_gaps).
        steps = np.diff(demo.times)
        stored = np.isclose(steps, dt, rtol=1e-9)
        assert np.all(stored | (steps > dt)) and stored.mean() > 0.99
    for demo in load_mat(path, max_end_spread=0.5):
        # Filled gaps (the default) take steps of at least the stored one, and less than twice.
        steps = np.diff(demo.times)
        assert np.all(steps >= dt * (1 - 1e-9)) and np.all(steps < 2 * dt)
    # GIVEN the same demonstrations without their dt
    stripped = tmp_path / name
    scipy.io.savemat(stripped, {"data": contents["data"]})
    # THEN each demonstration's estimated step is the stored one, despite the position jumps
    for demo in load_mat(stripped, max_end_spread=0.5):
        assert demo.dt[0] == pytest.approx(dt, rel=0.01)


@pytest.mark.parametrize("name", ["3D_Cshape_top.mat", "3D_viapoint_1.mat", "3D_sink.mat"])
def test_filled_gaps_make_each_recording_a_continuous_tube(name):
    path = shared_file(name)
    kept = load_mat(path, max_end_spread=0.5, gaps="retime")
    filled = load_mat(path, max_end_spread=0.5)

    def largest_step(demos: Demonstrations) -> float:
        steps = [np.linalg.norm(np.diff(d.positions, axis=0), axis=1).max() for d in demos]
        return max(steps) / demos.extent()

    # GIVEN recordings that jump by more than a tenth of the task's extent in one sample
    assert largest_step(kept) > 0.1
    # THEN with the dropped samples put back no step is longer than 2 % of it
    assert largest_step(filled) < 0.02
    np.testing.assert_array_equal(filled.target, kept.target)
    for got, recorded in zip(filled, kept, strict=True):
        # The same start, end and duration, and every recorded sample kept where it was.
        np.testing.assert_array_equal(got.positions[[0, -1]], recorded.positions[[0, -1]])
        assert got.duration == pytest.approx(recorded.duration, rel=1e-12)
        index = np.searchsorted(got.times, recorded.times - 1e-9)
        np.testing.assert_allclose(got.times[index], recorded.times, rtol=0, atol=1e-9)
        np.testing.assert_allclose(got.positions[index], recorded.positions, rtol=0, atol=1e-9)
        np.testing.assert_allclose(got.velocities[index], recorded.velocities, rtol=0, atol=1e-9)


def test_fill_gaps_puts_back_the_samples_a_recording_dropped():
    from snds.data.gaps import fill_gaps

    # GIVEN an accelerating motion along a parabola, sampled at 0.01 s, 30 samples missing
    times = 0.01 * np.arange(200)
    positions = np.stack([times, times**2], axis=1)
    velocities = np.stack([np.ones_like(times), 2 * times], axis=1)
    keep = np.r_[0:50, 80:200]
    got_positions, got_velocities, got_times = fill_gaps(positions[keep], velocities[keep], 0.01)
    # THEN the gap gets its 30 samples back, where and when the motion was (a cubic Hermite
    # curve holds a parabola exactly, and the velocities give the gap its 0.31 s exactly)
    np.testing.assert_allclose(got_times, times, rtol=0, atol=1e-12)
    np.testing.assert_allclose(got_positions, positions, rtol=0, atol=1e-12)
    np.testing.assert_allclose(got_velocities, velocities, rtol=0, atol=1e-12)
    # AND the recorded samples are the recorded ones, bit for bit
    np.testing.assert_array_equal(got_positions[keep], positions[keep])
    np.testing.assert_array_equal(got_velocities[keep], velocities[keep])


def test_fill_gaps_changes_nothing_without_a_gap():
    from snds.data.gaps import fill_gaps

    demo = quadratic_demos(count=1, uneven=False)[0]
    got_positions, got_velocities, got_times = fill_gaps(demo.positions, demo.velocities, 0.01)
    np.testing.assert_array_equal(got_positions, demo.positions)
    np.testing.assert_array_equal(got_velocities, demo.velocities)
    np.testing.assert_allclose(got_times, 0.01 * np.arange(len(demo.times)), rtol=1e-12)


def test_an_unknown_gap_mode_is_refused(tmp_path):
    path = tmp_path / "demos.mat"
    scipy.io.savemat(path, {"Data": concatenated(quadratic_demos(uneven=False)), "dt": 0.01})
    with pytest.raises(DataError, match="unknown gap mode 'drop'"):
        load_demonstrations(path, gaps="drop")


@pytest.mark.parametrize(
    "name, refused, accepted",
    [
        ("3D_Cshape_top.mat", 0.06, 0.07),
        ("3D_viapoint_1.mat", 0.05, 0.06),
        ("3D_sink.mat", 0.03, 0.04),
        ("3D-pick-box.mat", 0.35, 0.36),
    ],
)
def test_end_spread_each_3d_file_needs(name, refused, accepted):
    path = shared_file(name)
    with pytest.raises(DataError, match="do not end at a common target") as error:
        load_mat(path, max_end_spread=refused)
    assert name in str(error.value)
    loaded = load_mat(path, max_end_spread=accepted)
    assert all(np.array_equal(demo.positions[-1], loaded.target) for demo in loaded)


def test_pick_box_is_refused_by_default():
    path = shared_file("3D-pick-box.mat")
    with pytest.raises(DataError, match="3D-pick-box.mat: demonstrations do not end"):
        load_demonstrations(path)


# Synthetic .mat files.


def concatenated(demos: list[Demonstration]) -> np.ndarray:
    """The LPV-DS ``Data`` matrix of ``demos``, shape (2n, sum T)."""
    return np.concatenate([np.hstack([d.positions, d.velocities]).T for d in demos], axis=1)


def test_concatenated_data_with_dt_round_trips(tmp_path):
    demos = quadratic_demos(uneven=False)  # every one ends at rest, as the layout requires
    path = tmp_path / "demos.mat"
    scipy.io.savemat(path, {"Data": concatenated(demos), "dt": 0.01})
    loaded = load_mat(path)
    assert loaded.name == "demos"
    for got, want in zip(loaded, demos, strict=True):
        np.testing.assert_array_equal(got.positions, want.positions)
        np.testing.assert_array_equal(got.velocities, want.velocities)
        np.testing.assert_allclose(got.times, want.times, rtol=1e-12)


def test_a_demo_starting_at_rest_is_not_cut_off(tmp_path):
    demos = quadratic_demos(uneven=False)
    at_rest = Demonstration(
        demos[1].positions, np.vstack([[0.0, 0.0], demos[1].velocities[1:]]), demos[1].times
    )
    path = tmp_path / "rest.mat"
    scipy.io.savemat(path, {"Data": concatenated([demos[0], at_rest, demos[2]]), "dt": 0.01})
    assert [len(demo.times) for demo in load_mat(path)] == [40, 40, 40]


def test_time_step_is_estimated_from_trapezoid_rule_despite_a_jump(tmp_path):
    # GIVEN positions integrated from velocities with dt = 0.02, then one 5 cm jump
    dt, times = 0.02, 0.02 * np.arange(300)
    velocities = np.stack([np.cos(times), -np.sin(2 * times), np.sin(times)], axis=1)
    velocities[-1] = 0.0
    steps = dt * (velocities[1:] + velocities[:-1]) / 2
    positions = np.vstack([np.zeros(3), np.cumsum(steps, axis=0)])
    positions[:20] -= 0.05
    path = tmp_path / "jump.mat"
    cells = np.empty((1, 1), dtype=object)
    cells[0, 0] = np.hstack([positions, velocities]).T
    scipy.io.savemat(path, {"data": cells})
    # THEN the estimate ignores the jump and finds the step
    (demo,) = load_mat(path)
    np.testing.assert_allclose(demo.dt, dt, rtol=1e-9)


# CSV and NPZ round trips.


def test_csv_with_velocities_round_trips_exactly(tmp_path):
    demos = quadratic_demos(dim=3)
    path = write_csv(tmp_path / "runs.csv", demos, labels=["b", "a", "10"])
    loaded = load_csv(path)
    assert loaded.name == "runs"
    assert_same_demos(loaded, demos)  # in order of first appearance, not sorted by label


def test_csv_without_velocities_differentiates_exactly_on_quadratics(tmp_path):
    # Second-order differences are exact for quadratics, also with uneven steps and at the ends.
    demos = quadratic_demos()
    loaded = load_csv(write_csv(tmp_path / "q.csv", demos, velocities=False))
    for got, want in zip(loaded, demos, strict=True):
        np.testing.assert_allclose(got.velocities, want.velocities, atol=1e-9)
        np.testing.assert_array_equal(got.positions, want.positions)


def sine_error(tmp_path: Path, length: int) -> float:
    """Largest CSV velocity error on x = sin t, y = cos t, with steps of 3 / length +-30%."""
    jitter = np.random.default_rng(1).uniform(0.7, 1.3, size=length)
    times = np.concatenate([[0.0], np.cumsum(3.0 / length * jitter)])
    positions = np.stack([np.sin(times), np.cos(times)], axis=1)
    truth = np.stack([np.cos(times), -np.sin(times)], axis=1)
    demo = Demonstration(positions, truth, times)
    (got,) = load_csv(write_csv(tmp_path / f"sine{length}.csv", [demo], velocities=False))
    return float(np.abs(got.velocities - truth).max())


def test_differentiation_is_accurate_and_second_order(tmp_path):
    coarse, fine = sine_error(tmp_path, 500), sine_error(tmp_path, 2000)
    assert coarse < 1e-4
    # Four times the samples: a second-order scheme cuts the error by about 16, first-order by 4.
    assert fine < coarse / 10


def test_npz_with_velocities_and_times_round_trips_exactly(tmp_path):
    demos = quadratic_demos(dim=3)
    path = tmp_path / "runs.npz"
    np.savez(
        path,
        pos=np.stack([d.positions for d in demos]),
        vel=np.stack([d.velocities for d in demos]),
        t=np.stack([d.times for d in demos]),
    )
    assert_same_demos(load_npz(path), demos)


@pytest.mark.parametrize(
    "times, expected_dt",
    [({"dt": 0.05}, 0.05), ({"t": 0.05 * np.arange(40)}, 0.05), ({}, DEFAULT_DT)],
)
def test_npz_time_options_and_differentiation(tmp_path, times, expected_dt):
    demos = quadratic_demos(uneven=False)
    path = tmp_path / "q.npz"
    np.savez(path, pos=np.stack([d.positions for d in demos]), **times)
    for got, want in zip(load_npz(path), demos, strict=True):
        np.testing.assert_allclose(got.dt, expected_dt, rtol=1e-12)
        # x = c (T - t)^2 sampled with another step is still quadratic: its slope is exact.
        scale = expected_dt / 0.01
        np.testing.assert_allclose(got.velocities * scale, want.velocities, atol=1e-9)


def write_any(path: Path, demos: list[Demonstration]) -> Path:
    """Writes ``demos`` (at rest at their ends, step 0.01 s) in the format of ``path``'s suffix."""
    stacked = {
        "pos": np.stack([d.positions for d in demos]),
        "vel": np.stack([d.velocities for d in demos]),
        "t": np.stack([d.times for d in demos]),
    }
    writers = {
        ".csv": lambda: write_csv(path, demos),
        ".npz": lambda: np.savez(path, **stacked),
        ".mat": lambda: scipy.io.savemat(path, {"Data": concatenated(demos), "dt": 0.01}),
    }
    writers[path.suffix.lower()]()
    return path


@pytest.mark.parametrize("name", ["d.csv", "d.CSV", "d.npz", "d.mat", "d.v2.csv"])
def test_load_demonstrations_dispatches_on_the_extension(tmp_path, name):
    demos = quadratic_demos(uneven=False)
    path = write_any(tmp_path / name, demos)
    assert_same_demos(load_demonstrations(path), demos)
    assert_same_demos(load_demonstrations(str(path)), demos)
    assert set(LOADERS) == {".mat", ".csv", ".npz"}


def test_max_end_spread_reaches_the_loaders(tmp_path):
    demos = quadratic_demos()
    moved = Demonstration(demos[0].positions + 10.0, demos[0].velocities, demos[0].times)
    path = write_csv(tmp_path / "far.csv", [moved, *demos[1:]])
    with pytest.raises(DataError, match="common target"):
        load_demonstrations(path)
    loaded = load_demonstrations(path, max_end_spread=1.0)
    assert all(np.array_equal(d.positions[-1], loaded.target) for d in loaded)


# Bad input: every problem is a one-line DataError naming the file.


def csv_text(text: str) -> Callable[[Path], Path]:
    def write(folder: Path) -> Path:
        path = folder / "bad.csv"
        path.write_text(text)
        return path

    return write


def npz_arrays(**arrays) -> Callable[[Path], Path]:
    def write(folder: Path) -> Path:
        path = folder / "bad.npz"
        np.savez(path, **arrays)
        return path

    return write


def mat_vars(**variables) -> Callable[[Path], Path]:
    def write(folder: Path) -> Path:
        path = folder / "bad.mat"
        scipy.io.savemat(path, variables)
        return path

    return write


def raw_bytes(name: str, data: bytes) -> Callable[[Path], Path]:
    def write(folder: Path) -> Path:
        path = folder / name
        path.write_bytes(data)
        return path

    return write


def truncated_mat(keep: int) -> Callable[[Path], Path]:
    def write(folder: Path) -> Path:
        whole = mat_vars(Data=concatenated(quadratic_demos(uneven=False)), dt=0.01)(folder)
        data = whole.read_bytes()
        whole.unlink()
        return raw_bytes("cut.mat", data[:keep])(folder)

    return write


def npy_named_npz(folder: Path) -> Path:
    """A plain .npy array saved under an .npz name."""
    np.save(folder / "a.npy", POS)
    return (folder / "a.npy").rename(folder / "a.npz")


def cells(*blocks: np.ndarray) -> np.ndarray:
    array = np.empty((len(blocks), 1), dtype=object)
    for i, block in enumerate(blocks):
        array[i, 0] = block
    return array


GOOD = "demo,t,x1,x2\n0,0,1,1\n0,1,0,0\n"
POS = np.zeros((2, 5, 2))
POS[:, 0] = 1.0

BAD_INPUTS = {
    "missing file": (lambda folder: folder / "absent.csv", "no such file"),
    "empty csv": (raw_bytes("e.csv", b""), "empty"),
    "empty mat": (raw_bytes("e.mat", b""), "empty"),
    "empty npz": (raw_bytes("e.npz", b""), "empty"),
    "wrong extension": (raw_bytes("d.txt", GOOD.encode()), r"unsupported file type '\.txt'"),
    "no extension": (raw_bytes("d", GOOD.encode()), "supported: .csv, .mat, .npz"),
    "csv header only": (csv_text("demo,t,x1\n"), "no samples"),
    "csv header typo demo": (csv_text(GOOD.replace("demo", "dmeo")), "'dmeo', expected 'demo'"),
    "csv header typo x": (csv_text(GOOD.replace("x2", "x3")), "'x3', expected 'x2'"),
    "csv header typo t": (csv_text(GOOD.replace(",t,", ",time,")), "'time', expected 't'"),
    "csv missing v2": (csv_text("demo,t,x1,x2,v1\n0,0,1,1,0\n0,1,0,0,0\n"), "lacks column 'v2'"),
    "csv extra column": (
        csv_text("demo,t,x1,v1,w\n0,0,1,0,0\n0,1,0,0,0\n"),
        "'w', expected no more columns",
    ),
    "csv no positions": (csv_text("demo,t\n0,0\n0,1\n"), "no position columns"),
    "csv nan": (csv_text(GOOD.replace("1,1\n", "nan,1\n")), "line 2: non-finite value 'nan'"),
    "csv inf": (csv_text(GOOD.replace("0,0\n", "0,-inf\n")), "line 3: non-finite value '-inf'"),
    "csv text value": (csv_text(GOOD.replace("1,1\n", "1,a\n")), "line 2: 'a' is not a number"),
    "csv short row": (csv_text(GOOD + "0,2,1\n"), "line 4 has 3 fields"),
    "csv single sample": (
        csv_text(GOOD + "1,0,0,0\n"),
        "demo '1': a demonstration needs at least 2",
    ),
    "csv duplicated time": (csv_text(GOOD + "0,1,0,0\n"), "demo '0': times must be strictly"),
    "csv not utf-8": (raw_bytes("latin.csv", "demo,t,x1\n0,0,é\n".encode("latin-1")), "UTF-8"),
    "csv ends far apart": (csv_text(GOOD + "1,0,1,1\n1,1,0,1\n"), "do not end at a common"),
    "truncated mat 20": (truncated_mat(20), "not a readable MATLAB file"),
    "truncated mat 100": (truncated_mat(100), "not a readable MATLAB file"),
    "truncated mat 127": (truncated_mat(127), "not a readable MATLAB file"),
    "truncated mat 300": (truncated_mat(300), "not a readable MATLAB file"),
    "mat header only": (truncated_mat(128), "no variable 'Data' or 'data'"),
    "mat garbage": (raw_bytes("g.mat", b"not a mat file" * 20), "not a readable MATLAB file"),
    "mat no data variable": (mat_vars(positions=np.zeros((4, 3))), r"found: positions"),
    "mat odd rows": (mat_vars(Data=np.ones((3, 4))), r"2n x N"),
    "mat nan": (mat_vars(Data=np.array([[1.0, np.nan], [1.0, 0.0]])), "NaN or inf"),
    "mat inf": (mat_vars(data=cells(np.array([[1.0, 0.0], [np.inf, 0.0]]))), "NaN or inf"),
    "mat different dims": (
        mat_vars(data=cells(np.ones((4, 3)), np.ones((6, 3))), dt=0.1),
        "different dimensions",
    ),
    "mat negative dt": (
        mat_vars(data=cells(np.ones((4, 3))), dt=-0.1),
        "'dt' must be one positive",
    ),
    "mat text cell": (mat_vars(data=cells(np.array(["abc"]))), "must hold real numbers"),
    "mat data not cell": (mat_vars(data=np.ones((4, 3))), "cell array"),
    "mat velocities all zero": (
        mat_vars(data=cells(np.vstack([np.ones((2, 3)), np.zeros((2, 3))]))),
        "cannot infer the time step",
    ),
    "mat velocities against motion": (
        mat_vars(data=cells(np.array([[0.0, 1.0, 2.0], [-1.0, -1.0, 0.0]]))),
        "cannot infer the time step",
    ),
    "mat single sample": (mat_vars(data=cells(np.ones((4, 1))), dt=0.1), "at least 2 samples"),
    "npz garbage": (raw_bytes("g.npz", b"PK not really a zip"), "not a readable .npz"),
    "npz is npy": (npy_named_npz, "not an .npz archive"),
    "npz pickled objects": (
        npz_arrays(pos=np.array([None, 1], dtype=object)),
        "not a readable .npz",
    ),
    "npz misspelt key": (npz_arrays(pos=POS, vell=POS), r"unexpected arrays \['vell'\]"),
    "npz no pos": (npz_arrays(vel=POS), "no 'pos' array"),
    "npz pos 2-D": (npz_arrays(pos=POS[0]), r"'pos' must have shape \(demos, samples, n\)"),
    "npz no coordinates": (npz_arrays(pos=np.zeros((2, 5, 0))), r"got \(2, 5, 0\)"),
    "npz vel shape": (npz_arrays(pos=POS, vel=POS[:, :4]), "'vel' has shape"),
    "npz t shape": (npz_arrays(pos=POS, t=np.arange(4.0)), "'t' must have shape"),
    "npz t and dt": (npz_arrays(pos=POS, t=np.arange(5.0), dt=0.1), "both 't' and 'dt'"),
    "npz zero dt": (npz_arrays(pos=POS, dt=0.0), "'dt' must be one positive"),
    "npz duplicated t": (npz_arrays(pos=POS, t=np.array([0, 1, 1, 2, 3.0])), "strictly increasing"),
    "npz nan": (
        npz_arrays(pos=np.where(POS == 1, np.nan, 0)),
        "demonstration 0: positions contains",
    ),
    "npz inf velocity": (npz_arrays(pos=POS, vel=np.full_like(POS, np.inf)), "NaN or inf"),
    "npz complex": (npz_arrays(pos=POS + 1j), "must hold real numbers"),
    "npz single sample": (npz_arrays(pos=POS[:, :1]), "at least 2 samples"),
    "npz ends far apart": (npz_arrays(pos=np.stack([POS[0], POS[1] + 5])), "common target"),
}


@pytest.mark.parametrize("case", list(BAD_INPUTS))
def test_bad_input_is_a_one_line_data_error_naming_the_file(case, tmp_path):
    make, problem = BAD_INPUTS[case]
    path = make(tmp_path)
    with pytest.raises(DataError, match=problem) as error:
        load_demonstrations(path)
    message = str(error.value)
    assert path.name in message and "\n" not in message


def test_a_directory_is_not_a_file(tmp_path):
    folder = tmp_path / "runs.csv"
    folder.mkdir()
    with pytest.raises(DataError, match="runs.csv: not a regular file"):
        load_csv(folder)


@settings(deadline=None, max_examples=60)
@given(keep=st.integers(0, 2000))
def test_any_truncation_of_a_mat_file_is_a_data_error(keep, tmp_path_factory):
    folder = tmp_path_factory.mktemp("cut", numbered=True)
    path = truncated_mat(keep)(folder)
    with pytest.raises(DataError, match="cut.mat"):
        load_mat(path)


# Random .npz contents: a DataError or valid demonstrations, never another exception.

DTYPES = (
    hnp.floating_dtypes()
    | hnp.integer_dtypes()
    | hnp.boolean_dtypes()
    | hnp.complex_number_dtypes()
    | hnp.unicode_string_dtypes()
)


def often(weight: int) -> st.SearchStrategy[bool]:
    """True in about ``weight`` of ``weight + 1`` draws."""
    return st.sampled_from([True] * weight + [False])


@st.composite
def npz_contents(draw) -> dict[str, np.ndarray]:
    """Mostly plausible archives, each with a chance of any shape, dtype, value or extra key."""
    # Empty sizes come from the random shapes below.
    demos, samples, n = draw(st.integers(1, 3)), draw(st.integers(1, 5)), draw(st.integers(1, 3))
    fitting = {"pos": (demos, samples, n), "vel": (demos, samples, n), "dt": ()}
    fitting["t"] = draw(st.sampled_from([(demos, samples), (samples,)]))

    def array(key: str) -> np.ndarray:
        shape = fitting[key] if draw(often(3)) else draw(hnp.array_shapes(min_dims=0, min_side=0))
        if not draw(often(3)):
            return draw(hnp.arrays(DTYPES, shape))
        values = draw(hnp.arrays(np.float64, shape, elements=st.floats(-1e3, 1e3)))
        # Cumulative positive steps: times that are usually valid, so both outcomes get tested.
        return np.cumsum(np.abs(values) + 1e-3, axis=-1) if key == "t" and values.ndim else values

    keys = ["pos", *(key for key in ["vel", "t", "dt"] if draw(st.booleans()))]
    contents = {key: array(key) for key in keys}
    if not draw(often(7)):
        contents["extra"] = array("dt")
    return contents


@settings(deadline=None, max_examples=300, suppress_health_check=[HealthCheck.too_slow])
@given(contents=npz_contents())
def test_load_npz_returns_valid_demonstrations_or_a_data_error(contents, tmp_path_factory):
    path = tmp_path_factory.getbasetemp() / "random.npz"
    np.savez(path, **contents)
    try:
        demos = load_npz(path, max_end_spread=1e9)
    except DataError as error:
        assert "random.npz" in str(error)
        return
    positions = contents["pos"]
    assert isinstance(demos, Demonstrations)
    assert len(demos) == positions.shape[0] and demos.dim == positions.shape[2]
    for demo in demos:
        assert demo.positions.shape == positions.shape[1:]
        assert np.array_equal(demo.positions[-1], demos.target)
        assert np.isfinite(demo.velocities).all() and (np.diff(demo.times) > 0).all()
