"""The run API: one call trains, saves with its settings, evaluates and reports, as ``snds
train`` does."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch

import snds
from snds.callbacks import Callback
from snds.data import DataSource
from snds.io import to_jsonable
from snds.models import load_model
from snds.recipes import RECIPES, Recipe
from snds.run import Run, SplitConfig, train_run
from snds.stability import CheckConfig

from conftest import SMALL

TINY = Recipe(
    policy=SMALL,
    train=dataclasses.replace(RECIPES["default"].train, steps=20),
    phase=None,
)
CHECK = CheckConfig(rollouts=4, samples=200, horizon_factor=2.0)


def _same(written: dict, record: dict) -> bool:
    """Whether a JSON file holds a record (NaN equal to NaN, tuples as lists)."""
    return json.dumps(written, sort_keys=True) == json.dumps(to_jsonable(record), sort_keys=True)


class Order(Callback):
    def __init__(self) -> None:
        self.hooks: list[str] = []

    def on_end(self, event) -> None:
        self.hooks.append("end")

    def on_saved(self, event) -> None:
        # The model is on disk when the page is told so.
        assert (event.folder / "model.safetensors").is_file()
        self.hooks.append("saved")

    def on_evaluated(self, event) -> None:
        written = json.loads((event.folder / "metrics.json").read_text())
        assert _same(written, event.metrics)
        self.hooks.append("evaluated")


def test_a_run_writes_its_config_metrics_and_model(tmp_path):
    order = Order()
    source = DataSource(motion="Line", demos=2)
    run = train_run(
        source,
        tmp_path / "run",
        recipe=TINY,
        seed=3,
        split=SplitConfig(test_fraction=0.25),
        check=CHECK,
        callbacks=[order],
    )
    # THEN the hooks of the run follow the fit's end, in order
    assert order.hooks == ["end", "saved", "evaluated"]
    assert isinstance(run, Run)
    with pytest.raises(dataclasses.FrozenInstanceError):
        run.model = None  # type: ignore[misc]
    folder = run.folder.path
    names = {p.name for p in folder.iterdir() if not p.name.startswith(".")}
    assert names == {"model.json", "model.safetensors", "metrics.json", "loss.json"}
    # The config beside the model is the run's: data, split (seeded by the run) and training.
    description = json.loads((folder / "model.json").read_text())
    assert {k: description[k] for k in ("data", "split", "train")} == run.config
    assert run.config["split"] == {"test_fraction": 0.25, "seed": 3, "test_demos": None}
    assert run.config["train"]["seed"] == 3 and run.config["train"]["steps"] == 20
    assert run.config["data"] == source.record()
    # The metrics file is the evaluation's record, with the fit's time, as snds train writes.
    metrics = json.loads((folder / "metrics.json").read_text())
    assert _same(metrics, run.metrics.to_dict())
    assert metrics["train_seconds"] == run.result.seconds > 0
    assert metrics["dtw_paper"] == run.metrics.dtw_paper
    assert metrics["stability"]["rollouts"] == 4
    assert json.loads((folder / "loss.json").read_text())["history"] == run.result.history
    assert len(run.result.history) == 20
    # The model on disk is the run's model.
    loaded, _ = load_model(folder)
    states = torch.tensor(run.demos[0].positions[::50], dtype=torch.float64)
    with torch.no_grad():
        expected = run.model.double()(states)
        np.testing.assert_array_equal(loaded.double()(states).numpy(), expected.numpy())


def test_a_run_of_a_file_path_uses_the_recipes_phase_and_the_package_exports_it(tmp_path):
    # The README's example imports from snds alone.
    assert snds.train_run is train_run and snds.Run is Run and snds.SplitConfig is SplitConfig
    csv = tmp_path / "line.csv"
    rows = ["demo,t,x1,x2"] + [f"0,{k / 10},{1 - k / 20},{2 - k / 10}" for k in range(21)]
    rows += [f"1,{k / 10},{1.2 - k / 20 * 1.2},{1.8 - k / 20 * 1.8}" for k in range(21)]
    csv.write_text("\n".join(rows) + "\n")
    run = snds.train_run(csv, tmp_path / "out", recipe=TINY, check=CHECK, split=SplitConfig())
    assert run.config["data"]["file"] == str(csv)
    assert "phase" not in run.config["data"]
    assert run.metrics.stability.rollouts == 4
