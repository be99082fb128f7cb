"""Refinement (snds.refine): a warm-started fit that keeps the guarantee, the model's
normalisation and phase, and resumes from its checkpoints like any fit."""

from __future__ import annotations

import copy
import dataclasses
import json
import shutil

import numpy as np
import pytest
import torch

from snds import train
from snds.callbacks import Callback
from snds.cli import main
from snds.data import DataSource, Demonstration, Demonstrations, Split, split_samples
from snds.errors import ConfigError, DataError
from snds.models import load_model
from snds.phase import Phase
from snds.policy import float64_copy
from snds.refine import RefineConfig, added_demonstrations, refine, refine_settings
from snds.refine_run import write_demonstrations
from snds.stability import CheckConfig, check_stability
from snds.train import CHECKPOINT, TrainConfig, fit

from conftest import SMALL, make_policy, spiral_demos

TRAIN = TrainConfig(steps=60, batch_size=64, window_batch_size=16)
SHORT = RefineConfig(steps=20, lr=5e-3)


@pytest.fixture(scope="module")
def task():
    """A policy trained on 2 spiral demonstrations, and the 3 (the third one new) with the
    0.8 / 0.2 split of seed 0."""
    torch.set_num_threads(1)
    demos = spiral_demos(count=3, samples=150)
    split = split_samples(demos, test_fraction=0.2, seed=0)
    old = demos.select([0, 1])
    trained = make_policy(old, SMALL, seed=3, dtype=torch.float32)
    fit(trained, old, Split(split.train[:2]), TRAIN, progress=False)
    return trained, demos, split


def same_weights(a: torch.nn.Module, b: torch.nn.Module) -> bool:
    left, right = a.state_dict(), b.state_dict()
    return left.keys() == right.keys() and all(torch.equal(left[k], right[k]) for k in left)


@pytest.mark.parametrize(
    "weight, extra", [(1, {}), (3, {}), (1, {"batch_size": None, "fit_lyapunov": True})]
)
def test_a_refinement_is_a_fit_from_the_trained_weights_bit_for_bit(task, weight, extra):
    trained, demos, split = task
    config = dataclasses.replace(SHORT, new_weight=weight, **extra)
    # WHEN the trained policy is refined with the third demonstration
    refined = copy.deepcopy(trained)
    done = refine(refined, demos, split, config=config, train=TRAIN, new=[2])
    # THEN it is the fit of the same weights with the refinement's settings, the new
    # demonstration counted `weight` times
    order = [0, 1] + [2] * weight
    expected = copy.deepcopy(trained)
    history = fit(
        expected,
        demos.select(order),
        Split(tuple(split.train[i] for i in order)),
        refine_settings(config, TRAIN),
        progress=False,
    ).history
    assert same_weights(refined, expected) and done.result.history == history
    assert done.train.steps == 20 and done.train.lr == 5e-3 and done.train.seed == TRAIN.seed
    # with the refinement's batch (None: the model's own) and V kept or trained as it says
    batch = TRAIN.batch_size if config.batch_size is None else config.batch_size
    assert done.train.batch_size == batch and done.train.fit_lyapunov == config.fit_lyapunov
    # and the policy's scaling is the trained one's
    assert refined.normalization.to_dict() == trained.normalization.to_dict()


class Killed(BaseException):
    """Stands for a kill inside a refinement."""


class KillAfter(Callback):
    """Stops a fit dead after ``steps`` steps."""

    def __init__(self, steps: int) -> None:
        self.steps = steps

    def on_step(self, event) -> None:
        if event.step + 1 >= self.steps:
            raise Killed


def test_a_killed_refinement_resumes_to_the_uninterrupted_one(task, tmp_path, monkeypatch):
    trained, demos, split = task
    reference = copy.deepcopy(trained)
    expected = refine(reference, demos, split, config=SHORT, train=TRAIN, new=[2]).result
    # GIVEN a refinement killed after 13 steps, with a checkpoint every 5
    checkpoint = tmp_path / CHECKPOINT
    with pytest.raises(Killed):
        refine(
            copy.deepcopy(trained),
            demos,
            split,
            config=SHORT,
            train=TRAIN,
            new=[2],
            callbacks=[KillAfter(13)],
            checkpoint=checkpoint,
            checkpoint_every=5,
        )
    # WHEN it is started again from the trained model with the same settings
    resumed = copy.deepcopy(trained)
    result = refine(
        resumed, demos, split, config=SHORT, train=TRAIN, new=[2], checkpoint=checkpoint
    ).result
    # THEN it ends with the uninterrupted refinement's weights and history, bit for bit
    assert same_weights(resumed, reference) and result.history == expected.history


def test_the_refined_policy_keeps_the_guarantee_and_learns_the_new_demonstration(task):
    trained, demos, split = task
    refined = copy.deepcopy(trained)
    refine(refined, demos, split, config=RefineConfig(steps=60), train=TRAIN, new=[2])
    policy64 = float64_copy(refined)
    # V decreases at the promised rate at states up to 100 extents away, in float64
    z = 100.0 * torch.randn(
        20_000, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(1)
    )
    z = z * torch.rand(20_000, 1, dtype=torch.float64) ** 3  # many near the target too
    terms = policy64.field_terms(z)
    assert ((terms.grad * terms.field).sum(-1) <= -policy64.decay(terms.value, z) + 1e-9).all()
    # every rollout from a wide box of starts reaches the target, with no violation
    report = check_stability(policy64, demos, CheckConfig(rollouts=40, samples=2000, seed=0))
    assert report.converged_fraction == 1.0 and report.decrease_violations == 0
    # and the new demonstration's velocities are fitted better than before the refinement
    new = demos[2]

    def error(policy) -> float:
        return float(np.mean((float64_copy(policy).predict(new.positions) - new.velocities) ** 2))

    assert error(refined) < 0.8 * error(trained)


def stroke(start, end, samples: int = 50) -> Demonstration:
    """A straight constant-speed motion from start to end over 2 s."""
    times = np.linspace(0.0, 2.0, samples)
    path = np.linspace(start, end, samples)
    return Demonstration(path, np.tile((np.subtract(end, start)) / 2.0, (samples, 1)), times)


def test_added_demonstrations_keep_the_model_target_and_phases():
    old = Demonstrations(
        (stroke([4.0, 0.0], [0.0, 0.0]), stroke([0.0, 3.0], [0.0, 0.0])), np.zeros(2)
    )
    # GIVEN a new demonstration reaching twice as far, ending a little off the target
    new = Demonstrations((stroke([-8.0, 1.0], [0.2, -0.1]),), np.array([0.2, -0.1]))
    phase = Phase(codes=3)
    # WHEN it is added for a phased model
    joined = added_demonstrations(old, new, phase=phase)
    # THEN the old demonstrations carry the phases the model was trained with
    trained = phase.apply(old)
    for before, after in zip(trained, joined.demos[:2]):
        np.testing.assert_array_equal(before.positions, after.positions)
    # the new one ends exactly on the model's target (positions and phase 0), starts where
    # it was demonstrated, with the old extent (4) scaling its phase and the next code
    assert joined.phase_dim == 3 and len(joined) == 3
    np.testing.assert_array_equal(joined[2].positions[-1], np.zeros(5))
    np.testing.assert_array_equal(joined[2].positions[0, :2], [-8.0, 1.0])
    np.testing.assert_allclose(joined[2].positions[0, 2:], 4.0 * phase.codebook(3)[2])
    # the offset is linear in time: velocities still integrate to the positions
    np.testing.assert_allclose(joined[2].velocities[0, :2], [(0.0 + 8.0) / 2.0, -1.0 / 2.0])


def test_a_new_demonstration_ending_far_from_the_target_is_refused():
    old = Demonstrations((stroke([4.0, 0.0], [0.0, 0.0]),), np.zeros(2))
    far = Demonstrations((stroke([4.0, 4.0], [2.0, 0.0]),), np.array([2.0, 0.0]))
    with pytest.raises(DataError, match="new demonstration 0 ends 2 from the model's target"):
        added_demonstrations(old, far)
    with pytest.raises(DataError, match="dimension 3, the model's 2"):
        added_demonstrations(old, Demonstrations((stroke([1, 1, 1], [0, 0, 0]),), np.zeros(3)))


@pytest.mark.parametrize(
    "field, value",
    [
        ("steps", 0),
        ("lr", 0.0),
        ("new_weight", 0),
        ("final_lr_fraction", 2.0),
        ("batch_size", -1),
        ("batch_size", 1.5),
    ],
)
def test_refine_config_refuses_bad_values(field, value):
    with pytest.raises(ConfigError, match=field.split("_")[0]):
        RefineConfig(**{field: value})


# snds train --init


@pytest.fixture(scope="module")
def trained_folder(tmp_path_factory):
    """A compact model trained by the command line on 2 spiral demonstrations of a CSV
    file, and a second file with a third demonstration."""
    folder = tmp_path_factory.mktemp("init")
    demos = spiral_demos(count=3, samples=120)
    write_demonstrations(demos.select([0, 1]), folder / "old.csv")
    write_demonstrations(demos.select([2]), folder / "more.csv")
    argv = ["train", "--data", str(folder / "old.csv"), "--steps", "30", *COMPACT]
    assert main(["--quiet", *argv, "--out", str(folder / "base")]) == 0
    return folder


COMPACT = ["--architecture", "compact", "--rollouts", "5", "--samples", "100"]


def refine_argv(folder, out) -> list[str]:
    return [
        "--quiet",
        "train",
        "--init",
        str(folder / "base"),
        "--data",
        str(folder / "more.csv"),
        *COMPACT,
        "--out",
        str(out),
    ]


def test_train_init_refines_on_old_and_new_demonstrations(trained_folder, tmp_path):
    # WHEN the model is refined with the third demonstration
    out = tmp_path / "refined"
    assert main(refine_argv(trained_folder, out)) == 0
    policy, record = load_model(out)
    base, base_record = load_model(trained_folder / "base")
    # THEN it keeps the trained model's scaling and phase, and records where both came from
    assert record["normalization"] == base_record["normalization"]
    phase = record["data"]["phase"]
    assert phase["codes"] == base_record["data"]["phase"]["codes"]
    assert phase["extent"] == pytest.approx(base.normalization.extent)
    assert record["refined_from"]["added"]["file"] == str(trained_folder / "more.csv")
    assert record["train_result"]["steps"] == RefineConfig().steps
    # and its demonstrations file holds the old ones, then the new, as trained on
    demos = DataSource.from_record(record["data"]).load()
    old = DataSource.from_record(base_record["data"]).load()
    assert len(demos) == 3 and demos.phase_dim == 3
    for before, after in zip(old, demos):
        np.testing.assert_array_equal(before.positions, after.positions)
        np.testing.assert_array_equal(before.velocities, after.velocities)
    # snds evaluate reads it back from what model.json records
    assert main(["--quiet", "evaluate", str(out), "--rollouts", "5", "--samples", "100"]) == 0


@pytest.mark.slow  # the library's refinement resumes in the default suite (above)
def test_a_killed_cli_refinement_resumes_bit_for_bit(trained_folder, tmp_path, monkeypatch):
    reference = tmp_path / "reference"
    assert main(refine_argv(trained_folder, reference)) == 0
    # GIVEN a refinement killed after 13 steps, with a checkpoint every 5
    out = tmp_path / "killed"
    original, calls = train.step_loss, []

    def loss(*args):
        calls.append(1)
        if len(calls) > 13:
            raise Killed
        return original(*args)

    with monkeypatch.context() as patch, pytest.raises(Killed):
        patch.setattr(train, "step_loss", loss)
        main([*refine_argv(trained_folder, out), "--checkpoint-every", "5"])
    assert (out / CHECKPOINT).is_file() and not (out / "model.json").exists()
    # WHEN it is resumed THEN it ends with the uninterrupted refinement's model, bit for bit
    assert main([*refine_argv(trained_folder, out), "--resume"]) == 0
    assert same_weights(load_model(out)[0], load_model(reference)[0])


def test_train_init_without_its_old_demonstrations_says_so_in_one_line(
    trained_folder, tmp_path, capsys
):
    # GIVEN a model whose recorded demonstrations file is gone
    moved = tmp_path / "base"
    shutil.copytree(trained_folder / "base", moved)
    record = json.loads((moved / "model.json").read_text())
    record["data"]["file"] = str(tmp_path / "gone.csv")
    (moved / "model.json").write_text(json.dumps(record))
    argv = refine_argv(trained_folder, tmp_path / "out")
    argv[argv.index("--init") + 1] = str(moved)
    # THEN refining it exits 2 with one line naming the model and the file
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert f"{moved} was trained on demonstrations that cannot be read now" in err
    assert "gone.csv" in err
    # and a refinement into the trained model's own folder is refused
    assert main(refine_argv(trained_folder, trained_folder / "base")) == 2
    assert "needs a directory of its own" in capsys.readouterr().err
