"""The pendant's time to a rendered 3-D view and the bytes it moves (``make bench``): in
headless Chromium (Debian's, as the UI tests drive it) against ``teachpath serve``, from the
page's start-up URL to the first frame drawn with the session's layers, for the demo session
(scan, trace), the demo reconstructed and planned (the plan's preview and arm too), and a session
with a 1M-point scan. Printed as a table; no time is asserted.

Each run is a fresh browser context (nothing cached), as an operator's first visit.
"""

from __future__ import annotations

import statistics
import time

import numpy as np
import pytest

from drivers.scanning.pointcloud import write_scan
from recon.inputs import Scan
from tests.server_process import Server
from tests.ui.conftest import CHROMIUM_ARGS, chromium_path

pytestmark = pytest.mark.bench

REPEATS = 5
TOKEN = "bench-token-abcdefghijklmnopqrstuv"
#: Waits until the workspace has drawn the scan, and the plan's arm when there is a plan.
DRAWN = """(planned) => {
  const w = document.querySelector('#workspace')?.workspace;
  return w && w.layers.scan && (!planned || w.layers.arm) && document.body.dataset.ready;
}"""


def _session(server: Server, name: str) -> str:
    return next(s["id"] for s in server.client.get("/sessions").json() if s["name"] == name)


def _one_visit(browser, server: Server, session: str, planned: bool) -> dict:
    """Open the start-up URL, open the session, wait for the drawn view; time and bytes."""
    context = browser.new_context(viewport={"width": 1500, "height": 1000})
    page = context.new_page()
    responses = []
    page.on("requestfinished", lambda request: responses.append(request))
    start = time.perf_counter()
    page.goto(server.start_url)
    page.wait_for_selector("body[data-ready=true]")
    page.get_by_role("button", name=session, exact=True).click()
    page.wait_for_function(DRAWN, arg=planned, timeout=120_000)
    # The frame after the layers are filled is on screen once a requestAnimationFrame has run.
    page.evaluate("() => new Promise((resolve) => requestAnimationFrame(() => resolve()))")
    seconds = time.perf_counter() - start
    sizes = {r.url: r.sizes() for r in responses}
    scan_bytes = sum(s["responseBodySize"] for u, s in sizes.items() if "/points" in u)
    total = sum(s["responseBodySize"] + s["responseHeadersSize"] for s in sizes.values())
    drawn = page.evaluate(
        "() => document.querySelector('#workspace').workspace.layers.scan.geometry.drawRange.count"
    )
    context.close()
    return {"s": seconds, "scan_bytes": scan_bytes, "total_bytes": total, "drawn": drawn}


def test_time_to_a_rendered_view(tmp_path):
    from playwright.sync_api import sync_playwright

    server = Server(tmp_path / "data", token=TOKEN, demo=True, timeout_s=120)
    rows = []
    try:
        client = server.client
        # A session with a 1M-point scan (a 0.5 m x 0.5 m plate with a bump, 1 mm noise).
        rng = np.random.default_rng(0)
        xy = rng.uniform(-0.25, 0.25, (1_000_000, 2))
        z = 0.02 * np.exp(-(xy**2).sum(axis=1) / 0.01) + rng.normal(0, 1e-3, len(xy))
        ply = tmp_path / "million.ply"
        write_scan(ply, Scan(points_m=np.column_stack([xy, z])))
        big = client.post("/sessions", json={"name": "million"}).json()["id"]
        with ply.open("rb") as handle:
            answer = client.put(f"/sessions/{big}/scan", files={"file": ("million.ply", handle)})
        assert answer.status_code == 201, answer.text
        ply_mb = ply.stat().st_size / 2**20
        demo = _session(server, "demo")
        # The demo first as it starts (scan, trace), then reconstructed and planned.
        with sync_playwright() as playwright:
            browser = playwright.chromium.launch(
                executable_path=chromium_path(), args=CHROMIUM_ARGS, headless=True
            )
            cases = [("demo", "demo", False)]
            for name, session, planned in cases:
                rows.append(
                    (name, [_one_visit(browser, server, session, planned) for _ in range(REPEATS)])
                )
            job = server.wait(client.post(f"/sessions/{demo}/reconstructions", json={}).json())
            body = {"reconstruction_id": job["result"]["reconstruction_id"], "speed_m_s": 0.05}
            server.wait(client.post(f"/sessions/{demo}/trajectories", json=body).json())
            for name, session, planned in [
                ("demo, planned", "demo", True),
                ("1M-point scan", "million", False),
            ]:
                rows.append(
                    (name, [_one_visit(browser, server, session, planned) for _ in range(REPEATS)])
                )
            browser.close()
    finally:
        server.stop()

    print(
        f"\nTime to a rendered 3-D view, headless Chromium, {REPEATS} fresh visits each "
        "(start-up URL -> session opened -> first frame with its layers)"
    )
    print(
        f"{'case':<16} {'median s':>9} {'min s':>7} {'max s':>7} {'scan pts drawn':>15} "
        f"{'scan MB wire':>13} {'page MB':>8}"
    )
    for name, visits in rows:
        times = [v["s"] for v in visits]
        v = visits[0]
        print(
            f"{name:<16} {statistics.median(times):>9.2f} {min(times):>7.2f} {max(times):>7.2f} "
            f"{v['drawn']:>15,} {v['scan_bytes'] / 2**20:>13.2f} {v['total_bytes'] / 2**20:>8.2f}"
        )
    print(
        f"(the 1M-point scan's PLY as uploaded: {ply_mb:.1f} MB; the page draws every k-th "
        "point, at most 200 000, as gzip'd float32)"
    )
