"""The modeling page in headless chromium: start, add suggestions, auto-complete, undo, download.

Runs against the real service (uvicorn in a thread) on the shipped artifacts; the downloaded
file must parse with trimesh and hold one mesh per placed part; the console must stay free of
errors. A screenshot is saved under test-artifacts/ (gitignored).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
import trimesh

IDLE = "document.getElementById('status').dataset.busy === 'false'"
PARTS = "[data-testid=placed-part]"
CARDS = "[data-testid=suggestion-card]"


def _parts(page: Any) -> int:
    return int(page.locator(PARTS).count())


def _wait_parts(page: Any, n: int) -> None:
    page.wait_for_function(f"document.querySelectorAll('{PARTS}').length === {n}")
    page.wait_for_function(IDLE)


@pytest.fixture()
def page(browser: Any, server: str) -> Any:
    context = browser.new_context(viewport={"width": 1400, "height": 900}, accept_downloads=True)
    pg = context.new_page()
    pg.set_default_timeout(60_000)
    problems: list[str] = []
    pg.on("console", lambda m: problems.append(f"console {m.type}: {m.text}") if m.type == "error" else None)
    pg.on("pageerror", lambda e: problems.append(f"page error: {e}"))
    pg.problems = problems
    pg.goto(server + "/")
    yield pg
    context.close()


def test_page_served_with_its_bundle(server: str) -> None:
    import httpx

    page = httpx.get(server + "/")
    assert page.status_code == 200 and "text/html" in page.headers["content-type"]
    assert 'src="/static/app.js"' in page.text
    bundle = httpx.get(server + "/static/app.js")
    assert bundle.status_code == 200 and "javascript" in bundle.headers["content-type"]
    assert len(bundle.content) > 100_000  # three.js is bundled in: nothing is fetched from the internet


def test_model_a_shape(page: Any, artifact_dir: Path) -> None:
    page.wait_for_selector("#start-part-select option", state="attached")
    categories = page.eval_on_selector_all("#category-select option", "os => os.map(o => o.value)")
    if "chair" in categories:
        page.select_option("#category-select", "chair")
        page.wait_for_function(IDLE)
    page.wait_for_selector("#start-part-select option", state="attached")
    page.click("#start-button")
    page.wait_for_selector(CARDS)
    _wait_parts(page, 1)

    # Two suggestions added by clicking; the service places them.
    for n in (2, 3):
        card = page.locator(CARDS).first
        part_id = card.get_attribute("data-part-id")
        with page.expect_response(lambda r: r.url.endswith("/suggest")) as answer:
            card.click()
            _wait_parts(page, n)
        assert answer.value.status == 200, answer.value.text()
        added = page.locator(PARTS).nth(n - 1).get_attribute("data-part-id")
        assert added == part_id, (added, part_id, page.problems)
    # The gallery is grouped by mode.
    assert page.locator("[data-testid=mode-group]").count() >= 1

    # Undo and redo.
    page.click("#undo-button")
    _wait_parts(page, 2)
    page.click("#redo-button")
    _wait_parts(page, 3)

    # Alternatives: a tree of possibilities, one button per node; a click applies that branch.
    with page.expect_response(lambda r: r.url.endswith("/assemble")) as answer:
        page.click("#alternatives-button")
    assert answer.value.status == 200, answer.value.text()
    page.wait_for_function(IDLE)
    nodes = answer.value.json()["nodes"]
    assert page.locator("[data-testid=tree-node]").count() == len(nodes)
    parts = 3
    if nodes:
        deepest = max(nodes, key=lambda n: n["depth"])
        page.click(f"[data-testid=tree-node][data-node='{deepest['node']}']")
        parts += deepest["depth"]
        _wait_parts(page, parts)

    # Auto-complete: the service's /assemble steps are appended.
    with page.expect_response(lambda r: r.url.endswith("/assemble")) as answer:
        page.click("#autocomplete-button")
    assert answer.value.status == 200, answer.value.text()
    added = len(answer.value.json()["steps"])
    _wait_parts(page, parts + added)
    total = _parts(page)

    # Download the model and parse it.
    with page.expect_download() as download:
        page.click("#download-button")
    path = download.value.path()
    scene = trimesh.load_scene(path, file_type="glb")
    # One node per placed part (a part added twice at one spot may share its mesh data).
    assert len(scene.graph.nodes_geometry) == total, (len(scene.graph.nodes_geometry), total)
    assert np.all(np.isfinite(scene.bounds))

    page.wait_for_function(IDLE)
    page.screenshot(path=str(artifact_dir / "page.png"))
    assert not page.problems, page.problems


def test_start_from_an_uploaded_mesh(page: Any, tmp_path: Path) -> None:
    """An uploaded mesh is the start: suggestions come for it, a click adds a part, undo removes it."""
    seat = trimesh.creation.box((0.8, 0.06, 0.8))
    path = tmp_path / "seat.obj"
    path.write_text(seat.export(file_type="obj"))
    page.wait_for_selector("#start-part-select option", state="attached")
    page.wait_for_function(IDLE)
    with page.expect_response(lambda r: r.url.endswith("/suggest")) as answer:
        page.set_input_files("#mesh-upload", str(path))
    assert answer.value.status == 200
    page.wait_for_selector(CARDS)
    page.wait_for_function(IDLE)
    assert _parts(page) == 0
    assert "uploaded mesh" in page.inner_text("#status")
    page.locator(CARDS).first.click()
    _wait_parts(page, 1)
    page.click("#undo-button")
    _wait_parts(page, 0)
    assert not page.problems, page.problems
