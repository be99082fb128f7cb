"""The run folder keeps a model with its own results only, whatever interrupts a run."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

import snds.models
import snds.runs
from snds.errors import ConfigError
from snds.runs import RunFolder
from snds.train import TrainResult

from conftest import SMALL, make_policy, spiral_demos

RECORD = {"data": {"motion": "spiral"}, "split": {"test_fraction": 0.2, "seed": 0}}


def _result(history: list[float]) -> TrainResult:
    return TrainResult(history=history, seconds=1.5, steps=len(history))


def _policy(seed: int):
    return make_policy(spiral_demos(), config=SMALL, seed=seed, dtype=torch.float64)


def test_save_then_load_gives_the_same_velocities_and_record(tmp_path: Path) -> None:
    # GIVEN a policy saved with its training result
    run = RunFolder(tmp_path / "run")
    policy = _policy(seed=1)
    run.save(policy, _result([3.0, 2.0, 1.0]), record=RECORD)
    # WHEN it is loaded back
    loaded, description = run.load()
    # THEN it computes the same velocities, and the record, history and config are kept
    x = 3 * torch.randn(500, 2, dtype=torch.float64)
    assert torch.equal(loaded(x), policy.eval()(x))
    assert description["data"] == RECORD["data"] and description["split"] == RECORD["split"]
    assert description["train_result"]["steps"] == 3
    assert "history" not in description["train_result"]
    assert run.read_history() == [3.0, 2.0, 1.0]
    assert run.read_config() == description


def test_a_killed_save_leaves_no_stale_results_beside_the_new_model(tmp_path, monkeypatch):
    # GIVEN a finished run: a model, its loss and its metrics
    run = RunFolder(tmp_path)
    run.save(_policy(seed=1), _result([1.0]), record=RECORD)
    run.write_metrics({"velocity_mse": 0.5})
    old_weights = (tmp_path / snds.models.WEIGHTS).read_bytes()

    # WHEN a new training's save is killed after the model, before its loss history
    def killed(path: Path, data: dict) -> None:
        if Path(path).name == "loss.json":
            raise KeyboardInterrupt
        original(path, data)

    original = snds.runs.write_json
    monkeypatch.setattr(snds.runs, "write_json", killed)
    with pytest.raises(KeyboardInterrupt):
        run.save(_policy(seed=2), _result([2.0]), record=RECORD)
    # THEN the new model is there and no result of the old one is beside it
    assert (tmp_path / snds.models.WEIGHTS).read_bytes() != old_weights
    assert run.read_metrics() is None and run.read_history() is None
    run.load()  # the pair of model files is consistent


def test_prepare_removes_temporaries_and_the_checkpoint_unless_resuming(tmp_path) -> None:
    # GIVEN a folder a killed training left: a temporary and a checkpoint
    run = RunFolder(tmp_path)
    temporary = tmp_path / ".model.json.abc.tmp"
    temporary.write_text("half")
    run.checkpoint.write_bytes(b"state")
    # WHEN a resumed training prepares it, THEN the checkpoint stays, the temporary goes
    run.prepare(resume=True)
    assert run.checkpoint.is_file() and not temporary.exists()
    # AND a new training removes the checkpoint too, as does a finished one
    run.prepare(resume=False)
    assert not run.checkpoint.exists()
    run.checkpoint.write_bytes(b"state")
    run.finish()
    assert not run.checkpoint.exists()


def test_prepare_refuses_a_file_in_place_of_the_folder(tmp_path) -> None:
    path = tmp_path / "model"
    path.write_text("not a folder")
    with pytest.raises(ConfigError, match="is a file, not a directory"):
        RunFolder(path).prepare()


def test_model_files_written_elsewhere_equal_a_save(tmp_path) -> None:
    # GIVEN the model files of a policy, made where the folder is not reachable
    policy = _policy(seed=3)
    files = RunFolder.model_files(policy, RECORD)
    # WHEN they are written into a folder that held another run's metrics
    run = RunFolder(tmp_path / "run")
    run.write_metrics({"old": True})
    run.write_files(files)
    # THEN the folder holds exactly the model, without the stale metrics, and loads
    assert sorted(p.name for p in run.path.iterdir()) == sorted(files)
    loaded, description = run.load()
    x = torch.randn(100, 2, dtype=torch.float64)
    assert torch.equal(loaded(x), policy.eval()(x))
    assert json.loads((run.path / "model.json").read_text()) == description
