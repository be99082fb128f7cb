"""Interrupted work, checkpoints, precision and the far field.

The kill tests start real ``snds train`` and ``snds benchmark`` processes, SIGKILL them
midway, check that every file they left is absent or complete, then resume and finish. They
shorten the stability check's horizon (see :data:`DRIVER`): the check itself is tested in
test_stability.py, and here only its files matter.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from safetensors import safe_open

from snds import evaluate as evaluate_module
from snds.cli import main
from snds.data import no_split, split_samples
from snds.errors import CheckpointError
from snds.methods import POLICY_KINDS
from snds.models import load_model
from snds.policy import PolicyConfig, StablePolicy, float64_copy
from snds.train import CHECKPOINT, TrainConfig, fit

from conftest import SMALL, make_policy, spiral_demos

HORIZON = 0.2
"""Stability rollouts of 0.2x the longest demonstration, not 10x: seconds, not minutes."""

DRIVER = f"""
import dataclasses, sys
import snds.evaluate
check = snds.evaluate.check_stability
snds.evaluate.check_stability = lambda policy, demos, config=snds.evaluate.CheckConfig(): check(
    policy, demos, dataclasses.replace(config, horizon_factor={HORIZON})
)
from snds.cli import main
sys.exit(main(sys.argv[1:]))
"""


@pytest.fixture(autouse=True, scope="module")
def one_thread():
    """One torch thread, as the CLI uses: two threads on a busy 2-core machine crawl."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture
def short_check(monkeypatch):
    """The same shortened stability check in this process."""
    check = evaluate_module.check_stability

    def short(policy, demos, config=None):
        config = evaluate_module.CheckConfig() if config is None else config
        return check(policy, demos, dataclasses.replace(config, horizon_factor=HORIZON))

    monkeypatch.setattr(evaluate_module, "check_stability", short)


def start(argv: list[str]) -> subprocess.Popen:
    """``snds ARGV`` in its own process group, so a kill reaches any worker too."""
    return subprocess.Popen(
        [sys.executable, "-c", DRIVER, "--quiet", *argv],
        start_new_session=True,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
    )


def kill_when(process: subprocess.Popen, ready, timeout: float = 300.0) -> None:
    """SIGKILLs the process group as soon as ``ready()`` holds."""
    deadline = time.monotonic() + timeout
    while not ready():
        if process.poll() is not None:
            pytest.fail(f"finished before the kill: {process.stderr.read().decode()}")
        if time.monotonic() > deadline:
            os.killpg(process.pid, signal.SIGKILL)
            pytest.fail("never got midway")
        time.sleep(0.01)
    os.killpg(process.pid, signal.SIGKILL)
    process.wait()
    process.stderr.close()


def visible(folder: Path) -> set[str]:
    """Names of the files in a folder, without atomic_write's hidden temporaries."""
    return {p.name for p in folder.iterdir() if not p.name.startswith(".")}


def checkpoint_record(path: Path) -> dict:
    with safe_open(str(path), framework="pt") as file:
        return json.loads(file.metadata()["snds_checkpoint"])


def same_weights(a: torch.nn.Module, b: torch.nn.Module) -> bool:
    left, right = a.state_dict(), b.state_dict()
    return left.keys() == right.keys() and all(torch.equal(left[k], right[k]) for k in left)


TRAIN = ["train", "--motion", "Line", "--demos", "2", "--steps", "80"]
TRAIN += ["--checkpoint-every", "10", "--rollouts", "5", "--samples", "100"]


#: The same run for positions, and lifted to SE(3) poses with grid starts in its check.
TRAIN_RUNS = {"positions": TRAIN, "poses": [*TRAIN, "--se3", "--grid"]}


@pytest.mark.parametrize("kind", list(TRAIN_RUNS))
def test_killed_train_resumes_to_the_uninterrupted_model(kind, tmp_path, short_check):
    # GIVEN the model of an uninterrupted run
    TRAIN = TRAIN_RUNS[kind]
    reference = tmp_path / "reference"
    assert main(["--quiet", *TRAIN, "--out", str(reference)]) == 0
    # WHEN the same run is killed with SIGKILL right after its first checkpoint
    run = tmp_path / "run"
    kill_when(start([*TRAIN, "--out", str(run)]), (run / CHECKPOINT).is_file)
    # THEN it left only a complete checkpoint, midway, and no model
    assert visible(run) == {CHECKPOINT}
    record = checkpoint_record(run / CHECKPOINT)
    assert 0 < record["step"] < 80 and not record["finished"]
    # WHEN it is resumed THEN it finishes with the same model, bit for bit, and the same files
    assert main(["--quiet", *TRAIN, "--resume", "--out", str(run)]) == 0
    assert same_weights(load_model(run)[0], load_model(reference)[0])
    assert sorted(p.name for p in run.iterdir()) == sorted(p.name for p in reference.iterdir())
    losses = [json.loads((d / "loss.json").read_text()) for d in (run, reference)]
    assert losses[0] == losses[1]
    assert json.loads((run / "model.json").read_text())["train_result"]["steps"] == 80
    assert json.loads((run / "model.json").read_text())["kind"] == (
        "se3" if kind == "poses" else "stable"
    )
    metrics = json.loads((run / "metrics.json").read_text())
    # --grid: 5 rollouts asked for, 2 grid points per axis of a 2-D (positions) or a 3-D
    # (poses: orientations drawn at each point) box
    assert metrics["stability"]["rollouts"] == (8 if kind == "poses" else 5)
    assert metrics == json.loads((reference / "metrics.json").read_text()) | {
        "train_seconds": metrics["train_seconds"]
    }


BENCH = ["benchmark", "--motions", "Line", "--methods", "snds", "--seeds", "2", "--demos", "2"]
BENCH += ["--steps", "20", "--rollouts", "5", "--samples", "100", "--jobs", "1"]


def rows(path: Path) -> list[dict]:
    return [json.loads(line) for line in path.read_text().splitlines()]


def test_killed_benchmark_keeps_complete_runs_and_resumes(tmp_path, short_check):
    out = tmp_path / "bench"
    results = out / "results.jsonl"
    # WHEN a sweep of two runs is killed with SIGKILL once the first is stored
    process = start([*BENCH, "--out", str(out)])
    kill_when(process, lambda: results.is_file() and results.read_text().endswith("\n"))
    # THEN every stored row has its model, complete; nothing else is half there
    done = rows(results)
    assert len(done) == 1
    for row in done:
        folder = out / "models" / "Line" / "snds" / f"seed={row['seed']}-demos=2"
        load_model(folder)
    assert not (out / "results.csv").exists() and not (out / "summary.md").exists()
    # WHEN it is run again THEN it trains only the missing runs and writes everything
    assert main(["--quiet", *BENCH, "--out", str(out)]) == 0
    final = rows(results)
    assert final[0] == done[0] and sorted(r["seed"] for r in final) == [0, 1]
    with open(out / "results.csv") as handle:
        assert [int(r["seed"]) for r in csv.DictReader(handle)] == [0, 1]
    for seed in range(2):
        load_model(out / "models" / "Line" / "snds" / f"seed={seed}-demos=2")


# Checkpoints in the API.


class Killed(BaseException):
    """Stands for a kill inside a fit."""


def interrupted_fit(policy, demos, split, config, checkpoint, monkeypatch, after: int) -> None:
    """Runs ``fit`` until ``after`` losses were computed, then stops it dead."""
    from snds import train

    original, calls = train.step_loss, []

    def loss(*args):
        calls.append(1)
        if len(calls) > after:
            raise Killed
        return original(*args)

    with monkeypatch.context() as patch:
        patch.setattr(train, "step_loss", loss)
        with pytest.raises(Killed):
            fit(
                policy,
                demos,
                split,
                config,
                progress=False,
                checkpoint=checkpoint,
                checkpoint_every=10,
            )


@pytest.fixture(scope="module")
def task():
    demos = spiral_demos(count=2, samples=200)
    config = TrainConfig(steps=40, window=2, batch_size=64, window_batch_size=16)
    return demos, split_samples(demos, test_fraction=0.2, seed=0), config


def test_resume_gives_the_same_weights_and_history_bit_for_bit(task, tmp_path, monkeypatch):
    demos, split, config = task
    reference = make_policy(demos, SMALL, seed=5)
    expected = fit(reference, demos, split, config, progress=False)
    checkpoint = tmp_path / CHECKPOINT
    interrupted_fit(
        make_policy(demos, SMALL, seed=5), demos, split, config, checkpoint, monkeypatch, 25
    )
    assert checkpoint_record(checkpoint)["step"] == 20
    resumed = make_policy(demos, SMALL, seed=5)
    result = fit(resumed, demos, split, config, progress=False, checkpoint=checkpoint)
    assert same_weights(resumed, reference) and result.history == expected.history
    assert result.steps == expected.steps == 40
    # A finished checkpoint gives the final weights without training again.
    again = make_policy(demos, SMALL, seed=5)
    assert fit(again, demos, split, config, progress=False, checkpoint=checkpoint).steps == 40
    assert same_weights(again, reference)


def test_a_pose_fit_resumes_bit_for_bit(tmp_path, monkeypatch):
    # GIVEN a pose task (a spiral lifted to SE(3)) and a fit killed after 25 steps
    from snds.data.poses import with_synthetic_orientations
    from snds.method import make_policy as make_any_policy

    poses = with_synthetic_orientations(spiral_demos(count=2, samples=150), seed=1)
    split = split_samples(poses, test_fraction=0.2, seed=0)
    config = TrainConfig(
        steps=40, batch_size=64, position_noise=0.0, noise_correction=0.0, shape_weight=0.01
    )
    reference = make_any_policy(poses, config=SMALL, seed=5)
    expected = fit(reference, poses, split, config, progress=False)
    checkpoint = tmp_path / CHECKPOINT
    killed = make_any_policy(poses, config=SMALL, seed=5)
    interrupted_fit(killed, poses, split, config, checkpoint, monkeypatch, 25)
    # WHEN it is resumed from its checkpoint
    resumed = make_any_policy(poses, config=SMALL, seed=5)
    result = fit(resumed, poses, split, config, progress=False, checkpoint=checkpoint)
    # THEN it ends where the uninterrupted fit ended, as a position fit does
    assert same_weights(resumed, reference) and result.history == expected.history


def test_a_checkpoint_of_other_settings_or_data_is_refused(task, tmp_path, monkeypatch):
    demos, split, config = task
    checkpoint = tmp_path / CHECKPOINT
    interrupted_fit(make_policy(demos, SMALL), demos, split, config, checkpoint, monkeypatch, 15)
    other = TrainConfig(**{**config.to_dict(), "lr": 2 * config.lr})
    changed = rf"other train settings \(train.lr: {config.lr} -> {2 * config.lr}\)"
    with pytest.raises(CheckpointError, match=changed):
        fit(make_policy(demos, SMALL), demos, split, other, progress=False, checkpoint=checkpoint)
    with pytest.raises(CheckpointError, match="other training data"):
        fit(
            make_policy(demos, SMALL),
            demos,
            no_split(demos),
            config,
            progress=False,
            checkpoint=checkpoint,
        )
    wider = PolicyConfig(**{**SMALL.to_dict(), "hidden": (48, 48)})
    with pytest.raises(CheckpointError, match="other architecture"):
        fit(make_policy(demos, wider), demos, split, config, progress=False, checkpoint=checkpoint)


@pytest.mark.parametrize("keep", [0, 10, 1000, -100])
def test_a_damaged_checkpoint_is_refused(task, tmp_path, monkeypatch, keep):
    demos, split, config = task
    checkpoint = tmp_path / CHECKPOINT
    interrupted_fit(make_policy(demos, SMALL), demos, split, config, checkpoint, monkeypatch, 15)
    checkpoint.write_bytes(checkpoint.read_bytes()[:keep] if keep else b"")
    with pytest.raises(CheckpointError, match="corrupted checkpoint"):
        fit(make_policy(demos, SMALL), demos, split, config, progress=False, checkpoint=checkpoint)


def test_resume_without_a_checkpoint_trains_from_the_start(tmp_path, short_check, capsys):
    out = tmp_path / "fresh"
    argv = ["train", "--motion", "Line", "--demos", "1", "--steps", "20", "--rollouts", "2"]
    assert main([*argv, "--samples", "10", "--resume", "--out", str(out)]) == 0
    assert "no checkpoint" in capsys.readouterr().err
    assert visible(out) == {"model.json", "model.safetensors", "metrics.json", "loss.json"}


# Precision and the far field.


@pytest.mark.parametrize("model_dtype", [torch.float32, torch.float64])
def test_a_model_takes_positions_of_any_dtype(model_dtype):
    demos = spiral_demos()
    policy = make_policy(demos, dtype=model_dtype)
    x = torch.randn(50, 2, dtype=torch.float64) * 10
    expected = policy(x.to(model_dtype))
    for dtype in (torch.float32, torch.float64, torch.int64):
        got = policy(x.to(dtype))
        assert got.dtype == model_dtype
        if dtype != torch.int64:
            torch.testing.assert_close(got, policy(x.to(dtype).to(model_dtype)), rtol=0, atol=0)
    assert torch.equal(policy(x.to(model_dtype)), expected)


def far_states(demos, dtype, count=2000, seed=0) -> torch.Tensor:
    """States in user units at 1 to 1e6 times the data's extent from the target, all directions."""
    generator = torch.Generator().manual_seed(seed)
    directions = torch.randn(count, demos.dim, generator=generator, dtype=torch.float64)
    directions /= directions.norm(dim=-1, keepdim=True)
    radii = demos.extent() * 10 ** torch.linspace(0, 6, count, dtype=torch.float64)
    return (torch.as_tensor(demos.target.copy()) + directions * radii[:, None]).to(dtype)


def stable_policies():
    demos = spiral_demos()
    trained = make_policy(demos)
    fit(trained, demos, no_split(demos), TrainConfig(steps=30, dtype="float64"), progress=False)
    policies = {"snds untrained": make_policy(demos), "snds trained": trained}
    for kind in ("lpvds", "seds", "sdsef"):
        cls = POLICY_KINDS[kind]
        policies[kind] = cls(dim=2, normalization=trained.normalization, config=cls.config_class())
    policies["snds default architecture"] = StablePolicy(
        dim=2, normalization=trained.normalization, config=PolicyConfig()
    )
    return demos, policies


@pytest.fixture(scope="module")
def far_field():
    return stable_policies()


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize(
    "name",
    ["snds untrained", "snds trained", "snds default architecture", "lpvds", "seds", "sdsef"],
)
def test_far_field_is_finite_and_downhill(far_field, name, dtype):
    # GIVEN a policy with a Lyapunov function, in float32 or float64
    demos, policies = far_field
    policy = policies[name].to(dtype).eval()
    # WHEN it is evaluated up to 1e6 times the data's extent from the target
    x = far_states(demos, dtype)
    with torch.no_grad():
        velocity = policy(x)
    # THEN every velocity is finite and points downhill on V (checked in float64)
    assert velocity.dtype == dtype and torch.isfinite(velocity).all()
    exact = float64_copy(policy)
    model_x = exact.to_model(x.double())
    _, grad_v = exact.lyapunov.value_and_grad(model_x)
    slope = (grad_v * velocity.double()).sum(-1)
    assert (slope < 0).all(), f"{int((slope >= 0).sum())} of {len(x)} states go uphill"
