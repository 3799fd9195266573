"""``/docs`` (Swagger UI) and ``/redoc`` render every operation in headless chromium with no internet.

Every request the page makes to anything but the service's own loopback address is aborted
(``context.route``), so a script, style or font loaded from a CDN would leave the page blank;
the aborted requests are listed in the failure message. Screenshots go to test-artifacts/.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import httpx
import pytest

REDOC_LOGO = "https://cdn.redoc.ly/redoc/logo-mini.svg"


def _operations(server: str) -> int:
    schema = httpx.get(server + "/openapi.json", timeout=30).json()
    return sum(1 for ops in schema["paths"].values() for method in ops
               if method in {"get", "post", "put", "patch", "delete"})


@pytest.fixture()
def offline_page(browser: Any, server: str) -> Any:
    """A page whose requests reach only the service; the ones that tried to leave are kept."""
    own = urlsplit(server).netloc
    context = browser.new_context(viewport={"width": 1400, "height": 900})
    blocked: list[str] = []

    def only_the_service(route: Any) -> None:
        url = route.request.url
        if urlsplit(url).netloc == own or url.startswith(("data:", "blob:")):
            route.continue_()
        else:
            blocked.append(url)
            route.abort("internetdisconnected")

    context.route("**/*", only_the_service)
    page = context.new_page()
    page.set_default_timeout(60_000)
    errors: list[str] = []
    page.on("pageerror", lambda e: errors.append(str(e)))
    page.blocked = blocked
    page.errors = errors
    yield page
    context.close()


def test_swagger_ui_renders_offline(offline_page: Any, server: str, artifact_dir: Path) -> None:
    expected = _operations(server)
    offline_page.goto(server + "/docs")
    offline_page.wait_for_function(
        f"document.querySelectorAll('#swagger-ui .opblock').length === {expected}")
    first = offline_page.locator("#swagger-ui .opblock-summary-path").first.inner_text()
    assert first.startswith("/"), first
    offline_page.screenshot(path=str(artifact_dir / "docs-offline.png"))
    assert not offline_page.blocked, offline_page.blocked
    assert not offline_page.errors, offline_page.errors


def test_redoc_renders_offline(offline_page: Any, server: str, artifact_dir: Path) -> None:
    expected = _operations(server)
    offline_page.goto(server + "/redoc")
    # ReDoc marks each operation (in the menu and in the content) with a data-section-id that
    # starts with "operation/"; the distinct ids are the operations rendered.
    offline_page.wait_for_function(
        "new Set(Array.from(document.querySelectorAll('[data-section-id^=\"operation/\"]'))"
        ".map(e => e.dataset.sectionId)).size === " + str(expected))
    offline_page.wait_for_selector("h2 >> text=/suggest/i")
    offline_page.screenshot(path=str(artifact_dir / "redoc-offline.png"))
    # The one thing ReDoc's bundle still asks the internet for is the "API docs by Redocly" logo
    # in its footer; with it blocked only that image is missing.
    assert all(url == REDOC_LOGO for url in offline_page.blocked), offline_page.blocked
    assert not offline_page.errors, offline_page.errors
