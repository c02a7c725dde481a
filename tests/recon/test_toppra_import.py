"""toppra imported without matplotlib (recon.toppra_import), each case in a fresh interpreter:
what a process has imported cannot be undone in this one."""

import os
import subprocess
import sys
import textwrap

import pytest


def _run(code: str) -> str:
    env = {**os.environ, "MPLBACKEND": "Agg"}
    done = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)],
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr
    return done.stdout.strip()


def test_toppra_loads_without_matplotlib_and_plans():
    out = _run(
        """
        import sys
        import numpy as np
        from recon.toppra_import import import_toppra

        toppra = import_toppra()
        assert not [m for m in sys.modules if m.startswith("matplotlib")], "matplotlib loaded"
        path = toppra.SplineInterpolator([0.0, 1.0], np.array([[0.0], [1.0]]))
        limits = [
            toppra.constraint.JointVelocityConstraint(np.array([[-1.0, 1.0]])),
            toppra.constraint.JointAccelerationConstraint(np.array([[-2.0, 2.0]])),
        ]
        trajectory = toppra.algorithm.TOPPRA(limits, path).compute_trajectory(0.0, 0.0)
        print(round(trajectory.duration, 3))
        """
    )
    # 1 rad at 1 rad/s and 2 rad/s^2, from rest to rest: 0.5 s up, 0.5 s cruise, 0.5 s down.
    assert float(out) == pytest.approx(1.5, abs=0.02)


def test_a_plot_helper_gets_the_real_pyplot_on_first_use():
    out = _run(
        """
        import sys
        from recon.toppra_import import _Deferred, import_toppra

        import_toppra()
        import toppra.algorithm.algorithm as algorithm

        assert isinstance(algorithm.plt, _Deferred)
        assert getattr(algorithm.plt, "__path__", None) is None  # a probe imports nothing
        assert "matplotlib.pyplot" not in sys.modules
        figure = algorithm.plt.figure  # a use: the real module
        import matplotlib.pyplot

        assert figure is matplotlib.pyplot.figure
        assert not isinstance(sys.modules["matplotlib.pyplot"], _Deferred)
        assert not isinstance(sys.modules["matplotlib"], _Deferred)
        print("ok")
        """
    )
    assert out == "ok"


def test_with_another_thread_alive_toppra_is_imported_as_it_is():
    """A stand-in in sys.modules would be handed to another thread importing matplotlib (or a
    submodule, which it cannot provide): with one alive, no stand-in is placed."""
    out = _run(
        """
        import sys
        import threading
        from recon.toppra_import import _Deferred, import_toppra

        done = threading.Event()
        other = threading.Thread(target=done.wait)
        other.start()
        import_toppra()
        import toppra.algorithm.algorithm as algorithm

        assert not isinstance(algorithm.plt, _Deferred)
        assert "matplotlib.backends" in sys.modules or "matplotlib.pyplot" in sys.modules
        done.set()
        other.join()
        print("ok")
        """
    )
    assert out == "ok"


def test_plan_imports_toppra_before_its_threads_start(tmp_path):
    """``teachpath plan`` imports toppra first thing, alone, so without matplotlib: in a fresh
    process the trajectory is planned and matplotlib never loaded (no --plot)."""
    from drivers.scanning.pointcloud import write_scan
    from drivers.tracking.canonical_csv import write_trace_csv
    from recon import scenes
    from service.cli import main

    scene = scenes.serpentine_plate(400, 20_000)
    trace, scan, recon = tmp_path / "trace.csv", tmp_path / "scan.ply", tmp_path / "recon.csv"
    write_trace_csv(trace, scene.recording)
    write_scan(scan, scene.scan)
    assert main(["reconstruct", str(trace), "--scan", str(scan), "--out", str(recon)]) == 0
    out = _run(
        f"""
        import sys
        from service.cli import main

        args = [{str(recon)!r}, "--scan", {str(scan)!r}, "--robot", "ur10e", "--speed-m-s",
                "0.1", "--out", {str(tmp_path / "trajectory.csv")!r}]
        assert main(["plan", *args]) == 0
        assert "matplotlib.pyplot" not in sys.modules
        print("ok")
        """
    )
    assert out.endswith("ok")
    assert (tmp_path / "trajectory.csv").exists()


def test_threads_importing_at_once_get_one_toppra_and_leave_no_stand_in():
    out = _run(
        """
        import sys
        import threading
        from recon.toppra_import import _Deferred, import_toppra

        start, got = threading.Barrier(8), []

        def load():
            start.wait()
            got.append(import_toppra())

        threads = [threading.Thread(target=load) for _ in range(8)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        assert len(got) == 8 and all(m is got[0] for m in got)
        assert hasattr(got[0].algorithm, "TOPPRA")
        assert not any(isinstance(m, _Deferred) for m in list(sys.modules.values()))
        print("ok")
        """
    )
    assert out == "ok"


def test_a_pyplot_already_loaded_is_the_one_toppra_gets():
    out = _run(
        """
        import matplotlib.pyplot
        from recon.toppra_import import import_toppra

        import_toppra()
        import toppra.algorithm.algorithm as algorithm
        import toppra.parametrizer as parametrizer

        assert algorithm.plt is matplotlib.pyplot and parametrizer.plt is matplotlib.pyplot
        print("ok")
        """
    )
    assert out == "ok"
