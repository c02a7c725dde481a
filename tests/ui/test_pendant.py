"""The teach pendant driven as an operator would, in Debian's chromium (see conftest.py)."""

from __future__ import annotations

from playwright.sync_api import expect

from tests.ui.conftest import TOKEN


def test_token_leaves_the_url_and_the_safety_bar_shows_the_sim_arm(pendant):
    page = pendant.page
    pendant.open()
    assert "token" not in page.url
    assert page.evaluate("sessionStorage.getItem('teachpath.token')") == TOKEN
    bar = page.locator("#safety-bar")
    expect(page.locator("#arm-kind")).to_have_text("SIM")
    expect(page.locator("#robot-model")).to_have_text("ur5e")
    expect(page.locator("#robot-mode")).to_have_text("SIMULATED")
    expect(page.locator("#safety-status")).to_have_text("NORMAL")
    expect(page.locator("#protective-stop")).to_have_text("no")
    expect(page.locator("#remote-control")).to_have_text("on")
    expect(page.locator("#arm-owner")).to_have_text("none")
    expect(page.locator("#speed-cap")).to_have_text("250 mm/s")
    expect(page.locator("#link-state")).to_have_text("live")
    expect(bar).to_be_visible()
    # Nothing moves: no Stop button.
    expect(page.get_by_role("button", name="Stop")).to_be_hidden()
    pendant.shot("safety-bar")
