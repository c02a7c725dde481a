"""The teach pendant driven as an operator would, in Debian's chromium (see conftest.py)."""

from __future__ import annotations

import re
import tempfile
from pathlib import Path

import pytest
from playwright.sync_api import expect

from tests.ui.conftest import TOKEN, pendant_for


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
    expect(page.locator("#protective-stop-field")).to_be_hidden()  # shown when there is one
    expect(page.locator("#remote-control")).to_have_text("on")
    expect(page.locator("#arm-owner")).to_have_text("none")
    expect(page.locator("#speed-cap")).to_have_text("250 mm/s")
    expect(page.locator("#link-state")).to_have_text("live")
    expect(bar).to_be_visible()
    # Nothing moves: no Stop button.
    expect(page.get_by_role("button", name="Stop")).to_be_hidden()
    pendant.shot("safety-bar")


def test_docs_render_offline_from_local_assets(pendant):
    page = pendant.page
    response = page.goto(f"{pendant.server.url}/docs")
    assert "default-src 'self'" in response.headers["content-security-policy"]
    assert response.headers["referrer-policy"] == "no-referrer"
    expect(page.locator(".swagger-ui .info .title")).to_contain_text("teachpath")
    expect(page.locator(".opblock-summary-path", has_text="/robot/events")).to_be_visible()
    pendant.shot("docs")
    page.goto(f"{pendant.server.url}/redoc")
    expect(page.get_by_role("heading", name=re.compile("^teachpath"), level=1)).to_be_visible()
    assert all(url.startswith(pendant.server.url) for url in pendant.guard.requests)
    assert any("/ui/vendor/swagger-ui/" in url for url in pendant.guard.requests)


def test_sessions_create_open_delete(pendant):
    page = pendant.page
    pendant.open()
    expect(page.locator("#session-list li", has_text="demo")).to_be_visible()
    pendant.create_session("door frame")
    expect(page.locator("#session-title")).to_have_text("Session door frame")
    expect(page.locator("#step-inputs .needs")).to_have_text("Needs a recording and a scan.")
    expect(page.locator("#steps li")).to_have_text(
        ["Inputs", "Calibration", "Reconstruct", "Plan", "Dry run", "Run"]
    )
    expect(page.get_by_role("button", name="Reconstruct")).to_be_disabled()
    expect(page.get_by_role("button", name="Dry run")).to_be_disabled()
    expect(page.get_by_role("button", name="Run on arm")).to_be_disabled()
    pendant.shot("new-session")
    page.on("dialog", lambda dialog: dialog.accept())
    page.get_by_role("button", name="Delete door frame").click()
    expect(page.locator("#session-list li", has_text="door frame")).to_have_count(0)
    expect(page.locator("#session-view")).to_be_hidden()


def test_uploads_show_the_422_inline_and_then_take_good_files(pendant, scene_files):
    page = pendant.page
    pendant.guard.allow(422, "/recording")
    pendant.open()
    pendant.create_session("uploads")
    expect(page.locator("#session-title")).to_have_text("Session uploads")
    recording = page.locator("#recording-form")
    recording.get_by_label("File", exact=True).set_input_files(
        {"name": "trace.csv", "mimeType": "text/csv", "buffer": b"t,x,y\nnot,a,trace\n"}
    )
    recording.get_by_role("button", name="Upload recording").click()
    message = recording.locator(".message")
    expect(message).to_have_attribute("data-code", re.compile(r"invalid_file|invalid_request"))
    expect(message).to_contain_text("check its format and units")
    expect(page.locator("#recording-current")).to_have_text("none yet")
    pendant.shot("upload-refused")

    recording.get_by_label("File", exact=True).set_input_files(
        {"name": "trace.csv", "mimeType": "text/csv", "buffer": scene_files["trace"]}
    )
    recording.get_by_label(re.compile("^Units")).select_option("m")
    recording.get_by_role("button", name="Upload recording").click()
    expect(message).to_have_text("trace.csv uploaded.")
    expect(page.locator("#recording-current")).to_contain_text("samples")
    scan = page.locator("#scan-form")
    # A scan written in millimetres, uploaded as metres (a 100 m part): refused at the upload,
    # saying which unit its numbers look like and what to pick on this form; nothing stored.
    pendant.guard.allow(422, "/scan")
    scan.get_by_label("File", exact=True).set_input_files(
        {"name": "scan_mm.ply", "mimeType": "application/octet-stream", "buffer": _scan_in_mm()}
    )
    scan.get_by_label(re.compile("^Format")).select_option("ply")
    scan.get_by_role("button", name="Upload scan").click()
    scan_message = scan.locator(".message")
    expect(scan_message).to_have_attribute("data-code", "units_mismatch")
    expect(scan_message).to_contain_text("pick its Units (m or mm)")
    expect(scan_message).to_contain_text("look like millimetres")
    expect(scan_message).to_contain_text("units set to mm")
    expect(page.locator("#scan-current")).to_have_text("none yet")
    pendant.shot("scan-units-refused")
    # The same file as millimetres: taken, its size on the card in millimetres.
    scan.get_by_label(re.compile("^Units")).select_option("mm")
    scan.get_by_role("button", name="Upload scan").click()
    size = re.compile(r"points, \d+ × \d+ × \d+ mm$")
    expect(page.locator("#scan-current")).to_have_text(size)
    in_mm = page.locator("#scan-current").inner_text().split(": ", 1)[1]
    # The scan in metres: the same part, the same size on its card.
    scan.get_by_label("File", exact=True).set_input_files(
        {"name": "scan.ply", "mimeType": "application/octet-stream", "buffer": scene_files["scan"]}
    )
    scan.get_by_label(re.compile("^Units")).select_option("m")
    scan.get_by_role("button", name="Upload scan").click()
    expect(page.locator("#scan-current")).to_have_text(f"scan.ply: {in_mm}")
    expect(page.locator("#steps li[data-step=inputs]")).to_have_class("done")
    expect(page.locator("#step-calibration .needs")).to_contain_text("T_base_tracker")
    expect(page.get_by_role("button", name="Reconstruct")).to_be_enabled()
    expect(page.get_by_role("button", name="Plan", exact=True)).to_be_disabled()
    pendant.shot("uploaded")


def _scan_in_mm() -> bytes:
    """The pendant tests' scene scan (recon.scenes.box_corner) written with its coordinates in
    millimetres."""
    from drivers.scanning.pointcloud import write_scan
    from recon import scenes
    from recon.inputs import Scan

    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "scan_mm.ply"
        write_scan(path, Scan(points_m=scenes.box_corner(0).scan.points_m * 1e3))
        return path.read_bytes()


def canvas_pixels(page) -> dict:
    """What the WebGL canvas shows: its size, the distinct colours and the non-background share."""
    return page.evaluate(
        """() => {
        const source = document.querySelector('#workspace canvas');
        const copy = document.createElement('canvas');
        copy.width = source.width; copy.height = source.height;
        const ctx = copy.getContext('2d');
        ctx.drawImage(source, 0, 0);
        const data = ctx.getImageData(0, 0, copy.width, copy.height).data;
        const colours = new Set(); let drawn = 0;
        for (let i = 0; i < data.length; i += 4) {
          const c = (data[i] << 16) | (data[i + 1] << 8) | data[i + 2];
          colours.add(c);
          if (c !== 0xf6f7f9) drawn++;
        }
        return {width: copy.width, height: copy.height, colours: colours.size,
                drawn: drawn / (data.length / 4)};
    }"""
    )


def test_demo_session_from_reconstruction_to_the_run_refusal(pendant, scene_files, tmp_path):
    page = pendant.page
    pendant.guard.allow(409, "/executions")
    posts = []
    page.on(
        "request",
        lambda r: posts.append(r.url.split("/")[-1]) if r.method == "POST" else None,
    )
    pendant.open()
    page.get_by_role("button", name="demo", exact=True).click()
    expect(page.locator("#session-title")).to_have_text("Session demo")
    expect(page.locator("#steps li[data-step=inputs]")).to_have_class("done")
    expect(page.locator("#steps li[data-step=calibration]")).to_have_class("done")
    expect(page.locator("#step-reconstruct .needs")).to_contain_text("press Reconstruct")

    # Reconstruct: the parameters come from the API's schema, with their units and ranges.
    radius = page.locator("#recon-radius_m")
    # In the operator's words and units: millimetres (the API takes metres).
    expect(radius).to_have_value("8")
    expect(radius).to_have_attribute("max", "200")
    expect(page.locator("label[for=recon-radius_m] .name")).to_have_text(
        "neighbourhood radius (mm)"
    )
    expect(page.locator("label[for=recon-radius_m] .hint")).to_contain_text("0.5 to 200 mm")
    # A checkbox's hint says what its state does, and follows it.
    use_scan = page.locator("#recon-use_scan")
    scan_hint = page.locator("label[for=recon-use_scan] .hint")
    expect(scan_hint).to_have_text("ticked: the scan corrects the trace")
    use_scan.uncheck()
    expect(scan_hint).to_contain_text("not ticked: the trace alone")
    use_scan.check()
    expect(scan_hint).to_have_text("ticked: the scan corrects the trace")
    expect(page.locator("#recon-method")).to_have_value("anchored")
    expect(page.locator("#recon-alpha")).to_have_value("auto")
    radius.fill("10")
    pendant.shot("reconstruct-params")
    button = page.get_by_role("button", name="Reconstruct")
    button.click()
    expect(button).to_be_disabled()
    expect(page.locator("#reconstruct-form .job-state")).to_contain_text("running")
    expect(page.locator("#steps li[data-step=reconstruct]")).to_have_class(re.compile("running"))
    pendant.shot("reconstructing")
    expect(page.locator("#reconstruct-summary")).to_contain_text("max displacement", timeout=90_000)
    expect(button).to_be_enabled()
    assert posts.count("reconstructions") == 1
    expect(page.locator("#reconstruct-form .job-state")).to_have_text("succeeded 100 %")
    summary = page.locator("#reconstruct-summary")
    expect(summary).to_contain_text(
        re.compile(r"registration\s*to the scan's (edge|surface): rmse")
    )
    expect(summary).to_contain_text(re.compile(r"motions the scan fixed\s*[1-6] of 6"))
    expect(summary).to_contain_text(re.compile(r"segments\s*edge \(points 0–\d+\)"))
    pendant.shot("reconstructed")

    # Plan: the speed slider stops at the server's cap.
    speed = page.locator("#plan-speed")
    expect(speed).to_have_attribute("max", "0.25")
    speed.fill("0.08")
    typed = page.get_by_label("Speed along the path in mm/s")
    expect(typed).to_have_value("80")  # the field beside the slider follows it
    expect(page.locator("#plan-speed-cap")).to_contain_text("250 mm/s")
    expect(typed).to_have_attribute("max", "250")
    # Typed in mm/s, the slider follows (to the millimetre per second).
    typed.fill("83")
    expect(speed).to_have_value("0.083")
    page.get_by_role("button", name="Plan", exact=True).click()
    summary = page.locator("#plan-summary")
    expect(summary.locator("tr[data-phase=process]")).to_be_visible(timeout=60_000)
    expect(summary).to_contain_text("83 mm/s")  # what was typed, not the slider's step
    expect(summary.locator(".report")).not_to_be_empty()
    assert posts.count("trajectories") == 1
    expect(page.get_by_role("button", name="Run on arm")).to_be_disabled()
    # Every phase's fastest TCP speed is shown, and the speed plot does not hide what is above
    # its scale (it was cut at 1.6 times the path's speed without a mark: the transit's 588
    # mm/s did not show).
    transit = summary.locator("tr[data-phase=transit] td")
    expect(transit).to_contain_text(re.compile(r"TCP up to \d+ mm/s"))
    fastest_mm_s = int(re.search(r"TCP up to (\d+) mm/s", transit.inner_text()).group(1))
    assert fastest_mm_s <= 250 + 1  # the server's cap holds in the transit too
    plot = page.locator("svg.plot[aria-label^='TCP speed']")
    expect(plot).to_contain_text("off the scale (red on top): up to")
    off_scale_mm_s = float(plot.get_attribute("data-off-scale"))
    assert 1.6 * 83 < off_scale_mm_s <= fastest_mm_s + 1, (off_scale_mm_s, fastest_mm_s)
    assert plot.locator("rect.clipped").count() >= 1
    pendant.shot("planned")

    # A dry run moves no arm: no Stop button (the simulated run cannot be stopped either).
    stop = page.get_by_role("button", name="Stop")
    dry = page.get_by_role("button", name="Dry run")
    # A full dry run: passed, and only now may the run be asked for.
    dry.click()
    expect(dry).to_be_disabled()
    expect(page.locator("#dryrun-form .job-state")).to_contain_text("running")
    expect(stop).to_be_hidden()
    pendant.shot("dry-running")
    expect(page.locator("#dryrun-summary")).to_contain_text("passed", timeout=60_000)
    assert posts.count("executions") == 1
    expect(page.locator("#steps li[data-step=dryrun]")).to_have_class("done")
    # This server has no real arm: the Run step says so and how to have one; it said "Ready"
    # and "the arm will move" before, and offered the button for a refusal.
    run = page.get_by_role("button", name="Run on arm")
    expect(run).to_be_disabled()
    run_needs = page.locator("#step-run .needs")
    expect(run_needs).to_contain_text("No real arm on this server (simulation only)")
    expect(run_needs).to_contain_text("TEACHPATH_UR_HOST")
    # Another mode has no dry run of its own.
    page.get_by_label(re.compile("^Mode")).select_option("movepath")
    expect(page.locator("#step-dryrun .needs")).to_contain_text("(mode movepath)")
    page.get_by_label(re.compile("^Mode")).select_option("servoj")
    expect(page.locator("#steps li[data-step=dryrun]")).to_have_class("done")
    pendant.shot("dry-run-passed")
    _every_download_is_the_servers_file(pendant, "#plan-summary", "trajectories", 3)
    _every_download_is_the_servers_file(pendant, "#dryrun-summary", "executions", 1)
    _every_download_is_the_servers_file(pendant, "#reconstruct-summary", "reconstructions", 1)
    _every_download_is_the_servers_file(pendant, "#scan-files", "scans", 1)

    # The workspace draws the scan, trace, reconstruction and path.
    page.wait_for_function("document.querySelector('#legend-max').textContent.endsWith('mm')")
    pixels = canvas_pixels(page)
    assert pixels["width"] > 300 and pixels["colours"] > 5 and pixels["drawn"] > 0.002, pixels
    # Framed on the workpiece: the scan fills a good part of the view; "Whole motion" takes in
    # the transit from the arm's pose too, and the workpiece shrinks.
    assert pixels["drawn"] > 0.05, pixels
    page.get_by_role("button", name="Whole motion").click()
    whole = canvas_pixels(page)
    assert whole["drawn"] < 0.5 * pixels["drawn"], (whole, pixels)
    pendant.shot("whole-motion")
    page.get_by_role("button", name="Workpiece").click()
    assert canvas_pixels(page)["drawn"] == pytest.approx(pixels["drawn"], rel=0.05)
    pendant.shot("workpiece")

    assert posts.count("executions") == 1  # nothing was sent for the arm

    # A new trace: the plan, its passed dry run and "Run on arm" belonged to the old one. They
    # stayed "done" and offered before; now they are shown outdated and the run is not offered.
    client = pendant.server.client
    sid = page.evaluate("sessionStorage.getItem('teachpath.session')")
    demo_trace = client.get(f"/sessions/{sid}").json()["recording_id"]
    demo_csv = client.get(f"/sessions/{sid}/recordings/{demo_trace}/csv").content
    trace = tmp_path / "new_trace.csv"
    trace.write_bytes(scene_files["trace"])
    page.locator("#recording-form input[type=file]").set_input_files(str(trace))
    page.get_by_role("button", name="Upload recording").click()
    expect(page.locator("#recording-current")).to_contain_text("new_trace.csv")
    for step in ("reconstruct", "plan", "dryrun", "run"):
        expect(page.locator(f"#steps li[data-step={step}]")).not_to_have_class(re.compile("done"))
    banner = page.locator("#plan-summary .outdated")
    expect(banner).to_contain_text("Outdated: made before the trace")
    expect(page.locator("#reconstruct-summary .outdated")).to_contain_text("the trace")
    expect(page.locator("#step-plan .needs")).to_contain_text("Reconstruct and plan again")
    expect(page.locator("#step-run .needs")).to_contain_text("The plan is outdated")
    expect(run).to_be_disabled()
    pendant.shot("outdated-plan")
    # Reconstructing the new trace makes that step current again.
    page.get_by_role("button", name="Reconstruct").click()
    expect(page.locator("#reconstruct-form .job-state")).to_have_text(
        "succeeded 100 %", timeout=90_000
    )
    expect(page.locator("#reconstruct-summary .outdated")).to_have_count(0)
    expect(page.locator("#steps li[data-step=reconstruct]")).to_have_class("done")
    # The old plan is not the new reconstruction's: the plan step asks for a new one.
    expect(page.locator("#step-plan .needs")).to_contain_text("press Plan")
    expect(page.locator("#plan-summary .outdated")).to_have_count(0)
    expect(run).to_be_disabled()
    # The demo session is shared by the other tests: its own trace is the current one again.
    restored = client.put(
        f"/sessions/{sid}/recording", files={"file": ("demo_trace.csv", demo_csv)}
    )
    assert restored.status_code == 201, restored.text


def test_a_reload_finds_the_running_dry_run_again_and_sends_nothing(pendant):
    page = pendant.page
    posts = []
    page.on("request", lambda r: posts.append(r.url) if r.method == "POST" else None)
    pendant.open()
    page.get_by_role("button", name="demo", exact=True).click()
    page.get_by_role("button", name="Reconstruct").click()
    expect(page.locator("#reconstruct-form .job-state")).to_have_text(
        "succeeded 100 %", timeout=90_000
    )
    # Slow, so that the dry run (simulated in real time) outlasts the reload by far.
    page.locator("#plan-speed").fill("0.01")
    page.get_by_role("button", name="Plan", exact=True).click()
    expect(page.locator("#plan-form .job-state")).to_have_text("succeeded 100 %", timeout=60_000)
    dry = page.get_by_role("button", name="Dry run")
    dry.click()
    expect(page.locator("#dryrun-form .job-state")).to_contain_text("running")
    sent = len(posts)
    page.reload()
    page.wait_for_selector("body[data-ready=true]")
    # The session is open again and its dry run followed to its end, its button held meanwhile.
    expect(page.locator("#session-title")).to_have_text("Session demo")
    expect(page.locator("#dryrun-form .job-state")).to_contain_text("running")
    expect(dry).to_be_disabled()
    expect(page.locator("#steps li[data-step=dryrun]")).to_have_class(re.compile("running"))
    pendant.shot("reloaded-while-running")
    expect(page.locator("#dryrun-form .job-state")).to_have_text("succeeded 100 %", timeout=60_000)
    expect(page.locator("#dryrun-summary")).to_contain_text("passed")
    expect(dry).to_be_enabled()
    assert len(posts) == sent, posts[sent:]  # nothing was sent again

    # A dry run stopped while it runs (from another screen, or the API) says so; the table
    # beside it is still the earlier, finished one (of the other mode: none here).
    # A job shows "running" from the moment the pool owns it; on a loaded machine the stop can
    # still reach it before a worker process has taken it, and then the page says (truly) that
    # it was cancelled before it started. Try again until a worker had it: the stop of a dry
    # run that ran must say so.
    page.locator("#exec-mode").select_option("movepath")
    client = pendant.server.client
    sid = page.evaluate("sessionStorage.getItem('teachpath.session')")
    message = page.locator("#dryrun-form .message")
    for _attempt in range(3):
        dry.click()
        expect(page.locator("#dryrun-form .job-state")).to_contain_text("running")
        running = [
            j
            for j in client.get(f"/sessions/{sid}/jobs").json()
            if j["kind"] == "execution" and j["state"] == "running"
        ]
        assert len(running) == 1, running
        stopped = client.post(f"/executions/{running[0]['params']['execution_id']}/stop")
        assert stopped.status_code == 200, stopped.text
        expect(message).to_contain_text(
            re.compile("stopped on request while it ran|cancelled before it started"),
            timeout=60_000,
        )
        expect(dry).to_be_enabled()
        if "before it started" not in message.inner_text():
            break
    expect(message).to_contain_text("stopped on request while it ran")
    expect(message).not_to_contain_text("before it started")
    # Its instruction is the dry run's, not the arm's (nothing moved).
    expect(message).to_contain_text("nothing moved and it did not pass")
    expect(message).not_to_contain_text("the arm stands where it stopped")
    page.locator("#exec-mode").select_option("servoj")

    # A second reconstruction with another radius: the two side by side, the newest in bold.
    page.locator("#recon-radius_m").fill("12")
    page.get_by_role("button", name="Reconstruct").click()
    expect(page.locator("#reconstruct-form .job-state")).to_have_text(
        "succeeded 100 %", timeout=90_000
    )
    compared = page.locator("table.comparison tr[data-reconstruction]")
    expect(compared.last).to_contain_text("12.0 mm")
    expect(compared.last).to_have_class("current")
    assert compared.count() >= 2
    expect(page.locator("table.comparison")).to_contain_text("8.0 mm")
    pendant.shot("comparison")


def test_the_high_contrast_theme_is_switched_on_and_kept(pendant):
    page = pendant.page
    pendant.open()
    body = page.locator("body")
    background = "getComputedStyle(document.body).backgroundColor"
    assert page.evaluate(background) == "rgb(255, 255, 255)"
    page.get_by_label("High contrast").check()
    expect(body).to_have_class(re.compile("contrast"))
    assert page.evaluate(background) == "rgb(0, 0, 0)"
    assert page.evaluate("getComputedStyle(document.body).color") == "rgb(255, 255, 255)"
    page.get_by_role("button", name="demo", exact=True).click()
    pendant.shot("high-contrast")
    page.reload()
    page.wait_for_selector("body[data-ready=true]")
    expect(body).to_have_class(re.compile("contrast"))
    expect(page.get_by_label("High contrast")).to_be_checked()
    page.get_by_label("High contrast").uncheck()
    assert page.evaluate(background) == "rgb(255, 255, 255)"


def test_the_calibration_panel_fits_pairs_and_the_tip_and_refuses_poor_fits(pendant, tmp_path):
    import numpy as np

    from recon.inputs import Recording
    from tests.recon.test_calibrate import pivot_recording
    from tests.service.test_api_inputs import _csv

    page = pendant.page
    pendant.guard.allow(422, "/calibration/")
    pendant.open()
    pendant.create_session("calibration bench")
    current = page.locator("#calibration-current")
    # One line per calibration the session and the cell use.
    expect(current.locator("tr", has_text="tracker → base")).to_contain_text("not calibrated")
    expect(current.locator("tr", has_text="tracker → scan")).to_contain_text("no first guess")
    expect(current.locator("tr", has_text="pen tip")).to_contain_text("not calibrated")
    expect(current.locator("tr", has_text="touches")).to_contain_text("none")
    expect(current.locator("tr", has_text="arm")).to_contain_text("ur5e: UR's nominal kinematics")
    expect(current.locator("tr", has_text="cell")).to_contain_text("0 keep-out boxes, 0 planes")

    # Five points touched with the robot (base) and the pen (tracker), in mm; the tracker
    # sits 450, 100, 50 mm from the base, axes aligned.
    base_mm = np.array([[400, 0, 0], [500, 0, 0], [450, 80, 0], [450, 0, 90], [520, 60, 40]])
    lines = [
        f"{b[0]} {b[1]} {b[2]}, {t[0]} {t[1]} {t[2]}"
        for b, t in zip(base_mm, base_mm - [450, 100, 50], strict=True)
    ]
    pairs = page.get_by_label("Pairs, one per line")
    pairs.fill("1 2 3, 4 5\n" + "\n".join(lines))
    page.get_by_role("button", name="Fit tracker → base").click()
    message = page.locator("#pairs-form .message")
    expect(message).to_contain_text("line 1: “1 2 3, 4 5” is not six numbers")
    pairs.fill("\n".join(lines))
    page.get_by_role("button", name="Fit tracker → base").click()
    summary = page.locator("#pairs-summary")
    expect(summary.locator("table.pairs tr")).to_have_count(6)  # a header and five pairs
    expect(summary).to_contain_text("RMS of the pairs used0.000 mm")
    base_line = current.locator("tr", has_text="tracker → base")
    expect(base_line).to_contain_text("translation (450.0, 100.0, 50.0) mm, turned 0.0°")
    expect(base_line).to_contain_text("(point pairs, ")
    expect(page.locator("#steps li[data-step=calibration]")).to_have_class("done")
    pendant.shot("pairs-fitted")

    # Tracker points at twice the scale (a units slip): refused with the figures, nothing stored.
    scaled = [
        f"{b[0]} {b[1]} {b[2]}, {2 * t[0]} {2 * t[1]} {2 * t[2]}"
        for b, t in zip(base_mm, base_mm - [450, 100, 50], strict=True)
    ]
    pairs.fill("\n".join(scaled))
    page.get_by_role("button", name="Fit tracker → base").click()
    expect(message).to_have_attribute("data-code", "poor_fit")
    expect(message).to_contain_text("was not stored")
    expect(summary.locator("tr.suspect")).to_have_count(5)
    expect(base_line).to_contain_text("translation (450.0, 100.0, 50.0) mm")
    pendant.shot("pairs-refused")

    # The pen's tip from a pivoting recording; a pivot whose tip slid is refused with its RMS.
    position, quat = pivot_recording(0)
    good = tmp_path / "pivot.csv"
    good.write_bytes(
        _csv(
            Recording(
                points_m=position, t_s=np.arange(len(position)) / 240.0, orientations_xyzw=quat
            )
        )
    )
    page.locator("#pivot-form input[type=file]").set_input_files(str(good))
    page.get_by_role("button", name="Calibrate tip").click()
    pivot = page.locator("#pivot-summary")
    expect(pivot).to_contain_text("tip offset")
    expect(pivot).to_contain_text("RMS")
    expect(current.locator("tr", has_text="pen tip")).to_contain_text("(pivoting, ")
    position, quat = pivot_recording(0, position_noise_m=3e-3)
    slid = tmp_path / "slid.csv"
    slid.write_bytes(
        _csv(
            Recording(
                points_m=position, t_s=np.arange(len(position)) / 240.0, orientations_xyzw=quat
            )
        )
    )
    page.locator("#pivot-form input[type=file]").set_input_files(str(slid))
    page.get_by_role("button", name="Calibrate tip").click()
    expect(page.locator("#pivot-form .message")).to_have_attribute("data-code", "poor_fit")
    expect(pivot).to_contain_text("RMS (tolerance 1.000 mm)")
    pendant.shot("pivot-refused")

    # A stored calibration file, as `teachpath calibrate base` writes it: loaded and named.
    from drivers.calibration import write_calibration

    T = np.eye(4)
    T[:3, 3] = [0.3, -0.2, 0.1]
    T[:2, :2] = [[0.0, -1.0], [1.0, 0.0]]  # turned 90 degrees about z
    stored = tmp_path / "T_base_tracker.json"
    write_calibration(stored, "T_base_tracker", T)
    page.locator("#calfile-form input[type=file]").set_input_files(str(stored))
    page.get_by_role("button", name="Load calibration").click()
    expect(page.locator("#calfile-form .message")).to_have_text("Loaded T_base_tracker.json.")
    expect(base_line).to_contain_text("translation (300.0, -200.0, 100.0) mm, turned 90.0°")
    expect(base_line).to_contain_text("(file T_base_tracker.json, ")
    # A file that is not a calibration: refused, saying why; nothing changes.
    wrong = tmp_path / "T_scan_sensor.json"
    write_calibration(wrong, "T_scan_sensor", T)
    page.locator("#calfile-form input[type=file]").set_input_files(str(wrong))
    page.get_by_role("button", name="Load calibration").click()
    message = page.locator("#calfile-form .message")
    expect(message).to_have_attribute("data-code", "invalid_file")
    expect(message).to_contain_text("holds T_scan_sensor; a session takes T_base_tracker")
    expect(base_line).to_contain_text("turned 90.0°")
    # Another session's calibration (the demo's: the same cell), chosen by its name.
    demo = next(x for x in pendant.server.client.get("/sessions").json() if x["name"] == "demo")
    page.locator("#copycal-form select").select_option(value=demo["id"])
    page.get_by_role("button", name="Use its calibration").click()
    expect(page.locator("#copycal-form .message")).to_contain_text("of “demo” set")
    shift = np.array(demo["T_base_tracker"])[:3, 3] * 1000
    expect(base_line).to_contain_text(f"translation ({', '.join(f'{v:.1f}' for v in shift)}) mm")
    pendant.shot("calibration-lines")


def _every_download_is_the_servers_file(pendant, box: str, collection: str, count: int) -> None:
    """Click each "Download" button of the artifact shown in ``box``: each file saved is the
    server's (the plan's requested ``/trajectorys/...``: 404, shown as a failed download)."""
    page = pendant.page
    details = page.locator(f"{box} details.provenance")
    details.locator("summary").click()
    artifact_id = details.get_attribute("data-artifact")
    sid = page.evaluate("sessionStorage.getItem('teachpath.session')")
    buttons = details.get_by_role("button", name=re.compile("^Download "))
    expect(buttons).to_have_count(count)
    suffixes = {"csv": "csv", "script": "urscript", "png": "plot.png", "ply": "ply"}
    with tempfile.TemporaryDirectory() as folder:
        for index in range(count):
            with page.expect_download() as info:
                buttons.nth(index).click()
            download = info.value
            name = download.suggested_filename
            assert name.startswith(artifact_id), name
            saved = Path(folder) / name
            download.save_as(saved)
            suffix = suffixes[name.rsplit(".", 1)[1]]
            served = pendant.server.client.get(
                f"/sessions/{sid}/{collection}/{artifact_id}/{suffix}"
            )
            assert served.status_code == 200 and len(served.content) > 100
            assert saved.read_bytes() == served.content, name
    expect(details.locator(".download-error")).to_be_empty()


def test_provenance_and_downloads_of_the_stored_files(pendant, scene_files, tmp_path):
    import hashlib

    page = pendant.page
    pendant.open()
    pendant.create_session("files")
    trace = tmp_path / "trace.csv"
    trace.write_bytes(scene_files["trace"])
    page.locator("#recording-form input[type=file]").set_input_files(str(trace))
    page.get_by_role("button", name="Upload recording").click()
    details = page.locator("#recording-files details.provenance")
    expect(details).to_be_visible()
    details.locator("summary").click()
    expect(details).to_contain_text("uploaded astrace.csv")
    expect(details).to_contain_text('"units"')
    artifact_id = details.get_attribute("data-artifact")
    sid = page.evaluate("sessionStorage.getItem('teachpath.session')")
    row = pendant.server.client.get(f"/sessions/{sid}/recordings/{artifact_id}").json()
    expect(details).to_contain_text(row["sha256"])
    with page.expect_download() as info:
        details.get_by_role("button", name="Download trace CSV").click()
    download = info.value
    assert download.suggested_filename == f"{artifact_id}.csv"
    saved = tmp_path / "downloaded.csv"
    download.save_as(saved)
    served = pendant.server.client.get(
        f"/sessions/{row['session_id']}/recordings/{artifact_id}/csv"
    )
    assert saved.read_bytes() == served.content and served.content.startswith(b"t,x,y,z")
    assert (
        hashlib.sha256(saved.read_bytes()).hexdigest() == hashlib.sha256(served.content).hexdigest()
    )
    expect(details).to_have_attribute("open", "")  # still open after the page redrew its steps
    pendant.shot("provenance")


def test_the_pendant_works_where_the_browser_refuses_site_storage(pendant):
    page = pendant.page
    # As a browser with site data blocked: reading either storage throws.
    page.add_init_script(
        """for (const name of ['sessionStorage', 'localStorage']) {
             Object.defineProperty(window, name, {get() {
               throw new DOMException('The operation is insecure.', 'SecurityError'); }});
           }"""
    )
    pendant.open()
    assert "token" not in page.url  # still taken out of the address bar, kept in the page
    expect(page.locator("#link-state")).to_have_text("live")
    page.get_by_role("button", name="demo", exact=True).click()
    expect(page.locator("#session-title")).to_have_text("Session demo")
    page.get_by_label("High contrast").check()
    expect(page.locator("body")).to_have_class(re.compile("contrast"))


def test_touches_are_uploaded_in_the_calibration_panel_and_place_the_scan(pendant, scene_files):
    """The operator uploads touches of the workpiece: a file with too few rests is refused
    inline, a good one is listed touch by touch, and the next reconstruction says the scan was
    placed by them (and can be told not to)."""
    from drivers.tracking.canonical_csv import write_trace_csv
    from recon import scenes

    page = pendant.page
    pendant.guard.allow(422, "/touches")
    pendant.open()
    pendant.create_session("touches")
    for form, name, data in (
        ("#recording-form", "trace.csv", scene_files["trace"]),
        ("#scan-form", "scan.ply", scene_files["scan"]),
    ):
        page.locator(form).get_by_label("File", exact=True).set_input_files(
            {"name": name, "mimeType": "application/octet-stream", "buffer": data}
        )
        page.locator(form).get_by_role("button", name=re.compile("^Upload")).click()
        expect(page.locator(form).locator(".message")).to_have_text(f"{name} uploaded.")

    touches = page.locator("#touches-form")
    # Two rests, a move between: one rest short of fixing anything.
    x = [0.02] * 120 + [0.02 + 0.001 * k for k in range(1, 40)] + [0.06] * 120
    still = "t,x,y,z\n" + "".join(f"{k / 120:.4f},{v},0.02,0\n" for k, v in enumerate(x))
    touches.get_by_label("Recording of the touches").set_input_files(
        {"name": "still.csv", "mimeType": "text/csv", "buffer": still.encode()}
    )
    touches.get_by_role("button", name="Upload touches").click()
    expect(touches.locator(".message")).to_contain_text("at least 3 are needed")
    expect(page.locator("#touches-summary")).to_be_empty()

    recording = scenes.touch_recording(scenes.box_corner(0), 0).recording
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "touches.csv"
        write_trace_csv(path, recording)
        content = path.read_bytes()
    touches.get_by_label("Recording of the touches").set_input_files(
        {"name": "touches.csv", "mimeType": "text/csv", "buffer": content}
    )
    touches.get_by_role("button", name="Upload touches").click()
    expect(touches.locator(".message")).to_have_text("touches.csv uploaded.")
    summary = page.locator("#touches-summary")
    expect(summary).to_contain_text("6 rests found in touches.csv")
    expect(summary).to_contain_text("touch 6")
    # The touched points are drawn in the 3-D view, where the calibration puts them.
    expect(page.locator("#calibration-current tr", has_text="touches")).to_contain_text(
        "6 points touched (touches.csv)"
    )
    page.wait_for_function(
        "() => document.querySelector('#workspace').workspace.layers.touches"
        "?.geometry.drawRange.count === 6"
    )
    pendant.shot("touches")

    page.get_by_role("button", name="Reconstruct").click()
    result = page.locator("#reconstruct-summary")
    expect(result).to_contain_text("by 6 touches of the workpiece", timeout=90_000)
    expect(result).to_contain_text("motions the touches fixed")
    pendant.shot("reconstructed-by-touches")
    page.locator("#reconstruct-params").get_by_label("use the touches").uncheck()
    page.get_by_role("button", name="Reconstruct").click()
    expect(result).to_contain_text("to the scan's edge", timeout=90_000)


def test_a_second_screen_without_the_start_url_shows_the_arm_and_signs_in(
    pendant, browser, screens
):
    """A new tab or a restarted browser has no ?token= address. It shows the safety bar live at
    once (and would show Stop); it is offered a sign-in by a pairing code that a signed-in
    screen makes, or by the token. A wrong code or token is said so and asked again."""
    page = pendant.page
    pendant.guard.allow(401, "/")
    page.goto(pendant.server.url + "/")
    page.wait_for_selector("body[data-ready=true]")
    form = page.locator("#sign-in")
    expect(form).to_be_visible()
    expect(page.locator("#banner")).to_contain_text("type a pairing code or paste the access token")
    # The safety state needs no sign-in.
    expect(page.locator("#link-state")).to_have_text("live")
    expect(page.locator("#arm-kind")).to_have_text("SIM")
    pendant.shot("sign-in")
    # A wrong token: asked again.
    page.get_by_label(re.compile("^or the access token")).fill("not-the-token")
    page.get_by_role("button", name="Sign in").click()
    page.wait_for_selector("body[data-ready=true]")
    expect(form).to_be_visible()
    assert "token" not in page.url
    # A pairing code, made on a signed-in screen ("Pair a screen").
    with pendant_for(browser, pendant.server, screens, "pairing-first-screen") as first:
        first.open()
        first.page.get_by_role("button", name="Pair a screen").click()
        shown = first.page.locator("#pairing-code")
        expect(shown).to_contain_text("type it on the other screen before")
        code = shown.get_attribute("data-code")
        first.shot("code")
    assert code and re.fullmatch(r"[0-9]{6}", code)
    wrong = f"{(int(code) + 1) % 10**6:06d}"
    code_field = page.get_by_label(re.compile("^Pairing code"))
    code_field.fill(wrong)
    page.get_by_role("button", name="Sign in").click()
    expect(page.locator("#sign-in-message")).to_contain_text("wrong code (4 tries left)")
    code_field.fill(code)
    page.get_by_role("button", name="Sign in").click()
    page.wait_for_selector("body[data-ready=true]")
    expect(form).to_be_hidden()
    expect(page.locator("#link-state")).to_have_text("live")
    assert "token" not in page.url  # taken out of the address bar, as the printed URL's is
    expect(page.get_by_role("button", name="demo", exact=True)).to_be_visible()
    pendant.shot("paired")
    # The code worked once; the token too signs a screen in.
    page.evaluate("sessionStorage.clear()")
    page.goto(pendant.server.url + "/")
    page.wait_for_selector("body[data-ready=true]")
    page.get_by_label(re.compile("^or the access token")).fill(TOKEN)
    page.get_by_role("button", name="Sign in").click()
    page.wait_for_selector("body[data-ready=true]")
    expect(form).to_be_hidden()
    expect(page.get_by_role("button", name="demo", exact=True)).to_be_visible()


def test_a_jobs_progress_never_goes_back_on_the_page(pendant):
    """Events and polls can arrive out of order (a stream that broke, then a poll answered
    from an older state): the bar and its label keep the largest progress seen."""
    import json

    page = pendant.page
    pendant.open()
    page.get_by_role("button", name="demo", exact=True).click()

    def events(route):
        job_id = route.request.url.split("/jobs/")[1].split("/")[0]
        body = "".join(
            f"event: job\ndata: {json.dumps({'id': job_id, 'state': 'running', 'progress': p})}\n\n"
            for p in (0.6, 0.3)
        )
        route.fulfill(status=200, headers={"Content-Type": "text/event-stream"}, body=body)

    polls = []

    def poll(route):
        response = route.fetch()
        job = response.json()
        if len(polls) < 3:  # the first polls answer from an older state
            job = {**job, "state": "running", "progress": 0.1}
        polls.append(job["progress"])
        route.fulfill(response=response, json=job)

    page.route("**/jobs/*/events", events)
    page.route(re.compile(r".*/jobs/[^/]+$"), poll)
    page.get_by_role("button", name="Reconstruct").click()
    label = page.locator("#reconstruct-form .job-state")
    expect(label).to_have_text("running 60 %")
    deadline = 100
    while len(polls) < 3 and deadline:
        page.wait_for_timeout(200)
        deadline -= 1
    assert polls[:3] == [0.1, 0.1, 0.1]
    expect(label).to_have_text("running 60 %")  # not 30 %, not 10 %
    assert page.locator("#reconstruct-form progress").evaluate("bar => bar.value") == 0.6
    page.unroute("**/jobs/*/events")
    expect(label).to_have_text("succeeded 100 %", timeout=90_000)
