"""End to end in a real browser: headless Chromium (Debian's /usr/bin/chromium, driven by
Playwright) opens ``thgs view`` on the small synthetic field, types a query, clicks the scene and
climbs the hierarchy. The server's state and the pixels of the page must both change.

Screenshots are kept in ``test-artifacts/viewer/`` (or ``$THGS_TEST_ARTIFACTS/viewer``).
scripts/setup.sh installs Chromium where it can (root or sudo with apt); elsewhere the test is
skipped, saying why.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np
import pytest

from conftest import REPO
from thgs.query import QueryConfig
from thgs.viewer.app import start_viewer, viewer_url
from thgs.viewer.splats import pack_rgba

CHROMIUM = Path(os.environ.get("THGS_CHROMIUM", "/usr/bin/chromium"))
CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--disable-quic",
]


def _artifacts() -> Path:
    folder = Path(os.environ.get("THGS_TEST_ARTIFACTS", REPO / "test-artifacts")) / "viewer"
    folder.mkdir(parents=True, exist_ok=True)
    return folder


@pytest.fixture(scope="module")
def browser(tmp_path_factory):
    if not CHROMIUM.is_file():
        pytest.skip(f"Chromium is not installed at {CHROMIUM} (apt install chromium)")
    playwright_api = pytest.importorskip(
        "playwright.sync_api", reason="Playwright is not installed (pip install playwright)"
    )
    profile = tmp_path_factory.mktemp("chromium-profile")
    with playwright_api.sync_playwright() as playwright:
        context = playwright.chromium.launch_persistent_context(
            str(profile),
            executable_path=str(CHROMIUM),
            args=CHROMIUM_ARGS,
            headless=True,
            viewport={"width": 1200, "height": 800},
        )
        yield context
        context.close()


def _input(page, label: str):
    """The input next to a viser GUI label (viser's labels are not tied to their inputs)."""
    return page.locator(
        f"xpath=//label[normalize-space()='{label}']"
        "/ancestor::div[contains(@class, 'mantine-Flex-root')][1]//input"
    )


def _canvas(page, path: Path) -> np.ndarray:
    from PIL import Image

    page.screenshot(path=str(path))
    return np.asarray(Image.open(path).convert("RGB"), dtype=np.int16)[:, :800]


def _settled(page, path: Path, *, differs_from: np.ndarray | None = None) -> np.ndarray:
    """The canvas once the picture stops changing (two screenshots 200 ms apart agree) and, with
    ``differs_from``, has changed from that picture at all; the last one after 15 s."""
    previous = None
    for _ in range(75):
        current = _canvas(page, path)
        changed = differs_from is None or not np.array_equal(current, differs_from)
        if previous is not None and changed and np.array_equal(current, previous):
            return current
        previous = current
        page.wait_for_timeout(200)
    return current


@pytest.mark.slow
@pytest.mark.browser
def test_query_click_and_climb_in_headless_chromium(browser, small_field):
    app = start_viewer(small_field, host="127.0.0.1", port=0)
    artifacts = _artifacts()
    try:
        state = app.state
        page = browser.new_page()
        page.goto(viewer_url(app, "127.0.0.1"))
        page.get_by_text("4,000 Gaussians").wait_for(timeout=60_000)
        before = _settled(page, artifacts / "1-opened.png")  # the splats arrive and are sorted

        _input(page, "Query").fill("teddy bear")
        page.get_by_role("button", name="Search").click()
        page.get_by_text("teddy bear:").wait_for(timeout=30_000)
        expected = state.query.select(["teddy bear"], QueryConfig(mode="level", level=3))[0]
        assert state.highlight.kind == "query" and state.highlight.regions == expected.regions
        np.testing.assert_array_equal(state.highlight.gaussians, expected.gaussians)
        np.testing.assert_array_equal(app.splats.rgba(), pack_rgba(*state.colors()))
        queried = _settled(page, artifacts / "2-query-teddy-bear.png", differs_from=before)
        # everything but the bear is dimmed: the picture darkens and changes over a large area
        changed = np.abs(queried - before).sum(axis=2) > 30
        assert changed.mean() > 0.05, f"only {changed.mean():.1%} of the scene's pixels changed"

        page.mouse.click(400, 400)  # the middle of the scene, left of the panel
        for _ in range(100):
            if state.highlight.kind == "pick":
                break
            page.wait_for_timeout(100)
        assert state.highlight.kind == "pick" and state.highlight.anchor is not None
        level, region = state.highlight.primary
        assert level == 3 and state.field.labels[state.highlight.anchor, 3] == region
        page.get_by_text(f"object {region}").first.wait_for(timeout=10_000)

        page.get_by_role("combobox", name="Level").click()
        page.get_by_role("option", name="1 sub-part").click()
        page.get_by_text("Selected: subpart").wait_for(timeout=10_000)
        sub_part = state.field.labels[state.highlight.anchor, 1]
        assert state.highlight.primary == (1, sub_part)
        page.get_by_role("button", name="Parent").click()
        page.get_by_text("Selected: part").wait_for(timeout=10_000)
        assert state.highlight.primary == (2, state.field.parent(1, sub_part))
        _settled(page, artifacts / "3-picked-part.png")
        page.close()
    finally:
        app.stop()
    assert shutil.disk_usage(artifacts).free > 0
