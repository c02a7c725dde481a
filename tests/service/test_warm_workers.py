"""A warm start: the job workers start with the service and import what the jobs need before
the first job, so the operator's first click does not wait for them."""

from __future__ import annotations

import pytest

from service.jobs import WARM_MODULES, JobManager
from service.settings import Settings
from service.store import Store
from tests.service.job_targets import LoadedModules


def _loaded_in_a_worker(tmp_path, *, warm: bool, modules=WARM_MODULES) -> list[str]:
    store = Store(tmp_path, f"sqlite:///{tmp_path / 'db.sqlite'}")
    jobs = JobManager(store, workers=1, warm=warm, warm_modules=modules)
    try:
        for started in jobs.warmed:
            started.result(timeout=120)  # the worker is up and has imported WARM_MODULES
        assert len(jobs.warmed) == (1 if warm else 0)
        future = jobs._pool.submit(LoadedModules(WARM_MODULES).run)
        return future.result(timeout=120)["loaded"]
    finally:
        jobs.shutdown()


@pytest.mark.parametrize("warm", [True, False], ids=["warm", "cold"])
def test_a_warm_worker_has_the_pipelines_imported_before_its_first_job(tmp_path, warm):
    loaded = _loaded_in_a_worker(tmp_path, warm=warm)
    if warm:
        assert loaded == list(WARM_MODULES)
    else:  # what the warm start saves: a cold worker imports them in its first job
        assert "recon.reconstruct" not in loaded and "service.plots" not in loaded


def test_a_module_that_fails_to_import_leaves_the_pool_working(tmp_path):
    """An initializer that raises breaks a process pool for good (every job would fail as a
    dead worker): a warm-up import that fails is logged, and the worker runs its jobs."""
    loaded = _loaded_in_a_worker(
        tmp_path, warm=True, modules=("teachpath_no_such_module", "service.plots")
    )
    assert "service.plots" in loaded  # the worker ran this job, and the rest was imported


def test_the_service_warms_its_workers_by_default():
    assert Settings.model_fields["warm_workers"].default is True
    for name in WARM_MODULES:  # each name is a module that imports (no typo to skip silently)
        __import__(name)
