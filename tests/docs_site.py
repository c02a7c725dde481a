"""Building the documentation site for the tests, as `make docs` does."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
MERMAID = ROOT / "service" / "ui" / "vendor" / "mermaid" / "mermaid.min.js"


def build_site(out: Path) -> Path:
    """The site built strictly into ``out`` (a broken link or reference fails), with the
    diagrams' script copied in."""
    built = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--quiet", "-d", str(out)],
        cwd=ROOT,
        env={**os.environ, "NO_MKDOCS_2_WARNING": "1"},
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert built.returncode == 0, built.stderr[-4000:]
    if not MERMAID.is_file():
        pytest.fail(f"{MERMAID} is missing: run scripts/setup.sh (make setup), which copies it")
    (out / "js").mkdir(exist_ok=True)
    shutil.copy(MERMAID, out / "js" / "mermaid.min.js")
    return out
