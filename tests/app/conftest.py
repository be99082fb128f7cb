"""Fixtures of the page's server: one server per module and one tiny trained job."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest

#: Training and check sizes that keep a job to a few seconds (the page's defaults are
#: snds train's; these only shrink the work).
TINY = {"steps": 30, "rollouts": 20, "samples": 500}


def spiral_strokes(count: int = 3, points: int = 80) -> list[list[list[float]]]:
    """Strokes as a hand draws them: inward spirals from different sides, ending near (5, -3),
    sampled at 60 Hz, as [x, y, t]."""
    strokes = []
    for k in range(count):
        s = np.linspace(0.0, 1.0, points)
        angle = 2.1 * k + 3.0 * s
        radius = (70.0 - 8 * k) * (1 - s) ** 1.3
        x = 5.0 + radius * np.cos(angle) + 0.4 * k * s
        y = -3.0 + radius * np.sin(angle)
        t = np.arange(points) / 60.0
        strokes.append(np.column_stack([x, y, t]).tolist())
    return strokes


def wait_for(client, job: str, states: set[str], timeout: float = 120.0) -> dict:
    """Polls a job until it is in one of ``states``."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        status = client.get(f"/api/jobs/{job}").json()
        if status["state"] in states:
            return status
        time.sleep(0.05)
    raise AssertionError(f"job {job} never reached {states}: {status}")


def read_events(client, job: str) -> list[dict]:
    """Every event of a job's stream, until it ends."""
    events = []
    with client.stream("GET", f"/api/jobs/{job}/events") as response:
        assert response.headers["content-type"].startswith("text/event-stream")
        for line in response.iter_lines():
            if line.startswith("data: "):
                events.append(json.loads(line[len("data: ") :]))
    return events


@pytest.fixture(scope="module")
def client():
    # Imported here: without the app extra the tests that need it skip, the rest still run.
    testclient = pytest.importorskip(
        "starlette.testclient", reason="snds app needs the app extra (pip install 'snds[app]')"
    )
    from snds.app import create_app

    with testclient.TestClient(create_app(), base_url="http://127.0.0.1") as test_client:
        yield test_client


@pytest.fixture(scope="module")
def trained(client):
    """A finished tiny SNDS job on three strokes: (job id, request body, its events)."""
    body = {"strokes": spiral_strokes(), "settings": TINY}
    answer = client.post("/api/train", json=body)
    assert answer.status_code == 202, answer.text
    job = answer.json()["id"]
    events = read_events(client, job)
    assert events[-1]["state"] == "done", events[-1]
    return job, body, events


@pytest.fixture(scope="session")
def helpers():
    """The module's helpers, for the tests (a conftest is not importable by name here)."""

    class Helpers:
        tiny = TINY
        strokes = staticmethod(spiral_strokes)
        wait_for = staticmethod(wait_for)
        read_events = staticmethod(read_events)

    return Helpers
