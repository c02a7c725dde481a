"""toppra, imported without the plotting library it loads for helpers teachpath never calls.

toppra's algorithm and parametrizer modules import ``matplotlib.pyplot`` at the top, for their
``plot_*`` helpers. That import is 0.3 s of ``teachpath plan``'s start-up (``python -X
importtime``: about all of toppra's 0.33 s), for nothing: teachpath never plots. While toppra is
imported, :func:`import_toppra` puts stand-ins for ``matplotlib`` and ``matplotlib.pyplot`` in
``sys.modules`` and takes them out again afterwards; toppra keeps a stand-in as its ``plt``, and
the first attribute read from it imports the real module and answers from that (so a plot helper
still works, only later).

The stand-ins are placed only where the calling thread is the process's only thread: another
thread importing matplotlib (or one of its submodules, which a stand-in cannot provide) during
that window would be handed a stand-in. Elsewhere (the service's processes, a CLI command after
its worker threads started) toppra is imported as it is, matplotlib with it; ``teachpath plan``
imports toppra first thing for that reason. Why not ``importlib.util.LazyLoader``: in Python
3.11 two threads touching a lazy module for the first time can both run its loader. One lock
covers the swap in ``sys.modules`` and the first real import through a stand-in.
"""

from __future__ import annotations

import importlib
import sys
import threading
import types
from typing import Any

#: Modules toppra imports at the top only for plotting.
DEFERRED = ("matplotlib", "matplotlib.pyplot")

_LOCK = threading.RLock()


class _Deferred(types.ModuleType):
    """Stands in for a module until one of its attributes is read; then imports the real one
    and answers from it."""

    def __getattr__(self, name: str) -> Any:
        if name.startswith("__") and name.endswith("__"):
            # Probes (``__path__``, ``__file__``, ...) are not a use: they import nothing.
            raise AttributeError(name)
        return getattr(_real(self.__name__), name)


def _real(name: str) -> types.ModuleType:
    """The real module ``name``, imported now if need be (stand-ins taken out first)."""
    with _LOCK:
        for deferred in DEFERRED:
            if isinstance(sys.modules.get(deferred), _Deferred):
                del sys.modules[deferred]
        return importlib.import_module(name)


def import_toppra() -> Any:
    """The ``toppra`` module (its package imports ``toppra.algorithm`` and ``toppra.constraint``),
    without importing matplotlib where this thread is the only one (and nothing has imported
    matplotlib already). Typed ``Any``: toppra has no type information.

    Safe to call from several threads at once, and as often as wanted.
    """
    with _LOCK:
        if "toppra" in sys.modules:
            return sys.modules["toppra"]
        placed = [name for name in DEFERRED if name not in sys.modules]
        if "matplotlib.pyplot" not in placed or threading.active_count() > 1:
            # pyplot is loaded already (nothing to spare), or another thread could import
            # matplotlib meanwhile and be handed a stand-in.
            placed = []
        for name in placed:
            sys.modules[name] = _Deferred(name)
        if "matplotlib" in placed:
            # ``import matplotlib.pyplot as plt`` reads the parent's attribute.
            parent: Any = sys.modules["matplotlib"]
            parent.pyplot = sys.modules["matplotlib.pyplot"]
        try:
            import toppra
        finally:
            for name in placed:
                if isinstance(sys.modules.get(name), _Deferred):
                    del sys.modules[name]
        return toppra
