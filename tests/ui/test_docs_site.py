"""The documentation site in the browser, served by the service at /guide: the diagrams draw,
the search finds, nothing is fetched from elsewhere and the page's security policy holds."""

from __future__ import annotations

import pytest
from playwright.sync_api import expect

from tests.docs_site import build_site
from tests.server_process import Server
from tests.ui.conftest import TOKEN, pendant_for

pytestmark = pytest.mark.timeout(300)


@pytest.fixture(scope="module")
def guide_server(tmp_path_factory):
    site = build_site(tmp_path_factory.mktemp("site"))
    server = Server(
        tmp_path_factory.mktemp("guide-data"),
        token=TOKEN,
        timeout_s=30,
        settings={"TEACHPATH_GUIDE_DIR": str(site)},
    )
    yield server
    server.stop()


def test_the_architecture_page_draws_its_diagrams_and_the_search_finds(
    browser, guide_server, screens
):
    with pendant_for(browser, guide_server, screens, "guide") as reader:
        page = reader.page
        page.goto(guide_server.url + "/guide/architecture.html")
        expect(page.get_by_role("heading", name="Module map")).to_be_visible()
        # Both diagrams drawn by the local mermaid script: the theme swaps each source block for
        # a div holding the drawing in a closed shadow root (the guard fails the test if the
        # theme fell back to fetching mermaid from a CDN).
        drawn = page.locator("div.mermaid")
        expect(drawn).to_have_count(2, timeout=30_000)
        expect(page.locator("pre.mermaid")).to_have_count(0)
        for i in range(2):
            box = drawn.nth(i).bounding_box()
            assert box is not None and box["height"] > 200 and box["width"] > 300, box
        drawn.first.scroll_into_view_if_needed()
        reader.shot("architecture")
        # The search index is the site's own: a word of the operator's guide is found.
        # Typed as a reader types; the index is built in a worker after the page loads, so the
        # query is typed again until the results come (up to half a minute on a busy machine).
        search = page.locator("input.md-search__input")
        search.click()
        results = page.locator(".md-search-result__item")
        for _ in range(30):
            search.fill("")
            search.press_sequentially("protective", delay=20)
            page.wait_for_timeout(1000)
            if results.count():
                break
        expect(results.first).to_be_visible()
        expect(page.locator(".md-search-result")).to_contain_text("matching documents")
        reader.shot("search")
