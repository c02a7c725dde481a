"""The documentation: the site builds with strict warnings (no broken link or reference), the
Python examples and the README's code run as written, and the service serves the site at
/guide with its own files only."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from tests.docs_site import build_site
from tests.server_process import Server
from tests.service.conftest import AUTH, make_settings

ROOT = Path(__file__).resolve().parents[1]
EXAMPLES = ROOT / "docs" / "examples"

pytestmark = pytest.mark.timeout(600)


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> Path:
    """The site as `make docs` builds it (strict), with the diagrams' script."""
    return build_site(tmp_path_factory.mktemp("site"))


def test_the_site_has_every_guide_the_api_reference_and_nothing_from_the_network(site):
    for page in (
        "index.html",
        "getting-started.html",
        "operator-guide.html",
        "guides/inputs.html",
        "guides/reconstruction.html",
        "guides/motion.html",
        "guides/service.html",
        "guides/replay.html",
        "examples.html",
        "accuracy.html",
        "real-parts.html",
        "speed.html",
        "architecture.html",
        "reference/recon.html",
    ):
        assert (site / page).is_file(), page
    reference = (site / "reference" / "recon.html").read_text()
    assert "ReconParams" in reference and "ndarray of shape (N, 3)" in reference
    architecture = (site / "architecture.html").read_text()
    assert architecture.count('class="mermaid"') == 2
    for html in site.rglob("*.html"):
        text = html.read_text()
        # Nothing loaded from elsewhere: scripts, styles, fonts, images are this site's.
        loaded = re.findall(r'(?:src|href)="(https?://[^"]+)"', text)
        assert all(not re.search(r"\.(js|css|woff2?|png|svg)(\?|$)", url) for url in loaded), (
            html,
            loaded,
        )
        assert "fonts.googleapis" not in text, html


def test_the_readme_links_to_files_that_exist():
    text = (ROOT / "README.md").read_text()
    links = re.findall(r"\]\(((?!https?:)[^)#]+)", text)
    assert links
    for link in links:
        assert (ROOT / link).exists(), link
    assert len(text.splitlines()) <= 160, "the README grows: put the long part into docs/"


@pytest.mark.parametrize("example", ["reconstruct_a_trace.py", "plan_and_dry_run.py"])
def test_a_python_example_runs_as_written(example, tmp_path):
    done = subprocess.run(
        [sys.executable, str(EXAMPLES / example)],
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": str(ROOT)},
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    if example == "reconstruct_a_trace.py":
        numbers = dict(re.findall(r"(trace|reconstruction): mean [\d.]+ mm, max ([\d.]+) mm",
                                  done.stdout))  # fmt: skip
        assert float(numbers["reconstruction"]) < float(numbers["trace"]), done.stdout
    else:
        assert "tool axis from the scan" in done.stdout and done.stdout.rstrip().endswith("passed")


def test_the_readmes_python_block_runs():
    text = (ROOT / "README.md").read_text()
    block = re.search(r"```python\n(.*?)```", text, re.S).group(1)
    exec(compile(block, "README.md", "exec"), {})


def test_the_rest_example_drives_a_running_service(tmp_path):
    files = tmp_path / "demo_files"
    made = subprocess.run(
        [sys.executable, "-m", "service.cli", "demo", "--out-dir", str(files)],
        capture_output=True,
        text=True,
        timeout=240,
    )
    assert made.returncode == 0, made.stderr
    server = Server(tmp_path / "data", token="t" * 32)
    try:
        done = subprocess.run(
            [sys.executable, str(EXAMPLES / "rest_from_python.py")],
            cwd=tmp_path,
            env={
                **os.environ,
                "PYTHONPATH": str(ROOT),
                "TEACHPATH_URL": server.url,
                "TEACHPATH_TOKEN": server.token,
                "TEACHPATH_DEMO_FILES": str(files),
            },
            capture_output=True,
            text=True,
            timeout=400,
        )
        assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-3000:]
        assert "dry run: completed True, faults []" in done.stdout
        assert [s["name"] for s in server.client.get("/sessions").json()] == ["from python"]
    finally:
        server.stop()


def test_the_service_serves_the_site_at_guide(site, tmp_path):
    with TestClient(create_app(make_settings(tmp_path, guide_dir=site)), headers=AUTH) as client:
        home = client.get("/guide/", headers={"Authorization": ""})  # no token needed to read
        assert home.status_code == 200 and "teachpath" in home.text
        assert "default-src 'self'" in home.headers["content-security-policy"]
        page = client.get("/guide/architecture.html")
        assert page.status_code == 200 and "Module map" in page.text
        assert client.get("/guide/js/mermaid.min.js").status_code == 200
        assert client.get("/guide/../pyproject.toml").status_code == 404
        assert client.get("/guide/nothing-here.html").status_code == 404


def test_a_service_without_the_built_site_says_how_to_build_it(tmp_path):
    settings = make_settings(tmp_path, guide_dir=tmp_path / "no-site")
    with TestClient(create_app(settings), headers=AUTH) as client:
        missing = client.get("/guide/")
        assert missing.status_code == 404 and "make docs" in missing.text
