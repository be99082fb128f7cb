"""POST /api/jobs/{id}/refine: a stroke added after training refines the job's policy
(snds train --init) as a new job; the job before stays."""

from __future__ import annotations

import json

import pytest

from snds.refine import RefineConfig

pytest.importorskip("starlette", reason="snds app needs the app extra (pip install 'snds[app]')")


def test_a_stroke_added_after_training_refines_the_policy(client, trained, helpers):
    read_events, spiral_strokes = helpers.read_events, helpers.strokes
    job, body, _ = trained
    # GIVEN the trained job's strokes and target, then a fourth stroke
    strokes = body["strokes"] + spiral_strokes(4)[3:]
    target = client.get(f"/api/jobs/{job}").json()["result"]["target"]
    # WHEN it is refined with them
    answer = client.post(f"/api/jobs/{job}/refine", json={"strokes": strokes, "target": target})
    assert answer.status_code == 202, answer.text
    refined = answer.json()["id"]
    events = read_events(client, refined)
    # THEN a new job refines the policy in the refinement's steps, then checks it
    assert events[-1]["state"] == "done", events[-1]
    assert max(e["step"] for e in events) == RefineConfig().steps
    status = client.get(f"/api/jobs/{refined}").json()
    assert len(status["result"]["demos"]) == 4
    stability = status["metrics"]["stability"]
    assert stability["converged_fraction"] == 1.0 and stability["decrease_violations"] == 0
    # from the job's model, which stays on the server for undo
    assert client.get(f"/api/jobs/{job}").json()["state"] == "done"
    record = json.loads((client.app.state.jobs.get(refined).model / "model.json").read_text())
    assert record["refined_from"]["model"].endswith(f"{job}/model")
    assert record["train_result"]["steps"] == RefineConfig().steps


def test_a_refinement_must_add_to_the_jobs_own_strokes(client, trained, helpers):
    job, body, _ = trained
    other = helpers.strokes(4)
    answer = client.post(f"/api/jobs/{job}/refine", json={"strokes": other[1:]})
    assert answer.status_code == 409
    assert "was trained on other strokes" in answer.json()["error"]
    same = client.post(f"/api/jobs/{job}/refine", json={"strokes": body["strokes"]})
    assert same.status_code == 409
    assert client.post("/api/jobs/0123/refine", json={"strokes": other}).status_code == 404
