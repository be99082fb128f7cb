"""The page's JSON API over HTTP (Starlette's TestClient): every endpoint, what it promises,
and how it treats bad input (each row of docs/bad-input.md's API table is a case here)."""

from __future__ import annotations

import io
import os
import re
import shutil
import signal
import subprocess
import time
import zipfile
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

pytest.importorskip("starlette", reason="snds app needs the app extra (pip install 'snds[app]')")

from starlette.testclient import TestClient  # noqa: E402

from snds.app import LIMITS, create_app  # noqa: E402
from snds.app.strokes import parse_strokes, write_csv  # noqa: E402
from snds.app.worker import Preview  # noqa: E402
from snds.cli import main  # noqa: E402
from snds.data import DataSource  # noqa: E402
from snds.models import load_model  # noqa: E402
from snds.phase import start_rule, start_states  # noqa: E402
from snds.policy import float64_copy  # noqa: E402
from snds.recipes import RECIPES  # noqa: E402
from snds.rollout import policy_guard  # noqa: E402
from snds.run import train_run  # noqa: E402
from snds.stability import CheckConfig  # noqa: E402


def _job(client: TestClient, job: str):
    return client.app.state.jobs.get(job)


def _policy(client: TestClient, job: str):
    policy, _ = load_model(_job(client, job).model)
    return float64_copy(policy)


# --- Health, page, files ----------------------------------------------------------------------


def test_health_and_limits(client) -> None:
    assert client.get("/api/health").json()["ok"] is True
    assert client.get("/api/limits").json() == LIMITS.to_dict()


def test_the_page_and_its_files_are_served(client) -> None:
    page = client.get("/")
    assert page.status_code == 200 and "<canvas" in page.text
    assert "/static/app.js" in page.text
    for name in ("app.js", "style.css"):
        assert client.get(f"/static/{name}").status_code == 200
    # No CDN: the page loads nothing from elsewhere.
    assert "http" not in page.text.replace("http-equiv", "")


@pytest.mark.parametrize(
    "path",
    [
        "/static/../server.py",
        "/static/%2e%2e/server.py",
        "/static/..%2fserver.py",
        "/static//etc/passwd",
        "/api/jobs/..%2f..%2fetc/model.zip",
        "/etc/passwd",
    ],
)
def test_no_path_outside_the_static_files_is_served(client, path: str) -> None:
    answer = client.get(path)
    assert answer.status_code == 404
    assert answer.json()["error"].startswith("not found: ")


def test_a_request_for_another_host_name_is_refused(client) -> None:
    # A page elsewhere that rebinds its DNS name to 127.0.0.1 must not reach the API.
    answer = client.get("/api/health", headers={"host": "evil.example"})
    # The JSON of every refusal, as docs/bad-input.md promises.
    assert (answer.status_code, answer.json()) == (
        400,
        {
            "error": "host 'evil.example' is not served here (only 127.0.0.1, ::1, [::1], "
            "localhost); open the page at its address"
        },
    )
    # The loopback's names, with a port, are served.
    for host in ("localhost:8765", "127.0.0.1", "[::1]:8765"):
        assert client.get("/api/health", headers={"host": host}).status_code == 200


# --- Training, streaming, results -------------------------------------------------------------


def test_training_streams_its_real_progress_and_ends_with_the_check(trained, helpers) -> None:
    job, _, events = trained
    steps = [e["step"] for e in events if e["state"] == "training"]
    # Monotone real step counts, up to the steps asked for.
    assert steps == sorted(steps)
    assert events[-1]["step"] == events[-1]["total"] == helpers.tiny["steps"]
    states = [e["state"] for e in events]
    assert "checking" in states and states.index("checking") < states.index("done")
    stability = events[-1]["metrics"]["stability"]
    assert stability["rollouts"] == helpers.tiny["rollouts"]
    assert stability["samples_checked"] == helpers.tiny["samples"]
    assert stability["converged_fraction"] == 1.0
    assert stability["decrease_violations"] == 0
    assert stability["largest_safe_dt"] > 0
    assert events[-1]["worker_cpu_seconds"] > 0


def test_the_run_folder_is_what_snds_train_writes(client, trained, tmp_path: Path) -> None:
    # GIVEN the job's strokes CSV and settings
    job, _, _ = trained
    folder = _job(client, job).model
    csv = tmp_path / "strokes.csv"
    csv.write_bytes((folder / "strokes.csv").read_bytes())
    # WHEN snds train runs on them with the same settings
    out = tmp_path / "cli"
    argv = ["--quiet", "train", "--data", str(csv), "--out", str(out), "--steps", "30"]
    assert main([*argv, "--rollouts", "20", "--samples", "500"]) == 0
    # THEN the same files, and the same weights bit for bit
    made = {p.name for p in folder.iterdir()} - {"strokes.csv"}
    assert made == {p.name for p in out.iterdir()}
    ours, _ = load_model(folder)
    theirs, _ = load_model(out)
    for (name, a), (_, b) in zip(ours.state_dict().items(), theirs.state_dict().items()):
        assert torch.equal(a, b), name


def test_result_holds_the_strokes_and_their_reproductions(trained) -> None:
    job, body, events = trained
    result = events[-1]["result"]
    strokes = parse_strokes(body)
    assert np.allclose(result["target"], strokes.target)
    for demo, repro, stroke in zip(result["demos"], result["reproductions"], strokes.positions):
        assert np.array_equal(np.array(demo), stroke)
        # A reproduction starts at its stroke's start and has its length.
        assert np.array_equal(repro[0], stroke[0]) and len(repro) == len(stroke)


def test_field_equals_the_policy_on_the_same_grid(client, trained) -> None:
    job, _, _ = trained
    answer = client.post(
        f"/api/jobs/{job}/field", json={"bounds": [-80, 90, -60, 70], "size": [17, 13]}
    )
    assert answer.status_code == 200
    field = answer.json()
    xs, ys = np.array(field["x"]), np.array(field["y"])
    assert np.array_equal(xs, np.linspace(-80, 90, 17))
    assert np.array_equal(ys, np.linspace(-60, 70, 13))
    points = np.stack(np.meshgrid(xs, ys), axis=-1).reshape(-1, 2)
    policy = _policy(client, job)
    # The default model has a phase: a point's velocity is the one a new start there takes.
    demos = _job(client, job).extra["demos"]
    assert demos.phase_dim == 3
    states = start_states(demos, points)
    expected = policy.predict(states)[:, :2].reshape(13, 17, 2)
    np.testing.assert_allclose(field["velocity"], expected, rtol=1e-12, atol=1e-12)
    lyapunov, _ = policy_guard(policy)
    with torch.no_grad():
        values = lyapunov(torch.from_numpy(states)).numpy().reshape(13, 17)
    np.testing.assert_allclose(field["V"], values, rtol=1e-12, atol=1e-15)
    assert np.array(field["V"]).min() >= 0


def test_rollout_reaches_the_target_and_recovers_from_a_push(client, trained) -> None:
    # GIVEN a start far from the strokes and a push halfway
    job, _, events = trained
    result = events[-1]["result"]
    push = [40.0, -30.0]
    body = {"start": [-90.0, 60.0], "pushes": [{"at": 0.3, "by": push}]}
    # WHEN the policy is rolled out
    answer = client.post(f"/api/jobs/{job}/rollout", json=body).json()
    states, times = np.array(answer["states"]), np.array(answer["t"])
    # THEN it ends within the check's tolerance of the target
    assert answer["arrived"] is True and answer["integrator"] == "guarded euler"
    assert np.linalg.norm(states[-1] - result["target"]) <= answer["tolerance"]
    assert answer["tolerance"] == pytest.approx(0.01 * result["extent"])
    # AND the push displaced it once, at its time
    jumps = np.flatnonzero(np.diff(times) == 0)
    assert len(jumps) == 1 and times[jumps[0]] >= 0.3
    np.testing.assert_allclose(states[jumps[0] + 1] - states[jumps[0]], push)
    # AND every guarded step decreased V (the push may not)
    # (the whole states: a push moves the position, the phase keeps its value)
    whole = np.concatenate([states, np.array(answer["phases"])], axis=1)
    np.testing.assert_array_equal(whole[jumps[0] + 1, 2:], whole[jumps[0], 2:])
    lyapunov, _ = policy_guard(_policy(client, job))
    with torch.no_grad():
        values = lyapunov(torch.from_numpy(whole)).numpy()
    assert (np.delete(np.diff(values), jumps[0]) < 0).all()


def test_model_zip_evaluates_exports_and_simulates_through_the_cli(
    client, trained, tmp_path: Path
) -> None:
    job, _, _ = trained
    answer = client.get(f"/api/jobs/{job}/model.zip")
    assert answer.status_code == 200 and answer.headers["content-type"] == "application/zip"
    with zipfile.ZipFile(io.BytesIO(answer.content)) as archive:
        archive.extractall(tmp_path)
    (model,) = tmp_path.iterdir()
    names = {p.name for p in model.iterdir()}
    assert names == {"model.json", "model.safetensors", "metrics.json", "loss.json", "strokes.csv"}
    data = ["--data", str(model / "strokes.csv")]
    sim = ["--robot", "iiwa", "--time-limit", "2", "--frames", "0", "--out", str(tmp_path / "sim")]
    for argv in (
        ["evaluate", str(model), *data, "--rollouts", "20", "--samples", "500"],
        ["export", str(model), "--format", "onnx", "--samples", "200"],
        ["simulate", str(model), *data, *sim],
    ):
        assert main(["--quiet", *argv]) == 0, argv
    assert (model / "policy.onnx").is_file()
    assert (tmp_path / "sim" / "sim.json").is_file()
    # And it trains on: the strokes are the file the job trained on (which snds train reads
    # to the same weights: test_the_run_folder_is_what_snds_train_writes).
    job_csv = _job(client, job).model / "strokes.csv"
    assert (model / "strokes.csv").read_bytes() == job_csv.read_bytes()


def test_onnx_download_computes_the_policy(client, trained, tmp_path: Path) -> None:
    from snds.export import load_onnx

    job, _, _ = trained
    answer = client.get(f"/api/jobs/{job}/policy.onnx")
    assert answer.status_code == 200, answer.text
    path = tmp_path / "policy.onnx"
    path.write_bytes(answer.content)
    points = np.random.default_rng(0).uniform(-100, 100, size=(200, 2))
    states = start_states(_job(client, job).extra["demos"], points)
    policy = _policy(client, job)
    expected = policy.predict(states)
    got = load_onnx(path)(states.astype(np.float32))
    scale = np.abs(expected).max()
    assert np.abs(got - expected).max() <= 3e-4 * scale


def test_strokes_csv_round_trips_into_the_same_strokes(client, trained, helpers) -> None:
    job, body, _ = trained
    csv = client.post("/api/strokes.csv", json=body)
    assert csv.status_code == 200 and csv.text.startswith("demo,t,x1,x2\n")
    assert csv.text == client.get(f"/api/jobs/{job}/strokes.csv").text
    back = client.post(
        "/api/strokes/upload", content=csv.content, headers={"content-type": "text/csv"}
    )
    assert back.status_code == 200
    again, before = parse_strokes(back.json()), parse_strokes(body)
    assert np.array_equal(again.target, before.target)
    for a, b in zip(again.positions, before.positions):
        assert np.array_equal(a, b)
    for a, b in zip(again.times, before.times):
        assert np.array_equal(a, b)


def test_a_dragged_target_is_where_every_stroke_ends(client, helpers) -> None:
    body = {"strokes": helpers.strokes(), "target": [10.0, 12.5]}
    back = client.post(
        "/api/strokes/upload",
        content=client.post("/api/strokes.csv", json=body).content,
        headers={"content-type": "text/csv"},
    ).json()
    assert back["target"] == [10.0, 12.5]
    assert all(stroke[-1][:2] == [10.0, 12.5] for stroke in back["strokes"])
    # Starts stay where they were drawn.
    assert [s[0] for s in back["strokes"]] == [s[0] for s in body["strokes"]]


# --- Jobs: cancelling, killed workers, responsiveness, shutdown -------------------------------


def _long_job(client: TestClient, helpers) -> str:
    body = {"strokes": helpers.strokes(), "settings": {"steps": 100_000}}
    job = client.post("/api/train", json=body).json()["id"]
    deadline = time.monotonic() + 60
    while client.get(f"/api/jobs/{job}").json()["step"] < 1:
        assert time.monotonic() < deadline, "the worker never started training"
        time.sleep(0.05)
    return job


def test_a_training_job_previews_its_field_before_the_model_is_saved(client, helpers) -> None:
    # GIVEN a long training that asks for previews on a 12 x 8 grid
    grid = {"bounds": [-60.0, 10.0, -30.0, 30.0], "size": [12, 8]}
    body = {"strokes": helpers.strokes(), "settings": {"steps": 100_000}, "preview": grid}
    job = client.post("/api/train", json=body).json()["id"]
    # THEN there is none at first (the first comes after a second of training)
    early = client.get(f"/api/jobs/{job}/preview")
    assert early.status_code == 409 and "has no preview" in early.json()["error"]
    # AND previews then come while it trains, each of a later step
    steps = []
    deadline = time.monotonic() + 90
    while len(steps) < 2:
        assert time.monotonic() < deadline, "no previews came"
        status = client.get(f"/api/jobs/{job}").json()
        if status["previews"] > len(steps):
            steps.append(client.get(f"/api/jobs/{job}/preview").json())
        time.sleep(0.05)
    assert status["state"] == "training" and "policy" not in _job(client, job).extra
    assert 0 < steps[0]["step"] < steps[1]["step"] < 100_000
    # each the field of the policy being trained on the asked grid: finite velocities and a V
    # that is positive away from the target
    latest = steps[1]
    assert np.allclose(latest["x"], np.linspace(-60, 10, 12))
    assert np.allclose(latest["y"], np.linspace(-30, 30, 8))
    velocity, value = np.array(latest["velocity"]), np.array(latest["V"])
    assert velocity.shape == (8, 12, 2) and np.isfinite(velocity).all()
    assert value.shape == (8, 12) and (value > 0).all()
    client.delete(f"/api/jobs/{job}")
    helpers.wait_for(client, job, {"cancelled"})


def test_previews_leave_the_trained_model_unchanged(tmp_path, helpers) -> None:
    # GIVEN the same short fit of the page's strokes, once with a preview at every step
    write_csv(parse_strokes({"strokes": helpers.strokes()}), tmp_path / "strokes.csv")
    recipe = RECIPES["default"]
    recipe = replace(recipe, train=replace(recipe.train, steps=12))
    source = DataSource(file=tmp_path / "strokes.csv", phase=recipe.phase)
    rule = start_rule(source.load())
    sent: list[dict] = []
    preview = Preview(
        sent.append, np.linspace(-60, 10, 5), np.linspace(-30, 30, 4), rule.start_states, every=0.0
    )
    check = CheckConfig(rollouts=5, samples=50)
    runs = [
        train_run(source, tmp_path / name, recipe=recipe, check=check, callbacks=callbacks)
        for name, callbacks in (("with", [preview]), ("without", []))
    ]
    # THEN every step but the last (whose saved field follows) sent one
    assert [message["step"] for message in sent] == list(range(1, 12))
    # AND the weights are the same to the bit: a preview reads the policy, never changes it
    trained = [run.model.state_dict() for run in runs]
    assert trained[0].keys() == trained[1].keys()
    assert all(torch.equal(trained[0][key], trained[1][key]) for key in trained[0])


def test_a_new_request_cancels_the_running_job_and_the_server_stays_responsive(
    client, trained, helpers
) -> None:
    first = _long_job(client, helpers)
    # While it trains, the server answers at once, the field of a finished job included.
    done, _, _ = trained
    for _ in range(5):
        start = time.perf_counter()
        assert client.get("/api/health").status_code == 200
        field = {"bounds": [-50, 50, -50, 50], "size": [20, 20]}
        assert client.post(f"/api/jobs/{done}/field", json=field).status_code == 200
        assert time.perf_counter() - start < 2.0
    second = client.post(
        "/api/train", json={"strokes": helpers.strokes(), "settings": {"steps": 100_000}}
    )
    assert second.status_code == 202
    status = helpers.wait_for(client, first, {"cancelled", "error", "done"})
    assert status["state"] == "cancelled"
    assert _job(client, first).process.poll() is not None
    cancelled = client.delete(f"/api/jobs/{second.json()['id']}")
    assert cancelled.status_code == 200
    assert helpers.wait_for(client, second.json()["id"], {"cancelled"})["state"] == "cancelled"


def test_a_killed_worker_is_an_error_on_its_job_and_the_server_keeps_working(
    client, helpers
) -> None:
    job = _long_job(client, helpers)
    os.kill(_job(client, job).process.pid, signal.SIGKILL)
    status = helpers.wait_for(client, job, {"error", "done", "cancelled"})
    assert status["state"] == "error"
    assert status["error"] == (
        "the training worker stopped unexpectedly (it was killed by signal 9); train again"
    )
    assert client.get("/api/health").json()["ok"] is True
    answer = client.get(f"/api/jobs/{job}/model.zip")
    assert answer.status_code == 409
    assert answer.json() == {"error": f"job {job} ended without a model (error)"}
    # A new job gets a new worker.
    again = client.post(
        "/api/train", json={"strokes": helpers.strokes(), "settings": {"steps": 100_000}}
    )
    assert again.status_code == 202
    assert _job(client, again.json()["id"]).process.pid != _job(client, job).process.pid
    client.delete(f"/api/jobs/{again.json()['id']}")
    helpers.wait_for(client, again.json()["id"], {"cancelled"})


def test_shutdown_stops_the_workers_and_removes_the_temporaries(helpers) -> None:
    with TestClient(create_app(), base_url="http://127.0.0.1") as own:
        runs = own.app.state.runs
        body = {"strokes": helpers.strokes(), "settings": {"steps": 100_000}}
        job = own.post("/api/train", json=body).json()["id"]
        worker = _job(own, job).process
        assert (runs / job / "model" / "strokes.csv").is_file()
    assert not runs.exists()
    assert worker.poll() is not None


# --- Bad input --------------------------------------------------------------------------------


def _stroke(points: int = 3) -> list[list[float]]:
    return [[float(10 * k), float(5 * k), 0.1 * k] for k in range(points)]


def _json(text: str) -> dict:
    return {"content": text, "headers": {"content-type": "application/json"}}


def _csv(text: str | bytes) -> dict:
    return {"content": text, "headers": {"content-type": "text/csv"}}


TRAIN = "/api/train"
UPLOAD = "/api/strokes/upload"
MAX = LIMITS.max_body_bytes

# (id, path, request, status, reason); "{job}" is the trained job's id.
BAD_INPUT = [
    (
        "malformed JSON",
        TRAIN,
        _json('{"strokes": ['),
        400,
        "malformed JSON: Expecting value at line 1 column 14",
    ),
    (
        "NaN literal",
        TRAIN,
        _json('{"strokes": [[[NaN, 0, 0], [1, 1, 1]]]}'),
        400,
        "malformed JSON: NaN is not a JSON number",
    ),
    ("not an object", TRAIN, _json("[1, 2]"), 400, "expected a JSON object"),
    (
        "no strokes list",
        TRAIN,
        {"json": {"strokes": "abc"}},
        400,
        "'strokes' must be a list of strokes, each a list of [x, y, t] points",
    ),
    ("no strokes", TRAIN, {"json": {"strokes": []}}, 422, "no strokes: draw at least one"),
    (
        "too many strokes",
        TRAIN,
        {"json": {"strokes": [_stroke()] * 11}},
        422,
        "11 strokes, at most 10",
    ),
    (
        "too many points in a stroke",
        TRAIN,
        {"json": {"strokes": [_stroke(5001)]}},
        422,
        "stroke 0 has 5001 points, at most 5000",
    ),
    (
        "too many points in all",
        TRAIN,
        {"json": {"strokes": [_stroke(4001)] * 5}},
        422,
        "20005 points in all, at most 20000",
    ),
    (
        "one-point stroke",
        TRAIN,
        {"json": {"strokes": [_stroke(), _stroke(1)]}},
        422,
        "stroke 1 has 1 point; a stroke needs at least 2",
    ),
    (
        "null coordinate (NaN from JavaScript)",
        TRAIN,
        {"json": {"strokes": [[[0, 0, 0], [1, None, 0.1]]]}},
        400,
        "stroke 0, point 1: expected a number, got null",
    ),
    (
        "overflowing number",
        TRAIN,
        _json('{"strokes": [[[0, 0, 0], [1e400, 1, 0.1]]]}'),
        422,
        "the number 1e400 is beyond a float's range (1.8e308)",
    ),
    (
        "coordinate beyond the limit",
        TRAIN,
        {"json": {"strokes": [[[0, 0, 0], [2e6, 1, 0.1]]]}},
        422,
        "stroke 0, point 1: 2e+06 is beyond +-1e+06",
    ),
    (
        "point of two numbers",
        TRAIN,
        {"json": {"strokes": [[[0, 0], [1, 1]]]}},
        400,
        "stroke 0, point 0: expected [x, y, t], got a list",
    ),
    (
        "times that do not increase",
        TRAIN,
        {"json": {"strokes": [[[0, 0, 0], [1, 1, 0.1], [2, 2, 0.1]]]}},
        422,
        "stroke 0: times must increase strictly (point 2 at 0.1 s after 0.1 s)",
    ),
    (
        "strokes that never move",
        TRAIN,
        {"json": {"strokes": [[[3, 3, 0], [3, 3, 0.1]]]}},
        422,
        "the strokes: demonstrations have zero extent (every sample is at the target)",
    ),
    (
        "unknown method",
        TRAIN,
        {"json": {"strokes": [_stroke()], "method": "gmm"}},
        422,
        "unknown method 'gmm' (known: snds, bc)",
    ),
    (
        "unknown setting",
        TRAIN,
        {"json": {"strokes": [_stroke()], "settings": {"lr": 1}}},
        422,
        "unknown setting 'lr' (known: steps, seed, rollouts, samples)",
    ),
    (
        "a 400-digit setting",
        TRAIN,
        _json('{"strokes": [], "settings": {"steps": ' + "9" * 400 + "}}"),
        422,
        "a number of 400 characters (999999999999... (400 characters)); at most 32 are read",
    ),
    (
        "a coordinate of 309 digits (beyond a float)",
        TRAIN,
        _json('{"strokes": [[[0, 0, 0], [1' + "0" * 308 + ", 1, 1]]]}"),
        422,
        "a number of 309 characters (100000000000... (309 characters)); at most 32 are read",
    ),
    (
        "a coordinate of 5000 digits (beyond Python's int parsing)",
        TRAIN,
        _json('{"strokes": [[[0, 0, 0], [' + "7" * 5000 + ", 1, 1]]]}"),
        422,
        "a number of 5000 characters (777777777777... (5000 characters)); at most 32 are read",
    ),
    (
        "a target far from the strokes' ends",
        TRAIN,
        {"json": {"strokes": [_stroke()], "target": [999999, 999999]}},
        422,
        "stroke 0 ends 1.414e+06 from the target, 100% of the strokes' extent 1.414e+06; ends "
        "must lie within 25% of it (as for snds train): move the target (the star) to where the "
        "strokes end, or end the strokes at it",
    ),
    (
        "a rollout start of 400 digits",
        "/api/jobs/{job}/rollout",
        _json('{"start": [' + "1" * 400 + ", 0]}"),
        422,
        "a number of 400 characters (111111111111... (400 characters)); at most 32 are read",
    ),
    (
        "field bounds beyond a float",
        "/api/jobs/{job}/field",
        _json('{"bounds": [0, 1e400, 0, 1]}'),
        422,
        "the number 1e400 is beyond a float's range (1.8e308)",
    ),
    (
        "setting out of range",
        TRAIN,
        {"json": {"strokes": [_stroke()], "settings": {"steps": 0}}},
        422,
        "settings.steps: expected an integer in 1..100000, got 0",
    ),
    (
        "wrong content type",
        TRAIN,
        {"content": "{}", "headers": {"content-type": "text/plain"}},
        415,
        "expected Content-Type application/json, got text/plain",
    ),
    ("huge body", TRAIN, _json(" " * (MAX + 1)), 413, f"body of {MAX + 1} bytes, at most {MAX}"),
    (
        "huge body without a length",
        TRAIN,
        {
            "content": (b" " * 65536 for _ in range(MAX // 65536 + 1)),
            "headers": {"content-type": "application/json"},
        },
        413,
        f"body larger than {MAX} bytes",
    ),
    (
        "upload with a header typo",
        UPLOAD,
        _csv("dmeo,t,x1,x2\n0,0,1,1\n0,1,0,0\n"),
        422,
        "upload.csv: header column 1 is 'dmeo', expected 'demo' (demo,t,x1,...,xn[,v1,...,vn])",
    ),
    (
        "upload that is not text",
        UPLOAD,
        _csv(b"\xff\xfe\x00PK\x03\x04"),
        422,
        "upload.csv: not a UTF-8 CSV file: 'utf-8' codec can't decode byte 0xff in position 0: "
        "invalid start byte",
    ),
    (
        "upload in 3-D",
        UPLOAD,
        _csv("demo,t,x1,x2,x3\n0,0,1,1,1\n0,1,0,0,0\n"),
        422,
        "upload.csv: has 3-D positions; the page draws 2-D",
    ),
    (
        "upload of 11 demonstrations",
        UPLOAD,
        _csv("demo,t,x1,x2\n" + "".join(f"{d},0,1,1\n{d},1,0,0\n" for d in range(11))),
        422,
        "11 strokes, at most 10",
    ),
    (
        "upload with NaN",
        UPLOAD,
        _csv("demo,t,x1,x2\n0,0,nan,1\n0,1,0,0\n"),
        422,
        "upload.csv: line 2: non-finite value 'nan'",
    ),
    (
        "upload as JSON",
        UPLOAD,
        _json("{}"),
        415,
        "expected Content-Type text/csv, got application/json",
    ),
    (
        "unknown job",
        "/api/jobs/nope/field",
        {"json": {"bounds": [0, 1, 0, 1]}},
        404,
        "no job 'nope' on this server",
    ),
    (
        "preview that is not an object",
        TRAIN,
        {"json": {"strokes": [_stroke(4)], "preview": [0, 1, 0, 1]}},
        400,
        "'preview' must be {bounds: [x0, x1, y0, y1], size: [nx, ny]}",
    ),
    (
        "preview with empty bounds",
        TRAIN,
        {"json": {"strokes": [_stroke(4)], "preview": {"bounds": [1, 0, 0, 1]}}},
        422,
        "bounds: expected x0 < x1 and y0 < y1",
    ),
    (
        "field without bounds",
        "/api/jobs/{job}/field",
        {"json": {"size": [3, 3]}},
        400,
        "'bounds' must be [x0, x1, y0, y1]",
    ),
    (
        "field with empty bounds",
        "/api/jobs/{job}/field",
        {"json": {"bounds": [1, 0, 0, 1]}},
        422,
        "bounds: expected x0 < x1 and y0 < y1",
    ),
    (
        "field grid too fine",
        "/api/jobs/{job}/field",
        {"json": {"bounds": [0, 1, 0, 1], "size": [201, 3]}},
        422,
        "size: expected an integer in 2..200, got 201",
    ),
    (
        "rollout without a start",
        "/api/jobs/{job}/rollout",
        {"json": {}},
        400,
        "'start' must be [x, y]",
    ),
    (
        "rollout too long",
        "/api/jobs/{job}/rollout",
        {"json": {"start": [0, 1], "duration": 1000, "dt": 0.01}},
        422,
        "duration / dt = 100000 steps, at most 20000; take a longer dt",
    ),
    (
        "too many pushes",
        "/api/jobs/{job}/rollout",
        {"json": {"start": [0, 1], "pushes": [{"at": 0, "by": [1, 1]}] * 51}},
        422,
        "51 pushes, at most 50",
    ),
    (
        "malformed push",
        "/api/jobs/{job}/rollout",
        {"json": {"start": [0, 1], "pushes": [{"at": 0}]}},
        400,
        'push 0: expected {"at": s, "by": [dx, dy]}',
    ),
]


@pytest.mark.parametrize(
    ("path", "request_", "status", "reason"),
    [case[1:] for case in BAD_INPUT],
    ids=[case[0] for case in BAD_INPUT],
)
def test_bad_input(client, trained, path: str, request_: dict, status: int, reason: str) -> None:
    job, _, _ = trained
    running = {j.id for j in client.app.state.jobs.running()}
    answer = client.post(path.replace("{job}", job), **request_)
    assert (answer.status_code, answer.json()) == (status, {"error": reason})
    # Refused before any work: no job was started.
    assert {j.id for j in client.app.state.jobs.running()} == running


def _readme_example() -> tuple[str, str]:
    """The jq program and the request body template of the README's curl example."""
    readme = (Path(__file__).resolve().parents[2] / "README.md").read_text()
    program = re.search(r"strokes=\$\(jq -nc '(.*?)'\)", readme, re.DOTALL)
    body = re.search(r'-d "(\{\\"strokes\\": \$strokes.*?\})" \| jq', readme)
    assert program and body, "the README's curl example changed shape: update this test"
    return program.group(1), body.group(1).replace('\\"', '"')


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("jq") is None, reason="the README's example needs jq")
def test_the_readme_curl_example_trains_a_model_whose_check_passes(client, helpers) -> None:
    # GIVEN exactly the README's strokes (its jq program) and its request body
    program, template = _readme_example()
    strokes = subprocess.run(
        ["jq", "-nc", program], check=True, capture_output=True, text=True
    ).stdout.strip()
    body = template.replace("$strokes", strokes)
    # WHEN they are trained with the page's defaults (snds train's) and the README's settings
    answer = client.post("/api/train", content=body, headers={"content-type": "application/json"})
    assert answer.status_code == 202
    status = helpers.wait_for(client, answer.json()["id"], {"done", "error"}, timeout=600)
    # THEN the stability check passes: every start arrives, V decreases everywhere checked,
    # and the rollouts from the strokes' starts retrace them
    assert status["state"] == "done", status.get("error")
    metrics = status["metrics"]
    stability = metrics["stability"]
    assert stability["converged_fraction"] == 1.0 and stability["decrease_violations"] == 0
    assert stability["still_moving"] == 0 and stability["time_to_arrive_max"] < stability["horizon"]
    assert metrics["retrace_frechet_max"] <= 0.05


def test_the_favicon_is_served(client) -> None:
    answer = client.get("/favicon.ico")
    assert answer.status_code == 200 and answer.headers["content-type"] == "image/svg+xml"
    assert answer.text.startswith("<svg")
