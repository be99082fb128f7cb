"""The page end to end in a real headless browser: Debian's Chromium driven by Playwright.

It draws three strokes with the mouse, trains with tiny settings, waits for the field to be
drawn, starts a rollout with a click, pushes the moving point with synthetic pointer events
and waits for it to reach the target, then compares with BC. Screenshots go to a temporary
folder, or to ``$SNDS_SCREENSHOTS`` (``SNDS_SCREENSHOTS=docs pytest tests/app/test_browser.py``
makes the README's pictures).
"""

from __future__ import annotations

import os
import socket
import threading
import time
import zipfile
from pathlib import Path

import pytest

pytest.importorskip("starlette", reason="snds app needs the app extra (pip install 'snds[app]')")
uvicorn = pytest.importorskip("uvicorn", reason="snds app needs the app extra")
sync_api = pytest.importorskip(
    "playwright.sync_api", reason="the browser test needs Playwright (pip install playwright)"
)

from snds.app import create_app  # noqa: E402
from snds.app.headless import available, launch  # noqa: E402

#: The page's query: tiny training settings (``SNDS_APP_QUERY=""`` takes snds train's own
#: defaults, as for the README's pictures).
QUERY = os.environ.get("SNDS_APP_QUERY", "steps=300&rollouts=10&samples=200")

#: Whether the canvas is painted dark 3.5 px beside each stroke's first and middle point, across
#: the stroke: by its start dot there; not in the middle, between its arrowheads.
STROKE_ENDS = """() => {
  const canvas = document.getElementById("canvas");
  const ratio = canvas.width / canvas.getBoundingClientRect().width;
  const ctx = canvas.getContext("2d");
  const beside = (a, b) => {
    const [ax, ay] = sndsApp.toPixels(a), [bx, by] = sndsApp.toPixels(b);
    const length = Math.hypot(bx - ax, by - ay) || 1;
    const x = ax - 3.5 * (by - ay) / length, y = ay + 3.5 * (bx - ax) / length;
    const pixel = ctx.getImageData(Math.round(x * ratio), Math.round(y * ratio), 1, 1);
    const [r, g, bl, alpha] = pixel.data;
    return alpha > 128 && r + g + bl < 350;
  };
  return sndsApp.strokes.map((s) => {
    const gap = (j, k) => {
      const [a, b] = [sndsApp.toPixels(s[j]), sndsApp.toPixels(s[k])];
      return Math.hypot(a[0] - b[0], a[1] - b[1]);
    };
    const far = (k) => {
      let j = k;
      while (j + 1 < s.length && gap(j, k) < 12) j += 1;
      return j;
    };
    const mid = Math.floor(s.length / 2);
    return [beside(s[0], s[far(0)]), beside(s[mid], s[far(mid)])];
  });
}"""

pytestmark = pytest.mark.skipif(
    not available(),
    reason="no Chromium installed (apt-get install chromium): the page's browser test needs it",
)


@pytest.fixture(scope="module")
def url():
    sock = socket.create_server(("127.0.0.1", 0))
    server = uvicorn.Server(uvicorn.Config(create_app(), log_level="warning"))
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True)
    thread.start()
    deadline = time.monotonic() + 30
    while not server.started:
        assert time.monotonic() < deadline, "the server did not start"
        time.sleep(0.05)
    yield f"http://127.0.0.1:{sock.getsockname()[1]}"
    server.should_exit = True
    thread.join(timeout=15)


@pytest.fixture(scope="module")
def page(url):
    with sync_api.sync_playwright() as playwright:
        browser = launch(playwright)
        page = browser.new_page(viewport={"width": 1280, "height": 800})
        page.goto(f"{url}/?{QUERY}")
        yield page
        browser.close()


@pytest.fixture(scope="module")
def shots(tmp_path_factory) -> Path:
    folder = os.environ.get("SNDS_SCREENSHOTS")
    return Path(folder) if folder else tmp_path_factory.mktemp("screenshots")


def _screen(page, world: list[float]) -> tuple[float, float]:
    box = page.locator("#canvas").bounding_box()
    x, y = page.evaluate("p => sndsApp.toPixels(p)", world)
    return box["x"] + x, box["y"] + y


# Synthetic pointer events: press on the moving point, drag it by (dx, dy) pixels, release.
# Dispatched in one go in the page, so the point cannot move away between reading and pressing.
PUSH = """([dx, dy]) => {
  const canvas = document.getElementById("canvas");
  const rect = canvas.getBoundingClientRect();
  const [x, y] = sndsApp.toPixels(sndsApp.rollout.position);
  const at = (kind, s) => canvas.dispatchEvent(new PointerEvent(kind, {
    clientX: rect.left + x + s * dx, clientY: rect.top + y + s * dy,
    button: 0, pointerId: 7, pointerType: "pen", bubbles: true }));
  at("pointerdown", 0);
  for (let k = 1; k <= 10; k++) at("pointermove", k / 10);
  at("pointerup", 1);
}"""


def test_draw_train_push_and_compare_with_bc(page, shots: Path, helpers) -> None:
    # GIVEN three strokes drawn with the mouse
    for stroke in helpers.strokes(3, points=60):
        first = _screen(page, stroke[0][:2])
        page.mouse.move(*first)
        page.mouse.down()
        for point in stroke[1:]:
            page.mouse.move(*_screen(page, point[:2]))
        page.mouse.up()
    assert page.evaluate("sndsApp.strokes.length") == 3
    assert page.evaluate("sndsApp.strokes.every(s => s.length > 30)")
    # Each stroke shows its direction: a dot at its start (a dark pixel beside the line, where
    # the line alone leaves none, as in its middle).
    beside = page.evaluate(STROKE_ENDS)
    assert beside == [[True, False]] * 3, beside
    page.screenshot(path=str(shots / "app_strokes.png"))
    place = "(({x, y, width}) => ({x, y, width}))(document.querySelector('aside')"
    place += ".getBoundingClientRect())"
    panel = page.evaluate(place)
    rows = page.evaluate("[...document.querySelectorAll('#metrics tr')].map(r => r.offsetHeight)")
    button = page.locator("#undo").bounding_box()["height"]

    # WHEN the page trains on them
    page.click("#train")
    # THEN the Train button keeps its one line while training (no "Train again" wrap)
    assert page.locator("#train").bounding_box()["height"] == button
    page.wait_for_function("sndsApp.drawn.snds", timeout=120_000)
    page.wait_for_function("sndsApp.jobs.snds.status.state === 'done'", timeout=120_000)
    # THEN the field and V are drawn, with the stability check's numbers
    assert page.evaluate("sndsApp.jobs.snds.field.V !== null")
    check = page.evaluate("sndsApp.jobs.snds.status.metrics.stability")
    assert check["converged_fraction"] == 1.0 and check["decrease_violations"] == 0
    assert page.text_content("#snds-converged") == f"{check['rollouts']} of {check['rollouts']}"
    assert page.text_content("#snds-violations") == f"0 of {check['samples_checked']}"
    assert page.text_content("#snds-safe").endswith(" s")
    assert page.text_content("#snds-shortened").endswith(" %")
    assert page.text_content("#snds-arrival").endswith("×")
    # the safe step beside the data's step; the job's time split into training and check
    assert page.text_content("#data-step").startswith("data step ")
    label = page.text_content("#progress-label")
    assert (
        label.startswith("SNDS: done: ")
        and " s training + " in label
        and label.endswith(" s check")
    )
    # and the panel did not move nor re-wrap its table
    assert page.evaluate(place) == panel
    filled = page.evaluate("[...document.querySelectorAll('#metrics tr')].map(r => r.offsetHeight)")
    assert filled == rows

    # WHEN a click starts a rollout and the moving point is pushed away
    page.mouse.click(*_screen(page, [-85.0, 55.0]))
    page.wait_for_function("sndsApp.rollout && sndsApp.rollout.status === 'running'")
    time.sleep(0.3)
    page.evaluate(PUSH, [-70, 60])
    # THEN it recovers and reaches the target
    page.wait_for_function("sndsApp.rollout.status === 'arrived'", timeout=60_000)
    rollout = page.evaluate(
        "({pieces: sndsApp.rollout.trail.length, pushed: sndsApp.rollout.trail[1].push,"
        " distance: sndsApp.rollout.finalDistance, tolerance: sndsApp.rollout.tolerance})"
    )
    assert rollout["pieces"] == 3 and rollout["pushed"] is True
    assert rollout["distance"] <= rollout["tolerance"]
    assert page.text_content("#status").startswith("Reached the target after a push")
    page.screenshot(path=str(shots / "app_trained.png"))

    # WHEN behavioural cloning is trained on the same strokes (the toggle)
    page.click("#bc")
    # THEN while BC trains, SNDS's field stays on the board and Run still works on it
    page.wait_for_function("sndsApp.jobs.bc && sndsApp.jobs.bc.status.state === 'training'")
    assert page.evaluate("!!sndsApp.jobs.snds.layer && !sndsApp.drawn.bc")
    assert not page.locator("#mode-run").is_disabled()
    assert page.text_content("#progress-label").startswith("BC: ")
    page.screenshot(path=str(shots / "app_bc_training.png"))
    page.wait_for_function("sndsApp.drawn.bc", timeout=120_000)
    page.wait_for_function("sndsApp.jobs.bc.status.state === 'done'", timeout=120_000)
    # THEN its field has no V, and its check is shown beside SNDS's
    assert page.evaluate("sndsApp.jobs.bc.field.V === null")
    assert page.text_content("#bc-violations") == "no V"
    assert page.text_content("#bc-converged").endswith(f" of {check['rollouts']}")
    assert page.evaluate(place) == panel
    filled = page.evaluate("[...document.querySelectorAll('#metrics tr')].map(r => r.offsetHeight)")
    assert filled == rows
    page.mouse.click(*_screen(page, [-85.0, 55.0]))
    page.wait_for_function("sndsApp.rollout && sndsApp.rollout.status === 'running'")
    time.sleep(1.5)
    page.screenshot(path=str(shots / "app_bc.png"))

    # WHEN BC is toggled off: SNDS's field and SNDS's own progress label are back
    page.click("#bc")
    assert page.text_content("#progress-label").startswith("SNDS: done: ")
    assert page.evaluate("sndsApp.showBC") is False
    # AND at 800 px wide, the panels sit side by side below the board, at its full width
    page.set_viewport_size({"width": 800, "height": 800})
    page.evaluate("window.dispatchEvent(new Event('resize'))")
    board, aside = page.locator("#board").bounding_box(), page.locator("aside").bounding_box()
    assert aside["y"] >= board["y"] + board["height"] and aside["width"] >= 0.9 * board["width"]
    tops = page.evaluate("[...document.querySelectorAll('aside section')].map(s => s.offsetTop)")
    assert tops[0] == tops[1]
    page.screenshot(path=str(shots / "app_trained_800.png"), full_page=True)
    page.click("#bc")  # BC is trained: shown at once
    assert page.text_content("#progress-label").startswith("BC: done: ")
    page.screenshot(path=str(shots / "app_bc_800.png"), full_page=True)
    page.set_viewport_size({"width": 1280, "height": 800})

    # AND the page's downloads: the model folder, its ONNX file, the strokes' CSV
    with page.expect_download(timeout=120_000) as download:
        page.click("#dl-model")
    with zipfile.ZipFile(download.value.path()) as archive:
        names = {Path(name).name for name in archive.namelist()}
    assert names == {"model.json", "model.safetensors", "metrics.json", "loss.json", "strokes.csv"}
    with page.expect_download(timeout=120_000) as download:
        page.click("#dl-onnx")
    assert Path(download.value.path()).stat().st_size > 10_000
    assert page.text_content("#status") == "Downloaded snds-bc-policy.onnx."
    with page.expect_download(timeout=120_000) as download:
        page.click("#dl-strokes")
    strokes_csv = Path(download.value.path())
    rows = strokes_csv.read_text().splitlines()
    assert rows[0] == "demo,t,x1,x2" and {row.split(",")[0] for row in rows[1:]} == {"0", "1", "2"}

    # AND in draw mode: undo, the target dragged (which makes the models stale), clear
    page.click("#mode-draw")
    page.click("#undo")
    assert page.evaluate("sndsApp.strokes.length") == 2
    goal = page.evaluate("sndsApp.strokes[0][sndsApp.strokes[0].length - 1].slice(0, 2)")
    x, y = _screen(page, goal)
    page.mouse.move(x, y)
    page.mouse.down()
    page.mouse.move(x + 30, y - 20, steps=5)
    page.mouse.up()
    moved = page.evaluate("sndsApp.target")
    assert moved != goal and page.evaluate("sndsApp.jobs.snds") is None
    page.click("#clear")
    assert page.evaluate("sndsApp.strokes.length") == 0
    # AND the downloaded strokes open again, as they were trained on
    page.set_input_files("#upload", str(strokes_csv))
    page.wait_for_function("sndsApp.strokes.length === 3")
    assert page.evaluate("sndsApp.target") == [float(v) for v in rows[-1].split(",")[2:]]


def test_a_stroke_added_after_training_refines_and_undo_reverts(page, shots: Path, helpers):
    # GIVEN a trained policy on three strokes, in draw mode
    page.click("#train")
    page.wait_for_function(
        "sndsApp.jobs.snds && sndsApp.jobs.snds.status.state === 'done'", timeout=120_000
    )
    before = page.evaluate("sndsApp.jobs.snds.id")
    page.click("#mode-draw")
    # WHEN a fourth stroke is drawn
    stroke = helpers.strokes(4, points=60)[3]
    page.mouse.move(*_screen(page, stroke[0][:2]))
    page.mouse.down()
    for point in stroke[1:]:
        page.mouse.move(*_screen(page, point[:2]))
    page.mouse.up()
    # THEN the page shows that it refines, with the policy before still on the board
    assert page.evaluate("document.body.dataset.state") == "refining"
    assert page.evaluate("sndsApp.refining !== null && sndsApp.jobs.snds.id") == before
    assert page.text_content("#progress-label").startswith("SNDS: refining")
    page.screenshot(path=str(shots / "app_refining.png"))
    # and the refined field replaces it, from a new job refining the one before
    page.wait_for_function(
        "sndsApp.timings.refine && sndsApp.timings.refine.drawn", timeout=120_000
    )
    refined = page.evaluate("sndsApp.jobs.snds.id")
    assert refined != before and page.evaluate("sndsApp.jobs.snds.refines.id") == before
    assert page.evaluate("sndsApp.jobs.snds.result.demos.length") == 4
    seconds = page.evaluate("(sndsApp.timings.refine.drawn - sndsApp.timings.refine.added) / 1e3")
    assert 0 < seconds < 60
    page.wait_for_function("sndsApp.jobs.snds.status.state === 'done'", timeout=120_000)
    check = page.evaluate("sndsApp.jobs.snds.status.metrics.stability")
    assert check["converged_fraction"] == 1.0 and check["decrease_violations"] == 0
    assert page.text_content("#progress-label").startswith("SNDS refined: ")
    page.screenshot(path=str(shots / "app_refined.png"))
    # WHEN undo is clicked THEN the stroke goes and the policy before is back on the board
    page.click("#undo")
    assert page.evaluate("sndsApp.strokes.length") == 3
    assert page.evaluate("sndsApp.jobs.snds.id") == before
    assert page.evaluate("!!sndsApp.jobs.snds.layer && sndsApp.refining === null")
    assert page.text_content("#status").startswith("Undone")


def test_the_field_is_previewed_while_training(page, shots: Path) -> None:
    # GIVEN the strokes on the board and a training far longer than a second
    steps = page.evaluate("sndsApp.settings.steps")
    page.evaluate("sndsApp.settings.steps = 100000")
    try:
        page.click("#train")
        # THEN the field of the policy being trained is drawn before its model is saved
        page.wait_for_function(
            "sndsApp.jobs.snds && !!sndsApp.jobs.snds.previewLayer", timeout=120_000
        )
        assert page.evaluate("sndsApp.jobs.snds.status.state") == "training"
        assert page.evaluate("sndsApp.jobs.snds.preview.step") > 0
        assert page.evaluate("sndsApp.jobs.snds.preview.V !== null")
        # and it is shown, not rolled out: Run waits for the saved model
        assert page.evaluate("!sndsApp.jobs.snds.layer && !sndsApp.jobs.snds.result")
        assert page.evaluate("document.getElementById('mode-run').disabled")
        # and the check's numbers of the policy before are gone until the new ones come
        assert page.text_content("#snds-converged") == "–"
        assert page.text_content("#warnings") == ""
        page.screenshot(path=str(shots / "app_preview.png"))
    finally:
        # The long job is replaced by one of the module's usual length.
        page.evaluate(f"sndsApp.settings.steps = {steps}")
        page.click("#train")
        page.wait_for_function(
            "sndsApp.jobs.snds && sndsApp.jobs.snds.status.state === 'done'", timeout=120_000
        )
