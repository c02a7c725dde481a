"""The pendant in a real browser: Debian's chromium driven by Playwright, against the real server
(``teachpath serve --demo`` on 127.0.0.1 with a temporary data dir).

Every page a test opens goes through :class:`Guard`: each request is intercepted and refused
unless it goes to a loopback address, and at the end the test fails on any such request, any
console error, uncaught exception or Content-Security-Policy violation.
A missing browser or Playwright fails the tests (never skips them): ``scripts/setup.sh``
installs both.
"""

from __future__ import annotations

import contextlib
import ipaddress
import os
import re
import shutil
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import urlsplit

import pytest

from tests.server_process import Server
from tests.service.conftest import scene_files  # noqa: F401 - shared fixture

TOKEN = "ui-token-abcdefghijklmnopqrstuv"
SETUP = "run scripts/setup.sh (make setup)"
#: Debian's chromium: headless, as root, WebGL through SwiftShader, nothing fetched by itself.
CHROMIUM_ARGS = [
    "--no-sandbox",
    "--headless=new",
    "--enable-unsafe-swiftshader",
    "--use-angle=swiftshader",
    "--use-gl=angle",
    "--ignore-gpu-blocklist",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-default-apps",
    "--disable-domain-reliability",
    "--disable-sync",
    "--disable-extensions",
    "--no-first-run",
    "--no-default-browser-check",
    "--metrics-recording-only",
    "--disable-features=Translate,OptimizationHints,MediaRouter,AutofillServerCommunication",
    "--no-pings",
    "--dns-prefetch-disable",
]


def chromium_path() -> str:
    path = os.environ.get("TEACHPATH_CHROMIUM") or shutil.which("chromium")
    if not path:
        pytest.fail(
            f"Debian's chromium is missing: {SETUP}, which installs it with apt-get "
            "(or set TEACHPATH_CHROMIUM to a Chromium binary)"
        )
    return path


@pytest.fixture(scope="session")
def server(tmp_path_factory):
    server = Server(tmp_path_factory.mktemp("ui-data"), token=TOKEN, demo=True, timeout_s=30)
    yield server
    server.stop()


@pytest.fixture(scope="session")
def browser():
    from playwright.sync_api import expect

    # Two shared cores: a page may take a while to render while a job runs beside it.
    expect.set_options(timeout=15_000)
    executable = chromium_path()
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        pytest.fail(f"Playwright for Python is missing: {SETUP} (it is in the dev extra)")
    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(
            executable_path=executable, args=CHROMIUM_ARGS, headless=True
        )
        yield browser
        browser.close()


def loopback(url: str) -> bool:
    parts = urlsplit(url)
    if parts.scheme in ("data", "blob", "about"):
        return True
    host = parts.hostname or ""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


class Guard:
    """What a page did that it must not: requests off this machine, console errors, exceptions,
    CSP violations."""

    def __init__(self, context, page) -> None:
        self.external: list[str] = []
        self.console_errors: list[str] = []
        self.page_errors: list[str] = []
        self.requests: list[str] = []
        self.allowed: list[tuple[int, str]] = []
        context.route("**/*", self._route)
        page.on("console", self._console)
        page.on("pageerror", lambda error: self.page_errors.append(str(error)))
        # Runs before the page's scripts, outside its CSP: collects the violations it reports.
        page.add_init_script(
            "window.__csp = [];"
            "document.addEventListener('securitypolicyviolation', (e) => window.__csp.push("
            "e.violatedDirective + ' ' + e.blockedURI + ' ' + e.sourceFile + ':' + e.lineNumber));"
        )
        self.page = page

    def _route(self, route) -> None:
        url = route.request.url
        self.requests.append(url)
        if loopback(url):
            route.continue_()
        else:
            self.external.append(url)
            route.abort()

    def allow(self, status: int, url_part: str) -> None:
        """An error answer the test provokes (Chrome logs each on the console)."""
        self.allowed.append((status, url_part))

    def _console(self, message) -> None:
        if message.type != "error":
            return
        answered = re.match(r"Failed to load resource: .* status of (\d+)", message.text)
        url = message.location.get("url", "")
        if answered and any(
            int(answered.group(1)) == status and part in url for status, part in self.allowed
        ):
            return
        self.console_errors.append(f"{message.text} ({message.location})")

    def csp_violations(self) -> list[str]:
        try:
            return self.page.evaluate("window.__csp || []")
        except Exception:  # the page is gone: its violations were reported on the console too
            return []

    def check(self) -> None:
        assert not self.external, f"requests off this machine: {self.external}"
        assert not self.page_errors, f"uncaught exceptions: {self.page_errors}"
        violations = self.csp_violations()
        assert not violations, f"Content-Security-Policy violations: {violations}"
        assert not self.console_errors, f"console errors: {self.console_errors}"


@dataclass
class Pendant:
    page: object
    guard: Guard
    server: Server
    shot: object

    def open(self) -> None:
        """Open the start-up URL (with the token) and wait until the page has loaded."""
        self.page.goto(self.server.start_url)
        self.page.wait_for_selector("body[data-ready=true]")

    def create_session(self, name: str) -> None:
        """Type a session's name and press Create, as an operator does (it opens the session)."""
        self.page.get_by_label("Session name").fill(name)
        self.page.get_by_role("button", name="Create").click()


@pytest.fixture(scope="session")
def screens(tmp_path_factory) -> Path:
    """Where the tests write their screenshots (one per step)."""
    folder = tmp_path_factory.mktemp("screens")
    print(f"\nscreenshots: {folder}")
    return folder


@contextlib.contextmanager
def pendant_for(
    browser, server: Server, screens: Path, name: str, **context_options
) -> Iterator[Pendant]:
    """A fresh browser context and page on ``server``, guarded (checked when it closes);
    ``pendant.shot(step)`` saves a screenshot named after ``name``. ``context_options`` go to
    the context (``has_touch=True``: a touch screen)."""
    context = browser.new_context(viewport={"width": 1500, "height": 1100}, **context_options)
    context.set_default_timeout(30_000)
    page = context.new_page()
    guard = Guard(context, page)

    def shot(step: str) -> Path:
        path = screens / f"{name}-{step}.png"
        # From the top: a full-page picture of a scrolled page repeats the sticky safety bar.
        page.evaluate("() => window.scrollTo(0, 0)")
        page.screenshot(path=str(path), full_page=True)
        return path

    try:
        yield Pendant(page=page, guard=guard, server=server, shot=shot)
        guard.check()
    finally:
        context.close()


@pytest.fixture
def pendant(browser, server, screens, request):
    """The pendant on the simulated arm's server (see :func:`pendant_for`)."""
    with pendant_for(browser, server, screens, request.node.name) as opened:
        yield opened


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    """A failed test on a server started here gets the server's last log lines, and the fake
    controller's, in its report: what the arm did is often the reason a page did not show it."""
    outcome = yield
    report = outcome.get_result()
    if report.when != "call" or not report.failed:
        return
    funcargs = getattr(item, "funcargs", {})
    for name in ("arm_server", "server"):
        server = funcargs.get(name)
        if server is not None and getattr(server, "output", None):
            report.sections.append((f"{name} log (last 60 lines)", "".join(server.output[-60:])))
    fake = funcargs.get("fake_ur_process")
    if fake is not None:
        lines = fake.log_text().splitlines()[-60:]
        report.sections.append(("fake UR log (last 60 lines)", "\n".join(lines)))
