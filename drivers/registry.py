"""Adapters registered by name and imported on first use: the :class:`Registry` every kind shares.

Modelled on python-can's interface registry: each kind of adapter (robot backends, tracker
sources, scan readers, trace readers) keeps a table of built-in names -> ``"module:attr"``, and
third-party packages add names through Python entry points (group ``teachpath.<kind>``, e.g. in
a plugin's ``pyproject.toml``::

    [project.entry-points."teachpath.robot_backends"]
    kuka = "teachpath_kuka:KukaBackend"

Nothing is imported until a name is used, and entry points are only looked up for a name that is
not built in (or to list every name), so a plugin cannot shadow a built-in adapter and a broken
plugin costs nothing to users who do not ask for it.

A module that cannot be imported because a third-party package is missing is reported as one
:class:`~drivers.errors.MissingDependencyError` whose message names the module and what to
install (:data:`INSTALL_HINTS`).
"""

from __future__ import annotations

import importlib
import shlex
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from importlib import metadata
from typing import Any, Generic, TypeVar

from drivers.errors import DriverError, MissingDependencyError

T = TypeVar("T")

#: Third-party module -> what to install for it: the extra of teachpath that brings it (see the
#: optional dependencies in pyproject.toml, which pin the versions the code relies on). Unlisted
#: modules are named as they are.
INSTALL_HINTS: dict[str, str] = {
    "open3d": "open3d-cpu",
    "pye57": "teachpath[e57]",
    "ezc3d": "teachpath[c3d]",
    "natnet": "teachpath[natnet]",
    "rtde_control": "teachpath[ur]",
    "rtde_receive": "teachpath[ur]",
    "dashboard_client": "teachpath[ur]",
    "dask": "teachpath[replay]",
    "distributed": "teachpath[replay]",
    "psycopg": "teachpath[postgres]",
}

#: Top-level packages of teachpath itself: an import error inside them is a bug, not a missing
#: dependency, and is raised as it is.
OWN_PACKAGES = frozenset({"drivers", "recon", "service"})


def missing_dependency(
    error: ImportError, needed_by: str, *, package: str | None = None
) -> MissingDependencyError:
    """The :class:`~drivers.errors.MissingDependencyError` for an ``ImportError``.

    Parameters
    ----------
    error : ImportError
        What the import raised; its ``name`` is the module that was not found.
    needed_by : str
        Who needs it, for the message ("the 'e57' scan reader").
    package : str, optional
        What to install; default from :data:`INSTALL_HINTS` by the missing module's top-level
        name, else that name.

    Returns
    -------
    MissingDependencyError
    """
    module = (error.name or "").split(".")[0] or "an unknown module"
    requirement = package or INSTALL_HINTS.get(module, module)
    if error.name is not None and isinstance(error, ModuleNotFoundError):
        problem = f"the Python module {module!r}, which is not installed"
    else:
        # Installed, but not in a version that has what teachpath imports from it.
        problem = f"the Python module {module!r}, which is installed but unusable ({error})"
    return MissingDependencyError(
        f"{needed_by} needs {problem}; install it (pip install {shlex.quote(requirement)})",
        module=module,
        package=requirement,
    )


@dataclass(frozen=True)
class _Plugin:
    target: str
    distribution: str | None
    extras: tuple[str, ...]

    def requirement(self) -> str | None:
        """What to install for the plugin's optional dependencies, if it says."""
        if self.distribution is None or not self.extras:
            return None
        return f"{self.distribution}[{','.join(self.extras)}]"


class Registry(Generic[T]):
    """Names of one kind of adapter -> the objects that implement them, imported on first use.

    Parameters
    ----------
    kind : str
        What the names name, for messages ("robot backend", "scan format").
    builtins : mapping of str to str
        Built-in name -> ``"module:attr"``. Copied; :attr:`builtins` is the copy.
    group : str
        Entry-point group through which other packages register more names.
    unknown_error : DriverError subclass
        Raised for a name that is neither built in nor registered by a package.
    base : type, optional
        What a loaded object must be a subclass of (a plugin's mistake is a ``TypeError``).

    Examples
    --------
    >>> readers = Registry("trace format", {"csv": "drivers.tracking.readers:read_canonical_raw"},
    ...                    group="teachpath.trace_readers", unknown_error=DriverError)
    >>> readers.names()
    ['csv']
    >>> readers.load("csv").__name__
    'read_canonical_raw'
    """

    def __init__(
        self,
        kind: str,
        builtins: Mapping[str, str],
        *,
        group: str,
        unknown_error: type[DriverError],
        base: type | None = None,
    ) -> None:
        for name, target in builtins.items():
            _split(target, name)  # a malformed built-in entry is a bug: fail at import time
        self.kind = kind
        self.builtins: dict[str, str] = dict(builtins)
        self.group = group
        self.unknown_error = unknown_error
        self.base = base

    def __repr__(self) -> str:
        return f"Registry({self.kind!r}, {sorted(self.builtins)!r}, group={self.group!r})"

    # -- names -----------------------------------------------------------------------------------

    def names(self) -> list[str]:
        """Every name, built in or registered by an installed package, sorted."""
        return sorted(set(self.builtins) | set(self._plugins()))

    def __iter__(self) -> Iterator[str]:
        return iter(self.names())

    def __contains__(self, name: object) -> bool:
        if not isinstance(name, str):
            return False
        return name in self.builtins or self._plugin(name) is not None

    def target(self, name: str) -> str:
        """The ``"module:attr"`` registered as ``name``.

        Raises
        ------
        DriverError
            :attr:`unknown_error` for an unknown name; the message lists the known ones.
        """
        return self._lookup(name)[0]

    def unknown(self, name: str) -> DriverError:
        """The error for an unknown ``name``, listing the available names."""
        return self.unknown_error(
            f"unknown {self.kind} {name!r}; available: {', '.join(self.names())}"
        )

    # -- loading ---------------------------------------------------------------------------------

    def load(self, name: str) -> T:
        """The object registered as ``name``, its module imported now.

        Raises
        ------
        DriverError
            :attr:`unknown_error` for an unknown name.
        MissingDependencyError
            The module (or one it imports) needs a package that is not installed.
        TypeError
            The object is not a subclass of :attr:`base`.
        """
        target, plugin = self._lookup(name)
        module_name, attr = _split(target, name)
        try:
            module = importlib.import_module(module_name)
        except ImportError as exc:
            missing = (exc.name or "").split(".")[0]
            if missing in OWN_PACKAGES:
                # An entry that points nowhere, or a plugin written for another teachpath:
                # a bug to fix, not a package to install.
                raise
            package = None
            if plugin is not None and missing == module_name.split(".")[0]:
                package = plugin.distribution
            elif plugin is not None:
                package = plugin.requirement()
            raise missing_dependency(exc, f"the {name!r} {self.kind}", package=package) from None
        try:
            obj = getattr(module, attr)
        except AttributeError:
            raise AttributeError(
                f"{module_name} has no attribute {attr!r} (registered as {self.kind} {name!r})"
            ) from None
        if self.base is not None and not (isinstance(obj, type) and issubclass(obj, self.base)):
            raise TypeError(
                f"{target} (registered as {self.kind} {name!r}) is not a {self.base.__name__}"
            )
        loaded: T = obj  # checked against ``base`` above when there is one
        return loaded

    # -- entry points ----------------------------------------------------------------------------

    def _lookup(self, name: str) -> tuple[str, _Plugin | None]:
        """The target of ``name`` and, if a package registered it, the plugin's details."""
        if name in self.builtins:
            return self.builtins[name], None
        plugin = self._plugin(name)
        if plugin is None:
            raise self.unknown(name)
        return plugin.target, plugin

    def _entry_points(self) -> list[metadata.EntryPoint]:
        # Looked up on every call, not cached: it only happens for names that are not built in,
        # and a package installed while the service runs is then seen.
        return list(metadata.entry_points(group=self.group))

    def _plugins(self) -> dict[str, _Plugin]:
        found: dict[str, _Plugin] = {}
        for entry in self._entry_points():
            if entry.name in self.builtins or entry.name in found:
                continue  # built-ins win; of two packages with one name, the first found
            dist = getattr(entry, "dist", None)
            found[entry.name] = _Plugin(
                # An entry without ":attr" is kept as it is, for load() to refuse with its name.
                target=entry.module + (f":{entry.attr}" if entry.attr else ""),
                distribution=None if dist is None else dist.name,
                extras=tuple(entry.extras),
            )
        return found

    def _plugin(self, name: str) -> _Plugin | None:
        return self._plugins().get(name)


def import_target(target: str) -> Any:
    """The object a ``"module:attr"`` string names, its module imported now.

    Raises
    ------
    ValueError
        Not of the form ``module:attr``.
    ImportError, AttributeError
        No such module or attribute.
    """
    module_name, sep, attr = target.partition(":")
    if not sep or not module_name or not attr:
        raise ValueError(f"{target!r} is not 'module:attr'")
    return getattr(importlib.import_module(module_name), attr)


def _split(target: str, name: str) -> tuple[str, str]:
    module_name, sep, attr = target.partition(":")
    if not sep or not module_name or not attr:
        raise ValueError(f"{name!r} is registered as {target!r}, which is not 'module:attr'")
    return module_name, attr
