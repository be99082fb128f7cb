"""Every kind of bad input of docs/bad-input.md: a specific exception from the API, and from the
CLI one line naming the problem, exit code 2, and no file written.

Each row of the table in docs/bad-input.md is one case of :data:`CASES` (its test id); the
loaders' finer cases are in tests/data/test_files.py.
"""

from __future__ import annotations

import json
import pickle
import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import scipy.io
import torch
from safetensors.torch import save_file

from snds.cli import main
from snds.data import (
    Demonstration,
    Demonstrations,
    Normalization,
    ReadOptions,
    load_demonstrations,
    load_lasa,
    load_recording,
)
from snds.data.poses import load_poses
from snds.errors import ConfigError, DataError, ModelFileError, SNDSError
from snds.models import FORMAT_VERSION, load_model, save_model
from snds.policy import PolicyConfig
from snds.train import TrainConfig, fit

from conftest import SMALL, make_policy, spiral_demos
from recording_files import line_poses, write_bag, write_lerobot

DOC = Path(__file__).resolve().parents[1] / "docs" / "bad-input.md"
GOOD_CSV = "demo,t,x1,x2\n0,0,1,1\n0,1,0,0\n1,0,1.2,0.9\n1,1,0,0\n"


@dataclass(frozen=True)
class Case:
    """One bad input: how to make it, what the API raises, and what both messages say.

    Attributes:
        make: Writes the input into a folder; returns the CLI arguments and the API call.
        error: The exception class the API raises.
        message: A regular expression both messages match.
    """

    make: Callable[[Path], tuple[list[str], Callable[[], object]]]
    error: type[SNDSError]
    message: str


def data_file(
    name: str, write: Callable[[Path], None], load: Callable[[Path], object] = load_demonstrations
):
    """A case whose input is a demonstrations file given to ``snds train --data``; ``load``
    is the API's loader of it."""

    def make(folder: Path):
        path = folder / name
        write(path)
        return ["train", "--data", str(path)], lambda: load(path)

    return make


def pose_file(name: str, rows: list[list[float]]):
    """A case whose input is a pose CSV file of these rows given to ``snds train --data``."""
    lines = "".join(",".join(map(str, row)) + "\n" for row in rows)
    return data_file(name, text("demo,t,x,y,z,qx,qy,qz,qw\n" + lines), load=load_poses)


#: Two pose demonstrations from (1, 1, 0) and (1, 0, 0) to the origin, at the identity.
GOOD_POSES = [
    [0, 0, 1, 1, 0, 0, 0, 0, 1],
    [0, 1, 0, 0, 0, 0, 0, 0, 1],
    [1, 0, 1, 0, 0, 0, 0, 0, 1],
    [1, 1, 0, 0, 0, 0, 0, 0, 1],
]


def _poses_with(index: int, quaternion: list[float]) -> list[list[float]]:
    rows = [list(row) for row in GOOD_POSES]
    rows[index][5:] = quaternion
    return rows


def text(content: str) -> Callable[[Path], None]:
    return lambda path: path.write_text(content)


def mat(**variables) -> Callable[[Path], None]:
    return lambda path: scipy.io.savemat(path, variables)


def npz(**arrays) -> Callable[[Path], None]:
    return lambda path: np.savez(path, **arrays)


def truncated_mat(path: Path) -> None:
    block = np.vstack([np.linspace(1, 0, 20)[None].repeat(2, 0), -np.ones((2, 20))])
    scipy.io.savemat(path, {"data": cells(block), "dt": 0.05})
    path.write_bytes(path.read_bytes()[:300])


def cells(*blocks: np.ndarray) -> np.ndarray:
    array = np.empty((len(blocks), 1), dtype=object)
    for i, block in enumerate(blocks):
        array[i, 0] = block
    return array


def saved_model(folder: Path, seed: int = 3) -> Path:
    """A small saved policy that records LASA Sine as its data (never read by these cases)."""
    directory = folder / "model"
    save_model(
        make_policy(spiral_demos(count=1, samples=50), seed=seed),
        directory,
        extra={"data": {"motion": "Sine", "demos": 1}},
    )
    return directory


def model_dir(spoil: Callable[[Path], None]):
    """A case whose input is a saved model spoilt by ``spoil``, given to ``snds evaluate``."""

    def make(folder: Path):
        directory = saved_model(folder)
        spoil(directory)
        return ["evaluate", str(directory)], lambda: load_model(directory)

    return make


def edit_description(**changes) -> Callable[[Path], None]:
    def spoil(directory: Path) -> None:
        path = directory / "model.json"
        path.write_text(json.dumps({**json.loads(path.read_text()), **changes}))

    return spoil


def wrong_shapes(directory: Path) -> None:
    tensors, _ = load_model(directory)
    state = {k: v.clone() for k, v in tensors.state_dict().items()}
    name = next(k for k in state if k.endswith("weight"))
    state[name] = torch.zeros(3, 3, dtype=torch.float64)
    save_file(state, str(directory / "model.safetensors"))


def weights_of_another_save(directory: Path) -> None:
    """Same architecture, other weights: what a save interrupted between its two files leaves."""
    other = saved_model(directory.parent / "other", seed=4)
    (directory / "model.safetensors").write_bytes((other / "model.safetensors").read_bytes())


class Exploit:
    """Pickles to a call that would write a file: loading it must never run it."""

    def __reduce__(self):
        return (exec, ("import pathlib; pathlib.Path('PWNED').write_text('x')",))


def pickle_as_weights(directory: Path) -> None:
    (directory / "model.safetensors").write_bytes(pickle.dumps(Exploit()))


def torch_file_as_weights(directory: Path) -> None:
    # torch.save's zip archive with a __reduce__ payload, as a .pt checkpoint would carry one.
    torch.save({"weights": Exploit()}, directory / "model.safetensors")


def unknown_motion(folder: Path):
    return ["train", "--motion", "Sinus"], lambda: load_lasa("Sinus")


def setting(argv: list[str], make_config: Callable[[], object]):
    def make(folder: Path):
        return ["train", "--motion", "Sine", *argv], make_config

    return make


def no_cuda(folder: Path):
    if torch.cuda.is_available():
        pytest.skip("this machine has a CUDA device")
    return ["train", "--motion", "Sine", "--device", "cuda"], lambda: TrainConfig(device="cuda")


def different_dimensions(folder: Path):
    path = folder / "dims.mat"
    scipy.io.savemat(path, {"data": cells(np.ones((4, 3)), np.ones((6, 3))), "dt": 0.1})
    return ["train", "--data", str(path)], lambda: load_demonstrations(path)


def never_move(folder: Path):
    path = folder / "still.csv"
    path.write_text("demo,t,x1,x2\n0,0,0,0\n0,1,0,0\n")
    return ["train", "--data", str(path)], lambda: Normalization.fit(load_demonstrations(path))


def below_float32(folder: Path):
    path = folder / "tiny.csv"
    path.write_text("demo,t,x1,x2\n0,0,1e-60,0\n0,1,0,0\n")
    return ["train", "--data", str(path)], lambda: Normalization.fit(load_demonstrations(path))


def recording(name: str, write: Callable[[Path], None], **options):
    """A case whose input is a recording given to ``snds train --data`` with the flags of
    these :class:`~snds.data.ReadOptions`; the API's call is :func:`load_recording`."""

    def make(folder: Path):
        path = folder / name
        write(path)
        flags = [
            part
            for field, value in options.items()
            for part in (f"--{field.replace('_', '-')}", str(value))
        ]
        return ["train", "--data", str(path), *flags], lambda: load_recording(
            path, options=ReadOptions(**options)
        )

    return make


def bag_with_joints(path: Path) -> None:
    pytest.importorskip("rosbags")
    write_bag(path, line_poses(10), others={"/joint_states": "sensor_msgs/msg/JointState"})


def empty_bag(path: Path) -> None:
    pytest.importorskip("rosbags")
    write_bag(path, line_poses(0))


def truncated_bag(path: Path) -> None:
    pytest.importorskip("rosbags")
    write_bag(path.parent / "whole", line_poses(20))
    data = next((path.parent / "whole").glob("*.mcap")).read_bytes()
    path.write_bytes(data[: len(data) // 2])
    for item in sorted((path.parent / "whole").iterdir()):
        item.unlink()
    (path.parent / "whole").rmdir()


def lerobot_actions(path: Path) -> None:
    pytest.importorskip("pyarrow")
    write_lerobot(path, [np.linspace([1.0, 1.0], [0.0, 0.0], 10)], column="action")


def npy_poses(path: Path) -> None:
    np.save(path, line_poses(10)[None])


def scaled_transforms(path: Path) -> None:
    transforms = np.tile(np.eye(4), (1, 10, 1, 1))
    transforms[0, :, :3, 3] = np.linspace([1.0, 0.0, 0.0], [0.0, 0.0, 0.0], 10)
    transforms[0, 4, :3, :3] *= 1.5
    np.save(path, transforms)


CASES: dict[str, Case] = {
    "empty file": Case(data_file("empty.csv", text("")), DataError, "empty.csv: file is empty"),
    "wrong extension": Case(
        data_file("demos.txt", text(GOOD_CSV)), DataError, r"unsupported file type '\.txt'"
    ),
    "no such file": Case(data_file("absent.csv", lambda path: None), DataError, "no such file"),
    "truncated mat": Case(
        data_file("cut.mat", truncated_mat), DataError, "cut.mat: not a readable MATLAB file"
    ),
    "csv header typo": Case(
        data_file("typo.csv", text(GOOD_CSV.replace("demo", "dmeo"))),
        DataError,
        "header column 1 is 'dmeo', expected 'demo'",
    ),
    "nan": Case(
        data_file("nan.csv", text(GOOD_CSV.replace("0,1,1\n", "0,nan,1\n"))),
        DataError,
        "line 2: non-finite value 'nan'",
    ),
    "inf": Case(
        data_file("inf.npz", npz(pos=np.array([[[1.0, np.inf], [0.0, 0.0]]]))),
        DataError,
        "demonstration 0: positions contains NaN or inf",
    ),
    "single sample": Case(
        data_file("one.csv", text(GOOD_CSV + "2,0,1,1\n")),
        DataError,
        "demo '2': a demonstration needs at least 2 samples, got 1",
    ),
    "zero-length demo": Case(
        data_file("zero.mat", mat(data=cells(np.ones((4, 0)), np.ones((4, 3))), dt=0.1)),
        DataError,
        "demonstration 0: a demonstration needs at least 2 samples, got 0",
    ),
    "different dimensions": Case(
        different_dimensions, DataError, r"demonstrations have different dimensions: \[2, 3\]"
    ),
    "duplicated time stamps": Case(
        data_file("dup.csv", text(GOOD_CSV.replace("1,1,0,0", "1,0,0,0"))),
        DataError,
        "demo '1': times must be strictly increasing",
    ),
    "ends far apart": Case(
        data_file("far.csv", text(GOOD_CSV.replace("1,1,0,0", "1,1,1,1"))),
        DataError,
        "do not end at a common target",
    ),
    "demos that never move": Case(
        never_move, DataError, "still.csv: demonstrations have zero extent"
    ),
    "demos below float32": Case(
        below_float32,
        DataError,
        r"tiny(\.csv)?: the demonstrations' extent is 1e-60, outside the float32 range",
    ),
    "pose not a unit quaternion": Case(
        pose_file("norm.csv", _poses_with(0, [0, 0, 0, 2])),
        DataError,
        r"norm.csv: demo '0': orientations are not unit quaternions \(norms 1..2\)",
    ),
    "pose zero quaternion": Case(
        pose_file("zero_q.csv", _poses_with(0, [0, 0, 0, 0])),
        DataError,
        r"zero_q.csv: demo '0': orientations has a zero quaternion \(row 0\)",
    ),
    "pose ends turned apart": Case(
        pose_file("turned.csv", _poses_with(3, [0, 0, 0.7071, 0.7071])),
        DataError,
        "turned.csv: demonstrations do not end at a common orientation",
    ),
    "bag without the topic": Case(
        recording("rec", bag_with_joints, topic="/ee"),
        DataError,
        r"rec: no topic '/ee' in the bag; it has: /ee_pose \(geometry_msgs/msg/PoseStamped\), "
        r"/joint_states \(sensor_msgs/msg/JointState\)",
    ),
    "bag topic of an unsupported type": Case(
        recording("rec", bag_with_joints, topic="/joint_states"),
        DataError,
        "rec: topic /joint_states has type sensor_msgs/msg/JointState; snds reads geometry_msgs",
    ),
    "empty bag": Case(
        recording("rec", empty_bag), DataError, "rec: topic /ee_pose has no messages"
    ),
    "truncated bag": Case(
        recording("cut.mcap", truncated_bag),
        DataError,
        r"cut.mcap: not a readable bag \(empty, truncated or corrupt\?\)",
    ),
    "dataset without the column": Case(
        recording("dataset", lerobot_actions),
        DataError,
        "dataset: the dataset has no column 'observation.state'; choose with --columns from: "
        "action",
    ),
    "recording without time stamps": Case(
        recording("poses.npy", npy_poses, quaternion_order="xyzw"),
        DataError,
        r"poses.npy: demonstration 0: a .npy array stores no time stamps: give its sampling "
        r"rate \(--rate HZ",
    ),
    "quaternions of unknown order": Case(
        recording("poses.npy", npy_poses, rate=10),
        DataError,
        "poses.npy: the array holds quaternions in unnamed columns: state their order with "
        "--quaternion-order xyzw or wxyz",
    ),
    "transforms that are not rotations": Case(
        recording("tf.npy", scaled_transforms, rate=10),
        DataError,
        "tf.npy: the 3x3 blocks are not rotations: a singular value is 0.5 from 1",
    ),
    "unknown motion": Case(unknown_motion, DataError, "unknown LASA motion 'Sinus'"),
    "bad setting": Case(
        setting(["--steps", "0"], lambda: TrainConfig(steps=0)),
        ConfigError,
        "steps must be >= 1, got 0",
    ),
    "negative decay rate": Case(
        setting(["--decay-rate", "-1"], lambda: PolicyConfig(decay_rate=-1)),
        ConfigError,
        "decay_rate and decay_far must be >= 0",
    ),
    "no cuda device": Case(no_cuda, ConfigError, "no CUDA device is available"),
    "npz with a pickled payload": Case(
        data_file("evil.npz", lambda path: np.savez(path, pos=np.array([Exploit()], dtype=object))),
        DataError,
        "evil.npz: not a readable .npz archive",
    ),
    "model dir without model.json": Case(
        model_dir(lambda d: (d / "model.json").unlink()), ModelFileError, "model.json: missing"
    ),
    "model dir without weights": Case(
        model_dir(lambda d: (d / "model.safetensors").unlink()),
        ModelFileError,
        "model.safetensors: missing",
    ),
    "corrupted model.json": Case(
        model_dir(lambda d: (d / "model.json").write_text('{"format_version": 1,')),
        ModelFileError,
        "model.json: corrupted JSON",
    ),
    "truncated weights": Case(
        model_dir(
            lambda d: (d / "model.safetensors").write_bytes(
                (d / "model.safetensors").read_bytes()[:1000]
            )
        ),
        ModelFileError,
        "model.safetensors: corrupted safetensors file",
    ),
    "newer format version": Case(
        model_dir(edit_description(format_version=FORMAT_VERSION + 1)),
        ModelFileError,
        "is newer than this snds reads",
    ),
    "wrong tensor shapes": Case(
        model_dir(wrong_shapes), ModelFileError, r"has shape \(3, 3\), the architecture needs"
    ),
    "weights of another save": Case(
        model_dir(weights_of_another_save), ModelFileError, "does not match model.json"
    ),
    "model.json with wrong types": Case(
        model_dir(edit_description(dim="2")),
        ModelFileError,
        "invalid architecture .dim must be a positive integer, got '2'",
    ),
    "model.json asking for huge layers": Case(
        model_dir(edit_description(policy={**SMALL.to_dict(), "hidden": [10**9, 10**9]})),
        ModelFileError,
        r"has shape \(32,\), the architecture needs \(1000000000,\)",
    ),
    "pickle as the model file": Case(
        model_dir(pickle_as_weights), ModelFileError, "corrupted safetensors file"
    ),
    "torch .pt with a payload as the model file": Case(
        model_dir(torch_file_as_weights), ModelFileError, "corrupted safetensors file"
    ),
}


def files_under(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in folder.rglob("*") if p.is_file()}


@pytest.mark.parametrize("case", list(CASES))
def test_bad_input(case, tmp_path, monkeypatch, capsys):
    # GIVEN the bad input, in a folder that is also the working directory
    monkeypatch.chdir(tmp_path)
    argv, call = CASES[case].make(tmp_path)
    before = files_under(tmp_path)
    # WHEN the API is called THEN it raises the specific error, with the message
    with pytest.raises(CASES[case].error, match=CASES[case].message):
        call()
    # WHEN the CLI is run THEN one line names the problem, exit code 2, nothing written
    out = tmp_path / "out"
    if argv[0] == "train":
        # Small defaults before the case's own arguments, which override them.
        fast = ["--out", str(out), "--steps", "5", "--rollouts", "10", "--samples", "100"]
        argv = [argv[0], *fast, *argv[1:]]
    assert main(["--quiet", *argv]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("snds: error: "), err
    assert re.search(CASES[case].message, err), err
    assert files_under(tmp_path) == before and not out.exists()
    assert not (tmp_path / "PWNED").exists()


def test_the_table_lists_every_case_and_only_them():
    # The table of docs/bad-input.md names each case by its test id (the page's API has its
    # own table, after its heading, backed by tests/app/test_api.py).
    library = DOC.read_text().split("## The page's API")[0]
    listed = re.findall(r"`test_bad_input\[(.+?)\]`", library)
    assert sorted(listed) == sorted(CASES)


# Inputs that are accepted: what the library does with them.


def linear_demos(scale: float = 1.0) -> Demonstrations:
    """Straight-line demos at constant speed that never stop, ending at (scale, -scale)."""
    times = np.linspace(0.0, 2.0, 60)
    target = np.array([1.0, -1.0]) * scale
    demos = []
    for direction in ([3.0, 1.0], [1.0, 2.0], [-2.0, 2.0]):
        velocity = -np.asarray(direction) * scale
        positions = target + (times[-1] - times)[:, None] * -velocity
        demos.append(Demonstration(positions, np.tile(velocity, (60, 1)), times))
    return Demonstrations(tuple(demos), target, "never_stop")


def test_demos_that_never_stop_still_give_a_policy_that_stops_at_the_target():
    # GIVEN demonstrations still at full speed at their last sample
    demos = linear_demos()
    assert min(np.linalg.norm(d.velocities[-1]) for d in demos) > 1.0
    policy = make_policy(demos)
    from snds.data import no_split

    # WHEN a policy is fitted THEN it fits the speed along the way and is 0 at the target
    fit(policy, demos, no_split(demos), TrainConfig(steps=100, dtype="float64"), progress=False)
    target = torch.tensor(demos.target)[None]
    assert torch.equal(policy(target), torch.zeros_like(target))
    error = np.abs(policy.predict(demos[0].positions[:30]) - demos[0].velocities[:30]).mean()
    assert error < 0.5 * np.linalg.norm(demos[0].velocities[0])


@pytest.mark.parametrize("scale", [1e-6, 1e6])
def test_huge_and_tiny_scales_give_the_same_policy_in_their_units(scale):
    # GIVEN the same demonstrations in units 1e6 times smaller or larger
    from snds.data import no_split
    from snds.losses import make_samples

    # A few steps: once a sample's rounding puts it on the other side of the projection's
    # kink, Adam amplifies the difference (to 1e-3 of the top speed within 4-8 steps, with
    # and without the nominal term); in the first 3 steps both runs stay within 5e-9.
    config = TrainConfig(steps=3, dtype="float64", batch_size=0)
    fitted = []
    for factor in (1.0, scale):
        demos = linear_demos(factor)
        policy = make_policy(demos, SMALL)
        samples = make_samples(demos, policy.normalization, no_split(demos), window=0)
        result = fit(policy, demos, no_split(demos), config, progress=False)
        fitted.append((policy, demos, samples, result))
    (unit, demos, unit_samples, unit_result), (scaled, _, scaled_samples, scaled_result) = fitted
    # THEN training sees the same numbers, up to rounding
    for name in ("positions", "velocities"):
        torch.testing.assert_close(
            getattr(scaled_samples, name), getattr(unit_samples, name), rtol=1e-12, atol=1e-12
        )
    # AND the fitted policies agree in their units
    assert np.isfinite(scaled_result.history).all()
    assert scaled_result.history == pytest.approx(unit_result.history, rel=1e-6)
    x = demos.positions()
    top = demos.max_speed()
    np.testing.assert_allclose(
        scaled.predict(x * scale) / scale, unit.predict(x), rtol=0, atol=1e-6 * top
    )


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--window", "-1"], "window and batch sizes must be >= 0"),
        (["--rollouts", "0"], "--rollouts must be >= 1, got 0"),
        (["--samples", "-1"], "--samples must be >= 0, got -1"),
        (["--device", "foo"], "unknown device 'foo'"),
        (["--decay-rate", "nan"], "decay_rate and decay_far must be >= 0"),
        (["--nominal-weight", "-1"], "nominal_weight must be a number >= 0, got -1"),
        (["--warp-weight", "inf"], "warp_weight must be a number >= 0, got inf"),
        (["--warp-layers", "-2"], "need warp_layers >= 0"),
        (["--tracking-gain", "-3"], "tracking_gain must be a number >= 0, got -3"),
        (["--smooth-weight", "-0.5"], "smooth_weight must be a number >= 0, got -0.5"),
    ],
)
def test_bad_settings_exit_2(argv, message, tmp_path, capsys):
    out = tmp_path / "out"
    assert (
        main(["--quiet", "train", "--motion", "Sine", "--steps", "5", "--out", str(out), *argv])
        == 2
    )
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and message in err, err
    assert not out.exists()
