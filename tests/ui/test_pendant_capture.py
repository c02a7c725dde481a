"""Live capture on the pendant, in a real browser: a NatNet feed (our replay server on
loopback, with the pen out of view for a while) drawn while it runs, the loss shown, a reload
that follows the running capture again without sending anything, and Stop keeping the samples
as the session's recording."""

from __future__ import annotations

import re

import numpy as np
from playwright.sync_api import expect

from drivers.tracking.natnet_server import NatNetReplayServer
from tests.drivers.test_natnet import RATE_HZ, synthetic
from tests.ui.test_pendant import canvas_pixels


def test_a_live_capture_is_drawn_while_tracing_and_kept_on_stop(pendant):
    page = pendant.page
    recording = synthetic(12.0)
    lost = np.zeros(len(recording), dtype=bool)
    lost[int(1.0 * RATE_HZ) : int(1.5 * RATE_HZ)] = True  # the pen out of view for 0.5 s
    posts = []
    page.on("request", lambda r: posts.append(r.url) if r.method == "POST" else None)
    with NatNetReplayServer(recording, rigid_body="Pen", command_port=0, valid=~lost) as server:
        pendant.open()
        pendant.create_session("live capture")
        expect(page.locator("#session-title")).to_have_text("Session live capture")
        form = page.locator("#capture-form")
        expect(form.get_by_label("Source")).to_have_value("natnet")
        form.get_by_label("Command port").fill(str(server.command_port))
        form.get_by_role("button", name="Start capture").click()
        stop = form.get_by_role("button", name="Stop capture")
        expect(stop).to_be_visible()
        expect(form.get_by_role("button", name="Start capture")).to_be_disabled()

        # Drawn while it runs: more samples each look, over an otherwise empty view.
        expect(page.locator("#capture-status")).to_contain_text("samples received", timeout=20_000)
        # The whole stretch, where it happened, once the pen is back in view.
        whole_loss = "tracking lost 1× (180 samples; first 1.00 s into the capture)"
        expect(page.locator("#capture-status")).to_contain_text(whole_loss, timeout=20_000)
        expect(page.locator("#capture-status")).not_to_contain_text("LOST NOW")
        # The live layer holds every sample received that was tracked, and grows.
        # (Read in one go: samples keep arriving between two reads.)
        both = (
            "() => [document.querySelector('#capture-status').textContent,"
            " document.querySelector('#workspace').workspace.layers.live.geometry.drawRange.count]"
        )

        def received_and_drawn() -> tuple[int, int]:
            text, drawn = page.evaluate(both)
            return int(re.match(r"(\d+) samples received", text).group(1)), drawn

        first, drawn = received_and_drawn()
        assert drawn == first - 180  # the 180 lost samples are not drawn
        page.wait_for_timeout(700)
        later, drawn_later = received_and_drawn()
        assert later > first and drawn_later == later - 180
        assert canvas_pixels(page)["drawn"] > 0.0005
        pendant.shot("capturing")

        # A reload finds the running capture again and follows it from its first sample.
        page.reload()
        page.wait_for_selector("body[data-ready=true]")
        expect(stop).to_be_visible()
        expect(page.locator("#capture-status")).to_contain_text(whole_loss, timeout=20_000)
        assert sum("/captures" in url for url in posts) == 1, posts
        page.wait_for_timeout(500)
        stop.click()
        message = form.locator(".message")
        expect(message).to_contain_text(
            re.compile(
                r"Capture stopped: \d+ samples received; "
                r"recording rec_\w+ keeps \d+ \(piece 2 of 2"
            )
        )
        expect(message).to_contain_text("tracker lost the pen for 0.50")
        expect(stop).to_be_hidden()
        expect(form.get_by_role("button", name="Start capture")).to_be_enabled()
    text = message.text_content()
    received = int(re.search(r"(\d+) samples received", text).group(1))
    kept = int(re.search(r"keeps (\d+)", text).group(1))
    # Everything sent until Stop, and the piece after the loss kept (the longer one).
    assert int(2.0 * RATE_HZ) < received < len(recording)
    assert kept == received - int(1.5 * RATE_HZ)
    expect(page.locator("#recording-current")).to_contain_text("samples")
    expect(page.locator("#steps li[data-step=inputs]")).not_to_have_class("done")  # no scan yet
    pendant.shot("captured")
    # The replay choice lists the captured recording.
    form.get_by_label("Source").select_option("replay")
    expect(form.locator("select[name=recording_id]")).to_contain_text(f"({kept} samples)")
    expect(form.get_by_label("Command port")).to_be_hidden()
