"""The optional extras: the core install runs the service with the simulated arm, and each
feature whose extra is missing says which extra to install.

A second environment per extra would take minutes to build; instead a child interpreter hides
the extras' modules (an import of them fails as it does where they are not installed) and runs
what a user of the core install would.
"""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

#: The extras' top-level modules, as pyproject.toml groups them.
EXTRA_MODULES = {
    "ur": ["rtde_control", "rtde_receive", "dashboard_client", "rtde_io"],
    "natnet": ["natnet"],
    "c3d": ["ezc3d"],
    "e57": ["pye57"],
    "replay": ["dask", "distributed"],
    "postgres": ["psycopg", "psycopg_binary"],
}

#: Installed as ``sitecustomize`` on the child's path: it hides the modules named in
#: TEACHPATH_TEST_HIDE from that interpreter and from every process it spawns (the ur_rtde
#: worker imports ur_rtde in a process of its own).
HIDE = textwrap.dedent(
    """
    import importlib.abc, os, sys
    HIDDEN = set(filter(None, os.environ.get("TEACHPATH_TEST_HIDE", "").split(",")))

    class Hide(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path=None, target=None):
            if name.split(".")[0] in HIDDEN:
                raise ModuleNotFoundError(f"No module named {name!r}", name=name)
            return None

    sys.meta_path.insert(0, Hide())
    """
)


def _run_without(hidden: list[str], body: str, tmp_path: Path) -> dict:
    """Run ``body`` (which prints one JSON line last) with ``hidden`` modules not importable."""
    site = tmp_path / "site"
    site.mkdir(exist_ok=True)
    (site / "sitecustomize.py").write_text(HIDE)
    done = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(body)],
        cwd=tmp_path,
        env={
            "PYTHONPATH": f"{site}:{ROOT}",
            "TEACHPATH_TEST_HIDE": ",".join(hidden),
            "PATH": "/usr/bin:/bin",
            "HOME": str(tmp_path),
        },
        capture_output=True,
        text=True,
        timeout=240,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(done.stdout.strip().splitlines()[-1])


def test_the_extras_are_declared_with_their_pins_and_all_gathers_them():
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    extras = project["optional-dependencies"]
    core = " ".join(project["dependencies"])
    for extra in EXTRA_MODULES:
        assert extra in extras, extra
        for requirement in extras[extra]:
            name = requirement.split("[")[0].split("=")[0].split(">")[0].split("<")[0]
            assert name not in core, f"{name} is both core and in [{extra}]"
    assert extras["ur"] == ["ur-rtde==1.6.5"] and extras["natnet"] == ["natnet==0.3.0"]
    assert extras["all"] == ["teachpath[ur,natnet,c3d,e57,replay,postgres]"]
    for package in ("recon", "drivers", "service"):
        assert (ROOT / package / "py.typed").is_file()


def test_the_core_install_serves_the_pendant_and_plans_on_the_simulated_arm(tmp_path):
    hidden = [module for modules in EXTRA_MODULES.values() for module in modules]
    shown = _run_without(
        hidden,
        """
        import json, sys
        from fastapi.testclient import TestClient
        from service.app import create_app
        from service.settings import Settings

        settings = Settings(data_dir="data", token="t" * 32, demo=False)
        with TestClient(create_app(settings), headers={"Authorization": "Bearer " + "t" * 32}) as c:
            health = c.get("/health").json()
            robot = c.get("/robot").json()
            page = c.get("/").status_code
            session = c.post("/sessions", json={"name": "core"}).status_code
        import sitecustomize  # the hider: what it hides was never loaded
        loaded = sorted(m for m in sys.modules if m.split(".")[0] in sitecustomize.HIDDEN)
        print(json.dumps({"health": health, "backend": robot["backend"], "page": page,
                          "session": session, "loaded": loaded}))
        """,
        tmp_path,
    )
    assert shown["backend"] == "sim" and shown["page"] == 200 and shown["session"] == 201
    assert shown["loaded"] == []


@pytest.mark.parametrize(
    "extra, body",
    [
        (
            "ur",
            """
            from drivers.robot.base import backend_config, create_backend
            backend = create_backend(backend_config("ur_rtde", host="127.0.0.9"))
            backend.connect()
            """,
        ),
        (
            "natnet",
            """
            from drivers.tracking.base import source_class
            source_class("natnet")
            """,
        ),
        (
            "e57",
            """
            from pathlib import Path
            from drivers.scanning.base import read_scan
            Path("scan.e57").write_bytes(b"ASTM-E57" + bytes(100))
            read_scan("scan.e57")
            """,
        ),
        (
            "replay",
            """
            from pathlib import Path
            from service.replay import Overrides, run_replay
            run_replay([], report_path=Path("r.csv"), overrides=Overrides.none(), tolerance_m=1e-3)
            """,
        ),
        (
            "postgres",
            """
            from service.store import Store
            Store("data", "postgresql://teachpath@127.0.0.9/teachpath")
            """,
        ),
    ],
)
def test_a_feature_without_its_extra_names_the_extra_to_install(extra, body, tmp_path):
    shown = _run_without(
        EXTRA_MODULES[extra],
        f"""
        import json
        try:
{textwrap.indent(textwrap.dedent(body), " " * 12)}
            print(json.dumps({{"error": None}}))
        except Exception as error:
            print(json.dumps({{"error": f"{{type(error).__name__}}: {{error}}"}}))
        """,
        tmp_path,
    )
    assert shown["error"] is not None, f"[{extra}] worked without its modules"
    assert f"teachpath[{extra}]" in shown["error"], shown["error"]


def test_the_c3d_reader_without_ezc3d_names_its_extra():
    """ezc3d is imported in the reader's isolated child (``python -I``, which the hiding above
    cannot reach); that a child's missing module becomes this error is tested with the
    isolation itself (tests/drivers/test_isolation.py). Here: the error names the extra."""
    from drivers.registry import missing_dependency

    error = ModuleNotFoundError("No module named 'ezc3d'", name="ezc3d")
    message = str(missing_dependency(error, "the 'c3d' trace reader"))
    assert "pip install 'teachpath[c3d]'" in message
