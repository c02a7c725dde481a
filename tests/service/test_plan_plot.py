"""The plan preview route (``GET .../trajectories/{id}/plot.png``): what `teachpath plan --plot`
writes, for a stored trajectory."""

from __future__ import annotations

import io

import matplotlib.pyplot as plt

from tests.service.conftest import planned_session


def test_a_planned_trajectory_has_its_preview_picture(client, scene_files):
    sid, trajectories = planned_session(client, scene_files, (0.05,), name="plot")
    tid = trajectories[0.05]
    response = client.get(f"/sessions/{sid}/trajectories/{tid}/plot.png")
    assert response.status_code == 200, response.text
    assert response.headers["content-type"] == "image/png"
    picture = plt.imread(io.BytesIO(response.content), format="png")
    assert picture.shape[:2] == (900, 1000)
    assert picture[..., :3].std() > 0.05  # drawn, not blank


def test_the_preview_of_an_unknown_trajectory_is_a_404(client, session):
    response = client.get(f"/sessions/{session}/trajectories/trj_000000000000/plot.png")
    assert response.status_code == 404 and response.json()["code"] == "not_found"
