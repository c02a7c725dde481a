"""The adapter registries: names, lazy imports, entry points of other packages, missing packages."""

from __future__ import annotations

import importlib
import importlib.metadata
import sys
import textwrap
from types import SimpleNamespace

import numpy as np
import pytest

from drivers import registry as registry_module
from drivers.errors import (
    MissingDependencyError,
    UnknownBackendError,
    UnknownFormatError,
)
from drivers.registry import Registry
from drivers.robot.base import BACKENDS, RobotBackend, backend_class, create_backend
from drivers.robot.clock import FakeClock
from drivers.robot.sim import SimBackend, SimConfig
from drivers.scanning.base import SCAN_READERS, format_for
from drivers.tracking.base import SOURCES, create_source, source_class
from drivers.tracking.natnet_source import NatNetConfig, NatNetSource
from drivers.tracking.readers import TRACE_READERS
from drivers.tracking.replay import ReplayConfig, ReplaySource
from recon.inputs import Recording

GROUP = "teachpath.test_backends"


def _entry(name, module, attr, *, extras=(), dist=None, group=GROUP):
    """What importlib.metadata yields for an entry point (the attributes the registry reads)."""
    return SimpleNamespace(
        group=group,
        name=name,
        module=module,
        attr=attr,
        extras=list(extras),
        dist=None if dist is None else SimpleNamespace(name=dist),
    )


class FakeEntryPoints(list):
    """Installed entry points (append to it); ``lookups`` records each group looked up."""

    def __init__(self) -> None:
        super().__init__()
        self.lookups: list[str] = []

    def __call__(self, *, group: str) -> list:
        self.lookups.append(group)
        return [entry for entry in self if entry.group == group]


@pytest.fixture
def entry_points(monkeypatch):
    """Replaces importlib.metadata.entry_points, which the registries call, with a fake."""
    fake = FakeEntryPoints()
    monkeypatch.setattr(importlib.metadata, "entry_points", fake)
    return fake


@pytest.fixture
def plugin_module(tmp_path, monkeypatch):
    """Writes a module into a folder on sys.path; forgets it afterwards."""
    monkeypatch.syspath_prepend(str(tmp_path))
    written = []

    def write(name: str, source: str) -> str:
        (tmp_path / f"{name}.py").write_text(textwrap.dedent(source))
        written.append(name)
        return name

    yield write
    for name in written:
        sys.modules.pop(name, None)


def _robots(**builtins) -> Registry:
    return Registry(
        "robot backend",
        builtins or {"sim": "drivers.robot.sim:SimBackend"},
        group=GROUP,
        unknown_error=UnknownBackendError,
        base=RobotBackend,
    )


def test_an_unknown_name_lists_the_available_ones(entry_points):
    entry_points.append(_entry("kuka", "teachpath_kuka", "KukaBackend"))
    with pytest.raises(UnknownBackendError) as raised:
        _robots().load("abb")
    assert str(raised.value) == "unknown robot backend 'abb'; available: kuka, sim"
    with pytest.raises(UnknownBackendError, match=r"available: sim, ur_rtde$"):
        backend_class("kuka")  # the real registry, with no package adding to it here
    with pytest.raises(UnknownFormatError, match=r"unknown scan format 'las'; available: bag, "):
        format_for("scan.las", "las")


def test_built_in_names_need_no_entry_point_lookup(entry_points):
    robots = _robots()
    assert robots.load("sim") is SimBackend
    assert "sim" in robots
    assert entry_points.lookups == []  # looked up only for names that are not built in
    assert "kuka" not in robots and entry_points.lookups == [GROUP]


def test_an_entry_point_is_found_when_the_name_is_not_built_in(entry_points, plugin_module):
    module = plugin_module(
        "teachpath_fake_kuka",
        """
        from typing import Literal

        from drivers.robot.sim import SimBackend, SimConfig


        class KukaConfig(SimConfig):
            kind: Literal["kuka"] = "kuka"


        class KukaBackend(SimBackend):
            kind = "kuka"
        """,
    )
    entry_points.append(_entry("kuka", module, "KukaBackend", dist="teachpath-kuka"))
    entry_points.append(_entry("sim", module, "KukaBackend"))  # cannot replace a built-in
    robots = _robots()
    assert module not in sys.modules  # nothing imported until asked for
    assert robots.names() == ["kuka", "sim"] and list(robots) == ["kuka", "sim"]
    kuka = robots.load("kuka")
    assert kuka.__name__ == "KukaBackend" and kuka.__module__ == module
    assert robots.load("sim") is SimBackend


def test_the_real_registries_read_entry_points_too(entry_points, plugin_module):
    module = plugin_module(
        "teachpath_fake_kuka2",
        """
        from typing import Literal

        from drivers.robot.sim import SimBackend, SimConfig


        class KukaConfig(SimConfig):
            kind: Literal["kuka"] = "kuka"


        class KukaBackend(SimBackend):
            kind = "kuka"
        """,
    )
    entry_points.append(_entry("kuka", module, "KukaBackend", group="teachpath.robot_backends"))
    plugin = importlib.import_module(module)
    backend = create_backend(plugin.KukaConfig(), clock=FakeClock())
    assert type(backend).__name__ == "KukaBackend" and "kuka" in BACKENDS


def test_a_plugin_that_is_not_an_adapter_is_refused(entry_points):
    entry_points.append(_entry("numpy", "numpy", "ndarray"))
    with pytest.raises(TypeError, match="numpy:ndarray .registered as robot backend 'numpy'"):
        _robots().load("numpy")


def test_a_missing_dependency_names_the_module_and_what_to_install(plugin_module, monkeypatch):
    module = plugin_module("teachpath_needs_fancy", "import fancy_lib_not_here\n")
    monkeypatch.setitem(registry_module.INSTALL_HINTS, "fancy_lib_not_here", "fancy-lib[cuda]>=2")
    robots = _robots(fancy=f"{module}:Backend")
    with pytest.raises(MissingDependencyError) as raised:
        robots.load("fancy")
    error = raised.value
    assert str(error) == (
        "the 'fancy' robot backend needs the Python module 'fancy_lib_not_here', which is not "
        "installed; install it (pip install 'fancy-lib[cuda]>=2')"
    )
    assert error.module == "fancy_lib_not_here" and error.package == "fancy-lib[cuda]>=2"
    # What the callers of the registries caught before there was a class of its own:
    assert isinstance(error, UnknownBackendError) and isinstance(error, UnknownFormatError)


def test_a_plugin_s_missing_dependency_names_its_extra(entry_points, plugin_module):
    module = plugin_module("teachpath_fake_abb", "import abb_rws_not_here\n")
    entry_points.append(_entry("abb", module, "Backend", extras=["rws"], dist="teachpath-abb"))
    entry_points.append(_entry("gone", "teachpath_gone_plugin", "Backend", dist="teachpath-gone"))
    robots = _robots()
    with pytest.raises(MissingDependencyError, match=r"pip install 'teachpath-abb\[rws\]'"):
        robots.load("abb")
    # A stale entry point of an uninstalled package: reinstall the package.
    with pytest.raises(MissingDependencyError, match=r"pip install teachpath-gone\)$"):
        robots.load("gone")


def test_an_installed_module_without_what_is_imported_from_it(plugin_module):
    module = plugin_module("teachpath_old_api", "from numpy import no_such_function\n")
    with pytest.raises(MissingDependencyError, match="'numpy', which is installed but unusable"):
        _robots(old=f"{module}:Backend").load("old")


def test_a_broken_built_in_entry_is_a_bug_not_a_missing_package():
    with pytest.raises(ModuleNotFoundError, match="drivers.robot.nothing"):
        _robots(nothing="drivers.robot.nothing:Backend").load("nothing")
    with pytest.raises(AttributeError, match="registered as robot backend 'sim'"):
        _robots(sim="drivers.robot.sim:NoSuchBackend").load("sim")
    with pytest.raises(ValueError, match="not 'module:attr'"):
        _robots(sim="drivers.robot.sim")


def test_the_four_registries_and_their_helpers():
    assert BACKENDS.names() == ["sim", "ur_rtde"]
    assert SOURCES.names() == ["natnet", "replay"]
    assert TRACE_READERS.names() == ["c3d", "csv", "motive", "rtde"]
    assert "ply" in SCAN_READERS and "bag" in SCAN_READERS and "las" not in SCAN_READERS
    assert sorted(SCAN_READERS) == SCAN_READERS.names()  # what the CLI's choices use
    assert source_class("replay") is ReplaySource and source_class("natnet") is NatNetSource
    with pytest.raises(UnknownBackendError, match=r"unknown tracker source 'vicon'; available"):
        source_class("vicon")


def test_create_source_picks_the_class_by_the_config_s_kind():
    recording = Recording(points_m=np.zeros((5, 3)), t_s=np.arange(5) / 100.0)
    replay = create_source(ReplayConfig(speed=None, batch_s=0.02), recording=recording)
    assert isinstance(replay, ReplaySource) and replay.batch_s == 0.02
    assert sum(len(batch) for batch in replay.batches()) == 5
    paced = create_source(ReplayConfig(speed=2.0), recording=recording, clock=FakeClock())
    assert paced.pacer.speed == 2.0 and isinstance(paced.pacer.clock, FakeClock)
    live = create_source(NatNetConfig(rigid_body="Pen"))
    assert isinstance(live, NatNetSource) and live.config.rigid_body == "Pen"


def test_create_source_refuses_what_a_source_does_not_take():
    with pytest.raises(ValueError, match="needs the recording"):
        create_source(ReplayConfig())
    with pytest.raises(ValueError, match="neither a recording nor a clock"):
        create_source(NatNetConfig(rigid_body="Pen"), clock=FakeClock())
    with pytest.raises(ValueError, match="speeed"):
        ReplayConfig(speeed=2.0)  # a typo is refused, not swallowed


def test_create_backend_picks_the_sim():
    backend = create_backend(SimConfig(), clock=FakeClock())
    assert isinstance(backend, SimBackend)
