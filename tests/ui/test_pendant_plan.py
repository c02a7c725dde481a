"""The pendant's plan timeline, feasibility on the path, point diagnostics, the distance measure
and the execution review, in a real browser on the demo session (planned through the REST API:
the clicks that reconstruct and plan are tested in test_pendant.py)."""

from __future__ import annotations

import colorsys
import json
import math
import re

import numpy as np
import pytest
from playwright.sync_api import expect

from tests.ui.test_pendant import canvas_pixels


def _reconstruct_demo(server) -> tuple[str, str]:
    """The demo session reconstructed; (session id, reconstruction id)."""
    client = server.client
    sid = next(s["id"] for s in client.get("/sessions").json() if s["name"] == "demo")
    job = server.wait(client.post(f"/sessions/{sid}/reconstructions", json={}).json())
    return sid, job["result"]["reconstruction_id"]


def _plan_demo(server) -> tuple[str, str]:
    """The demo session reconstructed and planned at 50 mm/s; (session id, reconstruction id)."""
    client = server.client
    sid, rid = _reconstruct_demo(server)
    body = {"reconstruction_id": rid, "speed_m_s": 0.05}
    job = server.wait(client.post(f"/sessions/{sid}/trajectories", json=body).json())
    assert job["state"] == "succeeded", job
    return sid, rid


def canvas_digest(page) -> int:
    """A checksum of the WebGL canvas's pixels: equal only for the same picture."""
    return page.evaluate(
        """() => {
        const source = document.querySelector('#workspace canvas');
        const copy = document.createElement('canvas');
        copy.width = source.width; copy.height = source.height;
        const ctx = copy.getContext('2d');
        ctx.drawImage(source, 0, 0);
        const data = ctx.getImageData(0, 0, copy.width, copy.height).data;
        let h = 0;
        for (let i = 0; i < data.length; i++) h = (Math.imul(h, 31) + data[i]) | 0;
        return h;
    }"""
    )


def _readout(page, key: str):
    return page.locator(f"#waypoint-readout td[data-key='{key}']")


def _click_point(page, layer: str, index: int) -> None:
    page.locator("#workspace canvas").scroll_into_view_if_needed()
    at = page.evaluate(
        "([layer, index]) => document.querySelector('#workspace').workspace.screenOf(layer, index)",
        [layer, index],
    )
    page.mouse.click(at["x"], at["y"])


def test_the_plan_timeline_the_path_margins_picking_and_the_review(pendant):
    page = pendant.page
    sid, rid = _plan_demo(pendant.server)
    pendant.open()
    page.get_by_role("button", name="demo", exact=True).click()

    # The timeline: at the start of the transit, with the plots of speed, joints and clearance.
    timeline = page.get_by_role("region", name="Plan timeline")
    expect(timeline).to_be_visible()
    expect(timeline.locator("svg.plot")).to_have_count(4)
    expect(page.locator("#timeline-now")).to_have_text(re.compile(r"^0\.00 s / \d+\.\d\d s$"))
    expect(_readout(page, "phase")).to_have_text("transit")
    total_s = float(page.locator("#timeline-now").text_content().split("/ ")[1].split(" ")[0])
    # The arm where it stands now (from the robot's state stream; the simulated arm at home):
    # drawn in green, its TCP the one the server reports.
    robot = pendant.server.client.get("/robot").json()
    assert len(robot["joints_m"]) == 8
    expect(page.locator("#workspace")).to_have_attribute(
        "data-live-arm", json.dumps(robot["joints_m"][-1], separators=(",", ":"))
    )
    # (At the plan's start the planned arm stands where the live one does: hidden here.)
    page.get_by_role("button", name="Whole motion").click()
    page.get_by_label("planned arm", exact=True).uncheck()
    with_live_arm = canvas_pixels(page)
    page.get_by_label("arm now", exact=True).uncheck()
    without_arm = canvas_pixels(page)
    assert without_arm["drawn"] < with_live_arm["drawn"], (without_arm, with_live_arm)
    # The planned arm's stick figure is drawn (in the whole motion's view: it stands metres
    # away).
    page.get_by_label("planned arm", exact=True).check()
    at_start = canvas_pixels(page)
    assert at_start["drawn"] > without_arm["drawn"], (at_start, without_arm)
    start_digest = canvas_digest(page)
    pendant.shot("timeline-start")
    # One colour, one meaning: orange is the trace alone. No other layer drawn in a fixed
    # colour (the path by phase, the frames' axes, the cell, the arms) is orange; the ramps
    # (displacement, and the path by a quantity) are read with their legend. Colours are
    # three.js's linear ones, judged as shown on the screen (sRGB).
    colours = page.evaluate(
        """() => { const w = document.querySelector('#workspace').workspace; const out = [];
          w.scene.traverse((o) => {
            if (!o.material || !o.visible || o.name === 'reconstruction') return;
            const name = o.name || (o.parent && o.parent.name) || o.type;
            const attr = o.geometry.attributes.color;
            if (o.material.vertexColors && attr) {
              const count = Math.min(attr.count, o.geometry.drawRange.count);
              const rgb = (i) => [attr.getX(i), attr.getY(i), attr.getZ(i)];
              for (let i = 0; i < count; i++) out.push([name, ...rgb(i)]);
              // A line shows the colours between its vertices too (the GPU blends them).
              const step = o.isLineSegments ? 2 : 1;
              if (o.isLine) for (let i = 0; i + 1 < count; i += step) {
                const [a, b] = [rgb(i), rgb(i + 1)];
                out.push([name, ...a.map((v, k) => (v + b[k]) / 2)]);
              }
            } else if (o.material.color) {
              const c = o.material.color; out.push([name, c.r, c.g, c.b]);
            }
          });
          return out; }"""
    )
    assert {name for name, *_ in colours} >= {"trace", "path", "frames", "arm"}

    def shown(linear: float) -> float:
        return 12.92 * linear if linear <= 0.0031308 else 1.055 * linear ** (1 / 2.4) - 0.055

    def orange(r, g, b) -> bool:
        hue, lightness, saturation = colorsys.rgb_to_hls(shown(r), shown(g), shown(b))
        return 20 <= hue * 360 <= 45 and saturation > 0.6 and lightness > 0.4

    orange_layers = {name for name, *rgb in colours if orange(*rgb)}
    assert orange_layers == {"trace"}, orange_layers

    # A click on the speed plot inside the process phase moves the time there: the arm is
    # drawn elsewhere and the waypoint's margins are read out.
    process = timeline.locator("svg.plot").first.locator("rect[data-phase=process]")
    process.scroll_into_view_if_needed()
    box = process.bounding_box()
    page.mouse.click(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)
    expect(_readout(page, "phase")).to_have_text("process")
    expect(_readout(page, "TCP speed")).to_have_text(re.compile(r"^(4[5-9]|5[0-5]) mm/s of 50$"))
    expect(_readout(page, "closest to the cell")).to_have_text(re.compile(r"^\d{1,3}\.\d mm$"))
    expect(_readout(page, "joint-limit margin")).to_have_text(re.compile(r"^\d+\.\d°$"))
    now_s = float(page.locator("#timeline-now").text_content().split(" s")[0])
    assert 0 < now_s < total_s
    assert canvas_digest(page) != start_digest  # the arm moved
    pendant.shot("timeline-process")

    # Play at 4x: the time runs on, then Pause holds it.
    page.get_by_label("playback").select_option("4")
    play = page.locator("#timeline-play")
    play.click()
    expect(play).to_have_text("Pause")
    page.wait_for_timeout(1000)
    play.click()
    expect(play).to_have_text("Play")
    later_s = float(page.locator("#timeline-now").text_content().split(" s")[0])
    assert later_s > now_s + 1.5 or math.isclose(later_s, total_s, abs_tol=0.01), (now_s, later_s)
    held = page.locator("#timeline-now").text_content()
    page.wait_for_timeout(300)
    expect(page.locator("#timeline-now")).to_have_text(held)

    # Feasibility on the path: coloured per waypoint by the chosen margin, the legend says how.
    page.get_by_role("button", name="Workpiece").click()
    path_colour = page.get_by_label("path by")
    by_phase = canvas_digest(page)
    path_colour.select_option("speed")
    expect(page.locator("#legend-path")).to_contain_text("red slowed to a stop")
    by_speed = canvas_digest(page)
    path_colour.select_option("clearance")
    expect(page.locator("#legend-path")).to_contain_text("50 mm or more from the cell")
    assert len({by_phase, by_speed, canvas_digest(page)}) == 3
    # Along the path the clearance colours vary (near the workpiece red-ish, in the air blue).
    spread = page.evaluate(
        "() => { const c = document.querySelector('#workspace').workspace.layers.path"
        ".geometry.attributes.color.array; let lo = 1, hi = 0;"
        " for (let i = 0; i < c.length; i += 3) {"
        " lo = Math.min(lo, c[i]); hi = Math.max(hi, c[i]); }"
        " return hi - lo; }"
    )
    assert spread > 0.3
    pendant.shot("path-by-clearance")
    # The tool's axis along the path, switched with the path; camera presets from above and
    # from the front show other pictures of the same layers.
    axes = "() => document.querySelector('#workspace').workspace.layers['tool-axes']"
    assert page.evaluate(f"() => ({axes})().geometry.drawRange.count") >= 60  # 30+ glyphs
    workpiece = canvas_digest(page)
    page.get_by_role("button", name="Top").click()
    top = canvas_digest(page)
    page.get_by_role("button", name="Front").click()
    assert len({workpiece, top, canvas_digest(page)}) == 3
    pendant.shot("front-view")
    page.get_by_role("button", name="Workpiece").click()
    assert canvas_digest(page) == workpiece
    page.get_by_label("planned TCP path", exact=True).uncheck()
    assert page.evaluate(f"() => ({axes})().visible") is False
    page.get_by_label("planned TCP path", exact=True).check()
    # By uncertainty: the legend's top is the largest 1-sigma uncertainty of the CSV.
    page.get_by_label("reconstruction by").select_option("uncertainty")
    expect(page.locator("#legend-quantity")).to_have_text("uncertainty (1σ)")
    table = pendant.server.client.get(f"/sessions/{sid}/reconstructions/{rid}/csv").text
    lines = table.splitlines()
    column = lines[0].split(",").index("uncertainty_m")
    top_mm = max(float(line.split(",")[column]) for line in lines[1:]) * 1000
    expect(page.locator("#legend-max")).to_have_text(f"{top_mm:.2f} mm")
    page.get_by_label("reconstruction by").select_option("mode")
    expect(page.locator("#legend-modes")).to_be_visible()
    expect(page.locator("#legend-displacement")).to_be_hidden()

    csv = pendant.server.client.get(f"/sessions/{sid}/reconstructions/{rid}/csv").text
    rows = [line.split(",") for line in csv.splitlines() if line and not line.startswith("#")]
    header, body = rows[0], rows[1:]
    xyz = np.array([[float(r[header.index(c)]) for c in "xyz"] for r in body])
    middle = len(xyz) // 2
    # With every layer shown, a click on a reconstruction point, or 6 px beside it, lands on
    # the reconstruction, not on the denser scan behind it (the nearest point to the ray won).
    readout = page.locator("#pick-readout")
    page.locator("#workspace canvas").scroll_into_view_if_needed()
    at = page.evaluate(
        "([layer, index]) => document.querySelector('#workspace').workspace.screenOf(layer, index)",
        ["reconstruction", middle],
    )
    for dx, dy in ((0, 0), (6, 0), (0, -6)):
        page.mouse.click(at["x"] + dx, at["y"] + dy)
        expect(readout).to_contain_text(re.compile(r"^reconstruction point \d+ at"))
    page.mouse.click(at["x"], at["y"])
    expect(readout).to_contain_text(f"reconstruction point {middle} at")
    # Click a reconstruction point: its diagnostics. Then measure between the path's ends; the
    # distance is the one between the CSV's first and last points.
    for name in ("scan", "raw trace", "planned TCP path", "planned arm", "arm now", "frames"):
        page.get_by_label(name, exact=True).uncheck()
    _click_point(page, "reconstruction", middle)
    expect(readout).to_contain_text(f"reconstruction point {middle} at")
    expect(readout).to_contain_text("displacement")
    expect(readout).to_contain_text("mode: an edge of the scan")
    expect(readout).to_contain_text("fit residuals")
    expect(readout).to_contain_text("(1σ)")
    pendant.shot("picked")
    # The framing buttons sit on the view: with the readout in sight, another framing keeps it
    # (it named the point, not the camera), all on one screen at a cell's touch panel's size.
    page.set_viewport_size({"width": 1280, "height": 800})
    said = readout.inner_text()
    for name in ("Top", "Workpiece"):
        button = page.get_by_role("button", name=name, exact=True)
        for element in (button, readout, page.locator("#workspace canvas")):
            box = element.bounding_box()
            assert box and box["y"] >= 0 and box["y"] + box["height"] <= 800, (name, box)
        button.click()
        expect(readout).to_have_text(said)
    page.set_viewport_size({"width": 1500, "height": 1100})
    page.get_by_label("measure (click two points)").check()
    _click_point(page, "reconstruction", 0)
    _click_point(page, "reconstruction", len(xyz) - 1)
    expected_mm = float(np.linalg.norm(xyz[-1] - xyz[0])) * 1000
    distance = readout.locator(".distance")
    expect(distance).to_contain_text("distance from the previous point")
    shown_mm = float(re.search(r"([\d.]+) mm", distance.text_content()).group(1))
    assert shown_mm == pytest_approx(expected_mm), (shown_mm, expected_mm)
    pendant.shot("measured")

    # The dry run's review: where the arm went against the plan.
    page.get_by_role("button", name="Dry run").click()
    expect(page.locator("#dryrun-summary")).to_contain_text("passed", timeout=60_000)
    review = page.get_by_role("region", name="Execution review")
    expect(review).to_be_visible()
    expect(review).to_contain_text(
        re.compile(
            r"dry run, servoj\): along the path \(process\) the arm was at most \d+\.\d{3} mm"
        )
    )
    # The review says what the dry run's table says: the same two deviations.
    table = page.locator("#dryrun-summary")
    along = table.locator("tr", has_text="largest deviation along the path").locator("td")
    anywhere = table.locator("tr", has_text="largest deviation anywhere").locator("td")
    headline = review.locator("#review-summary").text_content()
    assert f"at most {along.text_content()} from the plan" in headline, headline
    assert f"anywhere {anywhere.text_content()}" in headline, headline
    expect(table.locator("tr", has_text="motion time")).to_contain_text("planned")
    expect(review.locator("svg.plot polyline")).to_have_count(1)
    pendant.shot("review")


def test_the_plan_parameters_come_from_the_schema_and_reach_the_plan(pendant):
    page = pendant.page
    sid, rid = _reconstruct_demo(pendant.server)
    pendant.open()
    page.get_by_role("button", name="demo", exact=True).click()
    form = page.locator("#plan-form")
    form.locator("summary").click()
    expect(form.locator("#plan-robot")).to_have_value("ur5e")  # the server's arm
    expect(form.locator("#plan-orientation")).to_have_value("auto")
    lead = form.locator("#plan-lead_deg")
    expect(lead).to_have_attribute("max", "60")
    expect(form.locator("label[for=plan-lead_deg] .name")).to_have_text("lead (°)")
    expect(form.locator("label[for=plan-lead_deg] .hint")).to_contain_text("-60 to 60°")
    approach = form.locator("#plan-approach_m")
    expect(approach).to_have_value("50")  # 0.05 m, shown in mm
    lead.fill("10")
    # One TCP field, showing the TCP the plan uses (the 100 mm default tool; the form showed a
    # 0,0,0 offset before), in mm and degrees as on UR's pendant.
    tcp = form.locator("#plan-tcp_pose")
    expect(tcp).to_have_value("0, 0, 100, 0, 0, 0")
    expect(form.locator("label[for=plan-tcp_pose] .name")).to_have_text(
        "TCP: x, y, z (mm), rx, ry, rz (deg)"
    )
    tcp.fill("0, 0")  # two numbers: refused on the page, nothing sent
    posts = []
    page.on("request", lambda r: posts.append(r.url) if r.method == "POST" else None)
    form.get_by_role("button", name="Plan").click()
    expect(form.locator(".message")).to_contain_text("rz (deg): give 6 numbers")
    assert not posts
    tcp.fill("0, 0, 9000, 0, 0, 0")  # 9 m: out of range, said in mm and degrees
    form.get_by_role("button", name="Plan").click()
    expect(form.locator(".message")).to_contain_text("[-6283.2, 6283.2] / [-360, 360]")
    assert not posts
    tcp.fill("0, 0, 120, 0, 0, 0")
    # Leaning 10° along the travel in this configuration, the tool meets the cylinder on the
    # way out: what to change. (With shoulder or wrist left to "any", another configuration is
    # tried and found clear.)
    form.locator("#plan-shoulder").select_option("right")
    form.locator("#plan-wrist").select_option("flip")
    form.get_by_role("button", name="Plan").click()
    message = form.locator(".message")
    expect(message).to_contain_text("the motion collides", timeout=60_000)
    expect(message).to_contain_text("comes too close to")
    expect(message).to_contain_text("Change the tool orientation (lead, tilt)")
    pendant.shot("plan-collides")
    lead.fill("0")
    form.locator("#plan-tilt_deg").fill("10")
    form.get_by_role("button", name="Plan").click()
    expect(message).to_be_empty(timeout=10_000)
    expect(form.locator(".job-state")).to_have_text("succeeded 100 %", timeout=60_000)
    pendant.shot("plan-parameters")
    trajectories = pendant.server.client.get(f"/sessions/{sid}/trajectories").json()
    params = trajectories[-1]["params"]
    assert trajectories[-1]["inputs"]["reconstruction_id"] == rid
    assert params["lead_deg"] == 0 and params["tilt_deg"] == 10
    assert params["tcp_pose"] == pytest.approx([0, 0, 0.12, 0, 0, 0]) and params["robot"] == "ur5e"
    # The millimetres on the form are metres in the request.
    assert params["approach_m"] == pytest.approx(0.05) and params["clearance_m"] == pytest.approx(
        0.01
    )
    # The plan summary says which TCP and payload it was planned with.
    plan = page.locator("#plan-summary")
    expect(plan).to_contain_text("x 0.0, y 0.0, z 120.0 mm; rx 0.0, ry 0.0, rz 0.0 deg")
    expect(plan).to_contain_text("not set by the plan: the controller's")
    assert params["speed_m_s"] == 0.05
    assert params["shoulder"] == "right" and params["wrist"] == "flip"


def test_two_reconstructions_overlaid_with_their_difference(pendant):
    page = pendant.page
    client = pendant.server.client
    sid, _ = _reconstruct_demo(pendant.server)
    job = client.post(f"/sessions/{sid}/reconstructions", json={"radius_m": 0.004}).json()
    older = pendant.server.wait(job)["result"]["reconstruction_id"]
    sid, current = _reconstruct_demo(pendant.server)
    pendant.open()
    page.get_by_role("button", name="demo", exact=True).click()
    row = page.locator(f"table.comparison tr[data-reconstruction={older}]")
    expect(page.locator("table.comparison tr.current button")).to_be_disabled()
    before = canvas_digest(page)
    row.get_by_role("button", name="Overlay").click()
    note = page.locator("#overlay-note")
    # The older reconstruction's arrays are fetched and drawn first (slow on a loaded machine).
    expect(note).to_contain_text(f"{older} over {current}", timeout=30_000)
    expected = client.get(
        f"/sessions/{sid}/reconstructions/{older}/difference?against={current}"
    ).json()
    expect(note).to_contain_text(f"{expected['max_m'] * 1000:.3f} mm at most")
    expect(page.locator("#legend-overlay")).to_be_visible()
    assert canvas_digest(page) != before
    for name in (
        "scan",
        "raw trace",
        "reconstruction",
        "planned TCP path",
        "planned arm",
        "arm now",
        "frames",
    ):
        page.get_by_label(name, exact=True).uncheck()
    _click_point(page, "overlay", expected["at_index"])
    readout = page.locator("#pick-readout")
    expect(readout).to_contain_text("mm from the current reconstruction")
    # The page measures in float32 positions a few hundred mm from the base: the last digit
    # may differ from the server's (0.646 against 0.645 was seen).
    shown_mm = float(re.search(r"([0-9.]+) mm from the current", readout.inner_text()).group(1))
    assert shown_mm == pytest_approx(expected["max_m"] * 1000), shown_mm
    pendant.shot("overlay")


def pytest_approx(value: float):
    """Within 0.02 mm: float32 positions of points a few hundred mm from the base."""
    import pytest

    return pytest.approx(value, abs=0.02)


def test_a_comma_decimal_is_taken_and_a_bad_value_is_said_in_the_fields_words(pendant):
    """Operators on many keyboards type "0,8"; the server's refusals name the field as on the
    form (it said "body.alpha.constrained-float")."""
    page = pendant.page
    pendant.guard.allow(422, "/reconstructions")  # the refusal below, on purpose
    pendant.open()
    page.get_by_role("button", name="demo", exact=True).click()
    alpha = page.locator("#recon-alpha")
    alpha.fill("0,8")
    page.get_by_role("button", name="Reconstruct").click()
    expect(page.locator("#reconstruct-form .job-state")).to_have_text(
        "succeeded 100 %", timeout=90_000
    )
    sid = page.evaluate("sessionStorage.getItem('teachpath.session')")
    reconstructions = pendant.server.client.get(f"/sessions/{sid}/reconstructions").json()
    assert reconstructions[-1]["params"]["alpha"] == pytest.approx(0.8)
    alpha.fill("5")  # over its range of [0, 1]: the server refuses, naming the field
    page.get_by_role("button", name="Reconstruct").click()
    message = page.locator("#reconstruct-form .message")
    expect(message).to_contain_text("trace weight α (alpha): ")
    expect(message).not_to_contain_text("body.")
    expect(message).not_to_contain_text("constrained")
    pendant.shot("alpha-refused")


def test_the_cell_is_edited_in_3d_and_outdates_the_plans_made_in_another(pendant):
    """Calibrate, Cell: a keep-out box added around a point clicked in the 3-D view and a wall
    typed in mm, drawn as a draft (dashed) while unsaved; saved, the plan made before is
    outdated; an edit from a view another pendant changed is refused and discarded; back to the
    start-up settings, the plan is current again."""
    page, client = pendant.page, pendant.server.client
    _sid, _ = _plan_demo(pendant.server)
    try:
        pendant.open()
        page.get_by_role("button", name="demo", exact=True).click()
        workspace = page.locator("#workspace")
        expect(workspace).to_have_attribute("data-cell", "0")
        form = page.locator("#cell-form")
        expect(page.locator("#cell-source")).to_have_text("Saved: the server's start-up settings.")
        add_at_pick = page.get_by_role("button", name="Add a box around the picked point")
        expect(add_at_pick).to_be_disabled()  # nothing picked yet
        # Two boxes added and the first removed: the second is box 1 now; removed too.
        page.get_by_role("button", name="Add a box", exact=True).click()
        page.get_by_label("box 1 x min (mm)").fill("300")
        page.get_by_role("button", name="Add a box", exact=True).click()
        page.get_by_role("button", name="remove box 1").click()
        expect(page.get_by_label("box 1 x min (mm)")).to_have_value("500")
        expect(page.get_by_role("button", name="remove box 2")).to_have_count(0)
        page.get_by_role("button", name="remove box 1").click()
        expect(form.locator("#cell-boxes tbody tr")).to_have_count(0)

        # A reconstruction point clicked in the 3-D view (base frame): a 100 mm box around it.
        for name in ("scan", "raw trace", "planned TCP path", "planned arm", "arm now"):
            page.get_by_label(name, exact=True).uncheck()
        _click_point(page, "reconstruction", 10)
        readout = page.locator("#pick-readout").text_content()
        picked_mm = np.array(
            re.search(r"at \(([-\d.]+), ([-\d.]+), ([-\d.]+)\) mm", readout).groups(), dtype=float
        )
        add_at_pick.click()
        box_row = form.locator("#cell-boxes tbody tr")
        expect(box_row).to_have_count(1)
        typed = box_row.locator("input").evaluate_all("inputs => inputs.map(i => i.value)")
        corners = [float(v) for v in typed]
        np.testing.assert_allclose(corners[:3], picked_mm - 50, atol=0.1)
        np.testing.assert_allclose(corners[3:], picked_mm + 50, atol=0.1)
        expect(workspace).to_have_attribute("data-cell-draft", "12")  # a box's 12 edges
        expect(workspace).to_have_attribute("data-cell", "0")  # nothing saved yet
        expect(page.locator("#cell-draft")).to_contain_text("Not saved: 1 box and 0 planes")

        # A wall 1 m behind the arm, typed with a comma decimal; a field that is not a number
        # is marked and nothing is sent.
        page.get_by_role("button", name="Add a plane").click()
        d = page.get_by_label("plane 1 d (mm)")
        d.fill("abc")
        expect(page.locator("#cell-draft")).to_contain_text("(the field is marked in red)")
        assert d.evaluate("input => input.validity.valid") is False
        page.get_by_role("button", name="Save cell").click()
        expect(form.locator("#cell-planes tr.invalid")).to_have_count(1)
        assert client.get("/cell").json()["revision"] == 0
        d.fill("-1000,5")
        expect(form.locator("tr.invalid")).to_have_count(0)
        expect(workspace).to_have_attribute("data-cell-draft", re.compile(r"^(1[3-9]|[2-9]\d)$"))
        # A maximum below its minimum is said on its field before anything is sent.
        x_max = page.get_by_label("box 1 x max (mm)")
        x_max.fill("0")
        expect(page.locator("#cell-draft")).to_contain_text("must be above x min")
        x_max.fill(f"{corners[3]:g}")
        expect(form.locator("tr.invalid")).to_have_count(0)
        pendant.shot("cell-draft")
        page.get_by_role("button", name="Save cell").click()
        expect(form.locator(".message")).to_have_text(
            "Cell saved (revision 1): plans made in another cell are now outdated."
        )
        saved = client.get("/cell").json()
        np.testing.assert_allclose(
            saved["keep_out_boxes_m"][0], np.array(corners) / 1000, atol=1e-9
        )
        assert saved["cell_planes"] == [[1.0, 0.0, 0.0, -1.0005]]
        expect(workspace).to_have_attribute("data-cell-draft", "0")
        # Nothing being edited: its legend entry goes too (the swatch once stayed, unlabelled).
        expect(page.locator("#legend-cell-draft")).to_be_hidden()
        expect(workspace).to_have_attribute("data-cell", re.compile(r"^(1[3-9]|[2-9]\d)$"))
        cell_line = page.locator("#calibration-current tr", has_text="cell")
        expect(cell_line).to_contain_text("1 keep-out box, 1 plane besides the mounting one")
        expect(cell_line).to_contain_text("edited in the pendant at ")
        # The plan was made in the cell without them: outdated, not offered for the arm.
        expect(page.locator("#step-plan .outdated")).to_contain_text(
            "the cell: planned with 0 keep-out boxes and 0 planes; the cell now has 1 keep-out "
            "box and 1 plane"
        )
        expect(page.locator("#steps li[data-step=plan]")).to_have_class("todo")
        pendant.shot("cell-saved")

        # This pendant starts an edit; another removes the wall meanwhile. This one's edit, from
        # the older view, is refused saying so, and Discard changes shows the other's cell. (The
        # edit starts first: a page not editing takes the newer cell as it arrives, and an edit
        # begun after that is made from it, rightly saved.)
        pendant.guard.allow(409, "/cell")
        page.get_by_label("box 1 z max (mm)").fill("400")
        other = {"keep_out_boxes_m": saved["keep_out_boxes_m"], "cell_planes": [], "revision": 1}
        assert client.put("/cell", json=other).status_code == 200
        page.get_by_role("button", name="Save cell").click()
        message = form.locator(".message")
        expect(message).to_have_attribute("data-code", "cell_changed")
        expect(message).to_contain_text("reload it, check the change and edit again")
        expect(page.locator("#cell-source")).to_contain_text(
            "changed by another pendant since you started editing"
        )
        # Pressed again, it is refused again: the draft never overwrites the other's change.
        page.get_by_role("button", name="Save cell").click()
        expect(message).to_have_attribute("data-code", "cell_changed")
        assert client.get("/cell").json()["cell_planes"] == []
        assert client.get("/cell").json()["revision"] == 2
        page.once("dialog", lambda dialog: dialog.accept())  # "Discard the changes you typed?"
        page.get_by_role("button", name="Discard changes").click()
        expect(form.locator("#cell-planes tbody tr")).to_have_count(0)
        expect(page.get_by_label("box 1 z max (mm)")).to_have_value(f"{corners[5]:g}")

        # Back to the start-up settings: nothing drawn, the plan is current again.
        # Asked first (it applies to every pendant at once): dismissed, nothing changes.
        page.once("dialog", lambda dialog: dialog.dismiss())
        page.get_by_role("button", name="Back to the start-up settings").click()
        assert client.get("/cell").json()["revision"] == 2
        page.once("dialog", lambda dialog: dialog.accept())
        page.get_by_role("button", name="Back to the start-up settings").click()
        expect(form.locator(".message")).to_have_text("Back to the start-up settings (revision 3).")
        expect(workspace).to_have_attribute("data-cell", "0")
        expect(page.locator("#step-plan .outdated")).to_have_count(0)
        expect(page.locator("#steps li[data-step=plan]")).to_have_class("done")
    finally:
        revision = client.get("/cell").json()["revision"]
        client.delete("/cell", params={"revision": revision})


def test_a_finger_picks_within_its_reach_where_a_mouse_must_come_closer(browser, server, screens):
    """On a touch screen a tap picks the nearest point within a finger's reach (22 px); a mouse
    click there, farther than 10 px from every point, picks nothing. Both on the spot itself
    pick the point under them."""
    from tests.ui.conftest import pendant_for

    _, rid = _reconstruct_demo(server)
    with pendant_for(browser, server, screens, "touch-pick", has_touch=True) as pendant:
        page = pendant.page
        pendant.open()
        page.get_by_role("button", name="demo", exact=True).click()
        page.wait_for_function(
            "(rid) => (document.querySelector('#workspace').dataset.shown || '').includes(rid)",
            arg=rid,
        )
        for name in ("scan", "raw trace", "planned TCP path", "planned arm", "arm now", "frames"):
            box = page.get_by_label(name, exact=True)
            if box.count() and box.is_checked():
                box.uncheck()
        page.locator("#workspace canvas").scroll_into_view_if_needed()
        # Where every reconstruction point is drawn, and the canvas.
        drawn = np.array(
            page.evaluate(
                """() => {
                const ws = document.querySelector('#workspace').workspace;
                const n = ws.layers.reconstruction.geometry.drawRange.count;
                return Array.from({length: n}, (_, i) => {
                    const p = ws.screenOf('reconstruction', i); return [p.x, p.y]; });
            }"""
            )
        )
        canvas = page.locator("#workspace canvas").bounding_box()
        middle = len(drawn) // 2
        along = drawn[min(middle + 10, len(drawn) - 1)] - drawn[max(middle - 10, 0)]
        normal = np.array([-along[1], along[0]]) / np.linalg.norm(along)
        # A spot beside the path's middle, 16 px from the nearest drawn point: out of a mouse's
        # reach (10 px), within a finger's (22 px).
        spot = None
        for offset_px in np.arange(12.0, 22.0, 0.5):
            for side in (1.0, -1.0):
                candidate = drawn[middle] + side * offset_px * normal
                nearest_px = float(np.linalg.norm(drawn - candidate, axis=1).min())
                inside = (
                    canvas["x"] + 60 < candidate[0] < canvas["x"] + canvas["width"] - 120
                    and canvas["y"] + 20 < candidate[1] < canvas["y"] + canvas["height"] - 20
                )
                if inside and 15.0 <= nearest_px <= 17.0:
                    spot = candidate
                    break
            if spot is not None:
                break
        assert spot is not None, "no spot 15-17 px beside the path's middle"
        readout = page.locator("#pick-readout")
        page.mouse.click(*spot)
        expect(readout).to_have_text("Nothing under the cursor: click on a point of a shown layer.")
        page.touchscreen.tap(*spot)
        expect(readout).to_contain_text(re.compile(r"^reconstruction point \d+ at"))
        expect(readout).to_contain_text("displacement")
        # The diagnostics are beside the view, on the same screen.
        view = page.locator("#workspace").bounding_box()
        shown = readout.bounding_box()
        assert shown["y"] < 1100 and abs(shown["x"] - view["x"]) < view["width"]
        # A mouse click on a point itself picks it.
        page.mouse.click(*drawn[middle])
        expect(readout).to_contain_text(f"reconstruction point {middle} at")
        pendant.shot("tapped")
