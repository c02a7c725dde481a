"""The cell the service plans in: keep-out boxes and cell planes from its settings."""

import pytest
from fastapi.testclient import TestClient
from pydantic import ValidationError

from service.app import create_app
from tests.service.conftest import AUTH, T_BASE_TRACKER, make_settings, planned_session, wait

#: A wall at x = 0.42 m of the base frame: the box-corner path runs from x = 0.37 to 0.45 m.
WALL_THROUGH_THE_PATH = (-1.0, 0.0, 0.0, -0.42)
#: The same wall 1.5 m in front of the base: far from the whole motion.
WALL_FAR_AWAY = (-1.0, 0.0, 0.0, -1.5)


@pytest.mark.parametrize(
    "setting, message",
    [
        ({"cell_planes": [(0.0, 0.0, 0.0, 0.5)]}, "plane 1: its normal (nx, ny, nz) is zero"),
        ({"cell_planes": [(1.0, 0.0, float("nan"), 0.5)]}, "plane 1: every number must be"),
        ({"cell_planes": [(1.0, 0.0, 0.0)]}, "cell_planes"),
        ({"keep_out_boxes": [(1.0, 1.0, 1.0, 0.0, 0.0, 0.0)]}, "each maximum (x, y, z) must"),
        ({"keep_out_boxes": [(0.0, 0.0, 0.0, 1.0, 1.0, float("inf"))]}, "finite"),
        ({"keep_out_boxes": [(0.0, 0.0, 0.0, 1.0, 1.0, 1.0)] * 33}, "at most 32 boxes"),
        ({"cell_planes": [(0.0, 0.0, 1.0, -400.0)]}, "were millimetres typed as metres"),
    ],
    ids=[
        "zero-normal",
        "nan-normal",
        "three-numbers",
        "inverted-box",
        "infinite-box",
        "33-boxes",
        "millimetres",
    ],
)
def test_a_cell_that_cannot_be_checked_stops_the_start(tmp_path, setting, message):
    with pytest.raises(ValidationError) as refused:
        make_settings(tmp_path, **setting)
    assert message in str(refused.value)


def test_the_environment_names_the_cell(tmp_path, monkeypatch):
    monkeypatch.setenv("TEACHPATH_CELL_PLANES", "[[-1, 0, 0, -1.5], [0, 1, 0, -0.8]]")
    monkeypatch.setenv("TEACHPATH_KEEP_OUT_BOXES", "[[-2, 1.2, 0, -1, 2, 1]]")
    settings = make_settings(tmp_path)
    assert settings.cell_planes == [(-1.0, 0.0, 0.0, -1.5), (0.0, 1.0, 0.0, -0.8)]
    assert settings.keep_out_boxes == [(-2.0, 1.2, 0.0, -1.0, 2.0, 1.0)]


def _client(tmp_path, **cell):
    return TestClient(create_app(make_settings(tmp_path, **cell)), headers=AUTH)


def test_a_plan_through_a_wall_of_the_cell_fails_naming_it(tmp_path, scene_files):
    with _client(tmp_path, cell_planes=[WALL_FAR_AWAY, WALL_THROUGH_THE_PATH]) as client:
        sid = client.post("/sessions", json={"name": "walled"}).json()["id"]
        client.put(f"/sessions/{sid}/recording", files={"file": ("t.csv", scene_files["trace"])})
        client.put(f"/sessions/{sid}/scan", files={"file": ("s.ply", scene_files["scan"])})
        client.put(f"/sessions/{sid}/calibration", json={"T_base_tracker": T_BASE_TRACKER})
        recon = wait(client, client.post(f"/sessions/{sid}/reconstructions", json={}).json())
        body = {"reconstruction_id": recon["result"]["reconstruction_id"], "speed_m_s": 0.05}
        job = wait(client, client.post(f"/sessions/{sid}/trajectories", json=body).json())
        assert job["state"] == "failed" and job["error"]["code"] == "collision", job
        detail = job["error"]["detail"]
        assert detail["obstacle"] == "cell plane 2", detail
        assert abs(detail["point_m"][0] - 0.42) < 0.011  # on the wall, within the margin
        assert "cell plane 2" in job["error"]["message"]
        # Nothing was stored for the refused plan.
        assert client.get(f"/sessions/{sid}/trajectories").json() == []


def test_a_plan_clear_of_the_cell_says_what_it_was_checked_against(tmp_path, scene_files):
    cell = {"cell_planes": [WALL_FAR_AWAY], "keep_out_boxes": [(-2, 1.2, 0, -1, 2, 1)]}
    with _client(tmp_path, **cell) as client:
        sid, trajectories = planned_session(client, scene_files, [0.05])
        summary = client.get(f"/sessions/{sid}/trajectories/{trajectories[0.05]}").json()["summary"]
        lines = "\n".join(summary["report"])
        assert "against: mounting plane, cell plane 1, keep-out box 1, scan (" in lines, lines
        assert "clear: no part comes within" in lines
        checked = [check for check in summary["checks"] if "collision" in check]
        assert checked and "cell plane 1, keep-out box 1" in checked[0], summary["checks"]
