import dataclasses
import json
import pickle
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import save_file

from snds.errors import ModelFileError
from snds.models import FORMAT_VERSION, load_model, save_model

from conftest import make_policy


@pytest.fixture
def saved(spiral, tmp_path):
    policy = make_policy(spiral, seed=11)
    save_model(policy, tmp_path / "model", extra={"data": {"motion": "spiral"}})
    return policy, tmp_path / "model"


def test_round_trip_gives_identical_outputs(saved):
    policy, directory = saved
    loaded, description = load_model(directory)
    x = torch.randn(1000, 2, dtype=torch.float64) * 20
    assert torch.equal(policy(x), loaded(x))
    assert description["data"] == {"motion": "spiral"}
    assert description["format_version"] == FORMAT_VERSION
    assert sorted(p.name for p in directory.iterdir()) == ["model.json", "model.safetensors"]


def test_missing_files_are_named(saved):
    _, directory = saved
    (directory / "model.safetensors").unlink()
    with pytest.raises(ModelFileError, match="model.safetensors: missing"):
        load_model(directory)
    with pytest.raises(ModelFileError, match="model.json: missing"):
        load_model(directory.parent / "nowhere")


def test_corrupted_json_and_weights_are_refused(saved):
    _, directory = saved
    weights = directory / "model.safetensors"
    weights.write_bytes(weights.read_bytes()[:100])
    with pytest.raises(ModelFileError, match="corrupted safetensors"):
        load_model(directory)
    (directory / "model.json").write_text("{not json")
    with pytest.raises(ModelFileError, match="corrupted JSON"):
        load_model(directory)


def test_newer_format_is_refused(saved):
    _, directory = saved
    description = json.loads((directory / "model.json").read_text())
    description["format_version"] = FORMAT_VERSION + 1
    (directory / "model.json").write_text(json.dumps(description))
    with pytest.raises(ModelFileError, match="newer"):
        load_model(directory)


def test_wrong_tensor_shapes_are_refused(saved):
    policy, directory = saved
    tensors = {k: v.clone() for k, v in policy.state_dict().items()}
    name = next(k for k in tensors if k.endswith("weight"))
    tensors[name] = torch.zeros(3, 3, dtype=torch.float64)
    save_file(tensors, str(directory / "model.safetensors"))
    with pytest.raises(ModelFileError, match="has shape"):
        load_model(directory)


class _Exploit:
    def __reduce__(self):
        return (exec, ("import pathlib; pathlib.Path('PWNED').write_text('x')",))


def test_a_pickle_in_place_of_the_weights_is_refused_and_never_run(saved, tmp_path, monkeypatch):
    _, directory = saved
    monkeypatch.chdir(tmp_path)
    (directory / "model.safetensors").write_bytes(pickle.dumps(_Exploit()))
    with pytest.raises(ModelFileError):
        load_model(directory)
    assert not (tmp_path / "PWNED").exists()


def test_written_files_get_the_usual_mode_not_mkstemp_s_private_one(saved):
    import os

    _, directory = saved
    umask = os.umask(0)
    os.umask(umask)
    for path in directory.iterdir():
        assert path.stat().st_mode & 0o777 == 0o666 & ~umask, path.name


def test_kind_picks_the_class_and_an_unknown_kind_is_refused(saved):
    policy, directory = saved
    description = json.loads((directory / "model.json").read_text())
    assert (description["kind"], description["method"]) == ("stable", "snds")
    # A file written before policies had kinds is an SNDS / BC policy.
    del description["kind"]
    (directory / "model.json").write_text(json.dumps(description))
    loaded, _ = load_model(directory)
    x = torch.randn(100, 2, dtype=torch.float64) * 20
    assert torch.equal(policy(x), loaded(x))
    description["kind"] = "gmr"
    (directory / "model.json").write_text(json.dumps(description))
    with pytest.raises(ModelFileError, match="unknown policy kind 'gmr'"):
        load_model(directory)


def test_a_model_saved_before_the_near_target_decay_loads_without_it(saved, spiral):
    # GIVEN a model.json written before PolicyConfig had decay_near (the key is absent)
    policy, directory = saved
    description = json.loads((directory / "model.json").read_text())
    del description["policy"]["decay_near"]
    (directory / "model.json").write_text(json.dumps(description))
    # WHEN it is loaded, THEN it is the policy it was trained as: without the term
    loaded, _ = load_model(directory)
    assert loaded.config.decay_near == 0.0
    old = make_policy(spiral, dataclasses.replace(policy.config, decay_near=0.0), seed=11)
    old.load_state_dict(policy.state_dict())
    x = torch.randn(1000, 2, dtype=torch.float64) * 0.3
    assert torch.equal(old(x), loaded(x))
    assert not torch.equal(policy(x), loaded(x))


def test_a_model_saved_before_the_warp_loads_with_a_convex_v(spiral, tmp_path):
    # GIVEN a convex model whose model.json predates the warp fields (the default since)
    config = dataclasses.replace(make_policy(spiral).config, warp_layers=0)
    policy = make_policy(spiral, config, seed=13)
    save_model(policy, tmp_path / "model")
    description = json.loads((tmp_path / "model" / "model.json").read_text())
    for key in ("warp_layers", "warp_features", "warp_scale"):
        del description["policy"][key]
    (tmp_path / "model" / "model.json").write_text(json.dumps(description))
    # WHEN it is loaded, THEN it is the convex policy it was trained as, not a warped one
    loaded, _ = load_model(tmp_path / "model")
    assert loaded.config.warp_layers == 0 and not hasattr(loaded.lyapunov, "warp")
    x = torch.randn(1000, 2, dtype=torch.float64) * 20
    assert torch.equal(policy(x), loaded(x))


def test_a_warped_policy_round_trips_and_records_its_warp(spiral, tmp_path):
    config = dataclasses.replace(make_policy(spiral).config, warp_layers=3)
    policy = make_policy(spiral, config, seed=12)
    with torch.no_grad():  # a warp away from the identity, as after training
        for p in policy.lyapunov.warp.parameters():
            p.add_(torch.randn_like(p))
    save_model(policy, tmp_path / "warped")
    loaded, description = load_model(tmp_path / "warped")
    x = torch.randn(1000, 2, dtype=torch.float64) * 20
    assert torch.equal(policy(x), loaded(x))
    assert description["policy"]["warp_layers"] == 3


FIXTURES = Path(__file__).parent / "fixtures" / "models-c52752d"


@pytest.mark.parametrize("name", ["sine", "angle-bc", "snake-se3"])
def test_models_saved_before_one_pipeline_give_the_same_velocities(name):
    # GIVEN model folders written by `snds train` at commit c52752d (before the SE(3) twins
    # became one pipeline): a warped SNDS policy (Sine), a compact BC one (Angle) and a pose
    # policy (Messy Snake, --se3), with that code's float64 velocities at 96 states 3 extents
    # around the target (poses: orientations uniform on SO(3))
    expected = json.loads((FIXTURES / "velocities.json").read_text())[name]
    policy, _ = load_model(FIXTURES / name)
    policy = policy.double()
    # WHEN today's code loads them and maps the same user states
    with torch.no_grad():
        velocities = policy(torch.tensor(expected["states"], dtype=torch.float64)).numpy()
    # THEN the velocities (twists) are those of then, to 1e-12 of the largest
    reference = np.array(expected["velocities"])
    assert velocities.shape == reference.shape
    assert np.abs(velocities - reference).max() <= 1e-12 * np.abs(reference).max()
