from tests.service.conftest import scene_files  # noqa: F401 - shared fixture
