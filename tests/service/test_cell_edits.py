"""The cell edited from the pendant (PUT /cell): stored under the arm's name, refused when it
cannot be checked, from an older view or while the arm runs; plans follow it."""

from __future__ import annotations

import json
import threading

import numpy as np
import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from service.store import CellChangedError, CellRow, Store
from tests.service.conftest import AUTH, make_settings, planned_session, wait

#: The box-corner trace runs from x = 0.37 to 0.45 m of the base frame: a wall at x = 0.42 m
#: cuts it, one at 1.5 m is far from every motion.
WALL_THROUGH_THE_PATH = [-1.0, 0.0, 0.0, -0.42]
WALL_FAR_AWAY = [-1.0, 0.0, 0.0, -1.5]
STARTUP_BOX = (-2.0, 1.2, 0.0, -1.0, 2.0, 1.0)


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory):
    return tmp_path_factory.mktemp("cell_edits")


@pytest.fixture(scope="module")
def client(data_dir):
    settings = make_settings(data_dir, keep_out_boxes=[STARTUP_BOX])
    with TestClient(create_app(settings), headers=AUTH) as test_client:
        yield test_client


@pytest.fixture
def fresh(client):
    """The cell back at the start-up settings before and after a test."""

    def reset():
        revision = client.get("/cell").json()["revision"]
        assert client.delete("/cell", params={"revision": revision}).status_code == 200

    reset()
    yield client
    reset()


def _put(client, boxes, planes, revision=None):
    if revision is None:
        revision = client.get("/cell").json()["revision"]
    return client.put(
        "/cell", json={"keep_out_boxes_m": boxes, "cell_planes": planes, "revision": revision}
    )


def test_an_edited_cell_applies_and_outlives_a_restart(fresh, data_dir):
    before = fresh.get("/cell").json()
    assert before["keep_out_boxes_m"] == [list(STARTUP_BOX)] and before["cell_planes"] == []
    assert before["source"] == "the server's start-up settings" and before["editable"]

    box = [0.6, -0.1, 0.0, 0.8, 0.1, 0.3]
    edited = _put(fresh, [box], [WALL_FAR_AWAY])
    assert edited.status_code == 200, edited.text
    body = edited.json()
    assert body["keep_out_boxes_m"] == [box] and body["cell_planes"] == [WALL_FAR_AWAY]
    assert body["revision"] == before["revision"] + 1
    assert body["source"].startswith("edited in the pendant at ")
    assert fresh.get("/cell").json() == body

    # Another instance on the same database (the service restarted) has the edited cell.
    settings = make_settings(data_dir, keep_out_boxes=[STARTUP_BOX])
    with TestClient(create_app(settings), headers=AUTH) as restarted:
        assert restarted.get("/cell").json()["keep_out_boxes_m"] == [box]

    # Back to the start-up settings: a change too, with its own revision.
    reset = fresh.delete("/cell", params={"revision": body["revision"]})
    assert reset.status_code == 200
    assert reset.json()["keep_out_boxes_m"] == [list(STARTUP_BOX)]
    assert reset.json()["revision"] == body["revision"] + 1
    assert reset.json()["source"] == "the server's start-up settings"


def test_an_edit_from_an_older_view_is_refused_and_changes_nothing(fresh):
    seen = fresh.get("/cell").json()["revision"]
    first = _put(fresh, [[0.6, -0.1, 0.0, 0.8, 0.1, 0.3]], [], revision=seen)
    assert first.status_code == 200
    second = _put(fresh, [], [WALL_FAR_AWAY], revision=seen)  # a second pendant's older view
    assert second.status_code == 409 and second.json()["code"] == "cell_changed"
    assert second.json()["detail"] == {"revision": seen + 1}
    assert "reload it" in second.json()["message"]
    assert fresh.get("/cell").json() == first.json()
    gone = fresh.delete("/cell", params={"revision": seen})
    assert gone.status_code == 409 and fresh.get("/cell").json() == first.json()


BAD_CELLS = {
    "inverted box": ([[0.8, 0, 0, 0.6, 0.1, 0.3]], [], "keep-out box 1: each maximum"),
    "flat box": ([[0.6, 0, 0, 0.8, 0, 0.3]], [], "keep-out box 1: each maximum"),
    "five numbers": ([[0.6, 0, 0, 0.8, 0.1]], [], "keep-out box 1: give 6 numbers"),
    "a text": ([[0.6, 0, 0, 0.8, "0.1", 0.3]], [], "keep-out box 1: give 6 numbers"),
    "a boolean": ([[0.6, 0, 0, 0.8, True, 0.3]], [], "keep-out box 1: give 6 numbers"),
    "nested": ([[[0.6], 0, 0, 0.8, 0.1, 0.3]], [], "keep-out box 1: give 6 numbers"),
    "millimetres": ([[600, -100, 0, 800, 100, 300]], [], "were millimetres typed as metres"),
    "huge": ([[0, 0, 0, 1e308, 1, 1]], [], "more than 10 m"),
    "zero normal": ([], [[0, 0, 0, 0.5]], "plane 1: its normal (nx, ny, nz) is zero"),
    "far plane": ([], [[1, 0, 0, 40.0]], "plane 1: it is more than 10 m"),
    "three numbers": ([], [[1, 0, 0]], "plane 1: give 4 numbers"),
    "too many boxes": ([[0.6, 0, 0, 0.8, 0.1, 0.3]] * 33, [], "at most 32 boxes"),
    "too many planes": ([], [WALL_FAR_AWAY] * 17, "and 16 planes"),
}


@pytest.mark.parametrize("case", BAD_CELLS, ids=list(BAD_CELLS))
def test_a_cell_that_cannot_be_checked_is_refused_saying_what_to_change(fresh, case):
    boxes, planes, words = BAD_CELLS[case]
    before = fresh.get("/cell").json()
    response = _put(fresh, boxes, planes)
    assert response.status_code == 422, response.text
    assert words in response.json()["message"], response.json()
    assert fresh.get("/cell").json() == before


@pytest.mark.parametrize(
    "body",
    [
        '{"keep_out_boxes_m": [[0, 0, 0, NaN, 1, 1]], "cell_planes": [], "revision": 0}',
        '{"keep_out_boxes_m": [[0, 0, 0, 1e999, 1, 1]], "cell_planes": [], "revision": 0}',
        '{"keep_out_boxes_m": [], "cell_planes": [], "revision": -1}',
        '{"keep_out_boxes_m": [], "cell_planes": [], "revision": 1' + "0" * 400 + "}",
        '{"keep_out_boxes_m": [], "cell_planes": [], "revision": "0"}',
        '{"keep_out_boxes_m": [], "cell_planes": []}',
        '{"keep_out_boxes_m": [], "cell_planes": [], "revision": 0, "owner": "x"}',
        '{"keep_out_boxes_m": ' + "[" * 5000 + "]" * 5000 + ', "cell_planes": [], "revision": 0}',
        json.dumps(
            {"keep_out_boxes_m": [[0, 0, 0, 1, 1, 1]] * 5000, "cell_planes": [], "revision": 0}
        ),
        "[1, 2",
        '{"keep_out_boxes_m": [[0, 0, 0, 1' + "0" * 400 + ', 1, 1]], "cell_planes": [], '
        '"revision": 0}',
    ],
    ids=[
        "nan",
        "overflow",
        "negative-revision",
        "400-digit-revision",
        "text-revision",
        "no-revision",
        "unknown-field",
        "nested-5000",
        "5000-boxes",
        "truncated",
        "400-digit-corner",
    ],
)
def test_hostile_bodies_get_a_4xx_and_change_nothing(fresh, body):
    before = fresh.get("/cell").json()
    response = fresh.put("/cell", content=body, headers={"Content-Type": "application/json"})
    assert 400 <= response.status_code < 500, response.text
    assert response.json()["message"]
    assert fresh.get("/cell").json() == before


def test_a_reset_needs_a_revision_that_is_a_number(fresh):
    for params in ({}, {"revision": "x"}, {"revision": -1}, {"revision": "9" * 40}):
        assert fresh.delete("/cell", params=params).status_code == 422, params


def test_only_a_signed_in_pendant_reads_or_edits_the_cell(fresh):
    for method in ("get", "put", "delete"):
        response = getattr(fresh, method)("/cell", headers={"Authorization": "Bearer wrong"})
        assert response.status_code == 401, (method, response.text)


def test_an_edit_is_refused_while_a_real_arm_execution_owns_the_arm(fresh):
    class Running:  # what the gate registers while the arm moves: only `running` is read
        running = True

    live = fresh.app.state.services.live
    with live.lock:
        live.executions["exe_running"] = Running()
    try:
        refused = _put(fresh, [], [WALL_FAR_AWAY])
        assert refused.status_code == 409 and refused.json()["code"] == "arm_running"
        assert "exe_running" in refused.json()["message"]
        assert fresh.get("/cell").json()["editable"] is False
    finally:
        with live.lock:
            del live.executions["exe_running"]
    assert fresh.get("/cell").json()["editable"] is True
    assert _put(fresh, [], [WALL_FAR_AWAY]).status_code == 200


def test_plans_follow_the_cell_edited(fresh, scene_files):
    # A wall through the path, set in the pendant: the plan fails naming it.
    assert _put(fresh, [], [WALL_FAR_AWAY, WALL_THROUGH_THE_PATH]).status_code == 200
    sid = fresh.post("/sessions", json={"name": "walled"}).json()["id"]
    fresh.put(f"/sessions/{sid}/recording", files={"file": ("t.csv", scene_files["trace"])})
    fresh.put(f"/sessions/{sid}/scan", files={"file": ("s.ply", scene_files["scan"])})
    from tests.service.conftest import T_BASE_TRACKER

    fresh.put(f"/sessions/{sid}/calibration", json={"T_base_tracker": T_BASE_TRACKER})
    recon = wait(fresh, fresh.post(f"/sessions/{sid}/reconstructions", json={}).json())
    body = {"reconstruction_id": recon["result"]["reconstruction_id"], "speed_m_s": 0.05}
    job = wait(fresh, fresh.post(f"/sessions/{sid}/trajectories", json=body).json())
    assert job["state"] == "failed" and job["error"]["detail"]["obstacle"] == "cell plane 2"

    # Only the far wall: the plan passes, records that cell and is current.
    assert _put(fresh, [], [WALL_FAR_AWAY]).status_code == 200
    job = wait(fresh, fresh.post(f"/sessions/{sid}/trajectories", json=body).json())
    assert job["state"] == "succeeded", job
    plan_url = f"/sessions/{sid}/trajectories/{job['result']['trajectory_id']}"
    plan = fresh.get(plan_url).json()
    assert plan["params"]["cell_planes"] == [WALL_FAR_AWAY] and plan["outdated"] == []

    # A box added afterwards: the plan is outdated, naming the cell; removing it makes the
    # plan current again (the contents count, not the revision).
    box = [0.6, -0.1, 0.0, 0.8, 0.1, 0.3]
    assert _put(fresh, [box], [WALL_FAR_AWAY]).status_code == 200
    (reason,) = fresh.get(plan_url).json()["outdated"]
    assert reason.startswith(
        "the cell: planned with 0 keep-out boxes and 1 plane; the cell now has 1 keep-out box "
        "and 1 plane (edited in the pendant at "
    ), reason
    assert fresh.get(f"/sessions/{sid}/trajectories").json()[-1]["outdated"] == [reason]
    assert _put(fresh, [], [WALL_FAR_AWAY]).status_code == 200
    assert fresh.get(plan_url).json()["outdated"] == []


def test_a_stored_cell_that_cannot_be_read_refuses_plans_until_set_again(fresh, scene_files):
    from recon.kinematics import HOME_Q_RAD

    assert _put(fresh, [], [WALL_FAR_AWAY]).status_code == 200
    away = (np.array(HOME_Q_RAD) + [0.2, 0.0, 0.0, 0.0, 0.1, 0.3]).tolist()
    sid, plans = planned_session(fresh, scene_files, [0.05], name="cell", start_q_rad=away)
    plan_url = f"/sessions/{sid}/trajectories/{plans[0.05]}"
    plan = fresh.get(plan_url).json()
    services = fresh.app.state.services
    with services.store.db.begin() as db:  # a damaged row (a hand edit, another version)
        db.get(CellRow, services.settings.cell_key).cell_planes = [[0, 0, 0, "x"]]
    refused = fresh.get("/cell")
    assert refused.status_code == 409 and refused.json()["code"] == "cell_unreadable"
    assert "set the boxes and planes again" in refused.json()["message"]
    # Nothing is planned against it; the plans stay listed, each saying why it cannot run.
    body = {"reconstruction_id": plan["inputs"]["reconstruction_id"], "speed_m_s": 0.05}
    for response in (
        fresh.post(f"/sessions/{sid}/trajectories", json=body),
        fresh.post(f"{plan_url}/move-to-start"),
    ):
        assert response.status_code == 409 and response.json()["code"] == "cell_unreadable"
    listed = fresh.get(f"/sessions/{sid}/trajectories")
    assert listed.status_code == 200
    assert any("cannot be read" in reason for reason in listed.json()[-1]["outdated"])
    # Setting it again from the revision the refusal names repairs it.
    revision = refused.json()["detail"]["revision"]
    assert _put(fresh, [], [WALL_FAR_AWAY], revision=revision).status_code == 200
    assert fresh.get("/cell").json()["cell_planes"] == [WALL_FAR_AWAY]
    assert fresh.get(plan_url).json()["outdated"] == []


def test_two_edits_from_one_view_at_once_store_exactly_one(tmp_path):
    url = make_settings(tmp_path).db_url
    stores = [Store(tmp_path, url) for _ in range(2)]
    barrier, outcomes = threading.Barrier(2), []

    def edit(store, planes):
        barrier.wait()
        try:
            store.set_cell("arm", boxes=[], planes=planes, expected_revision=0)
            outcomes.append("stored")
        except CellChangedError as exc:
            outcomes.append(exc.revision)

    threads = [
        threading.Thread(target=edit, args=(store, [[0, 0, 1, -float(n)]]))
        for n, store in enumerate(stores)
    ]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert sorted(outcomes, key=str) == [1, "stored"]
    assert stores[0].cell("arm").revision == 1


def test_two_arms_on_one_database_keep_their_own_cells(tmp_path):
    """Each arm's edited cell is stored under its name: the simulated arm by default, a real
    one by its model and address, or TEACHPATH_CELL_NAME."""
    assert make_settings(tmp_path).cell_key == "simulated"
    assert make_settings(tmp_path, ur_host="10.0.0.7").cell_key == "ur5e@10.0.0.7"
    left_settings = make_settings(tmp_path, cell_name="left cell")
    right_settings = make_settings(tmp_path, cell_name="right cell")
    with (
        TestClient(create_app(left_settings), headers=AUTH) as left,
        TestClient(create_app(right_settings), headers=AUTH) as right,
    ):
        assert _put(left, [], [WALL_FAR_AWAY]).status_code == 200
        assert right.get("/cell").json()["cell_planes"] == []
        assert right.get("/cell").json()["revision"] == 0
        assert left.get("/cell").json()["cell_planes"] == [WALL_FAR_AWAY]


def test_two_edits_of_a_stored_cell_from_one_view_store_exactly_one(tmp_path):
    """The compare-and-set holds for updates too (SQLite takes no row locks)."""
    url = make_settings(tmp_path).db_url
    stores = [Store(tmp_path, url) for _ in range(2)]
    stores[0].set_cell("arm", boxes=[], planes=[[0, 0, 1, -1.0]], expected_revision=0)
    for attempt in range(5):  # a race: tried a few times, never more than one may win
        revision = stores[0].cell("arm").revision
        barrier, outcomes = threading.Barrier(2), []

        def edit(store, offset, revision=revision, barrier=barrier, outcomes=outcomes):
            barrier.wait()
            try:
                store.set_cell(
                    "arm", boxes=[], planes=[[0, 0, 1, offset]], expected_revision=revision
                )
                outcomes.append("stored")
            except CellChangedError as exc:
                outcomes.append(exc.revision)

        threads = [
            threading.Thread(target=edit, args=(store, -2.0 - n)) for n, store in enumerate(stores)
        ]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join()
        assert sorted(outcomes, key=str) == [revision + 1, "stored"], (attempt, outcomes)
        assert stores[1].cell("arm").revision == revision + 1


def test_a_plane_means_what_the_pendant_draws_whatever_the_normals_length(fresh):
    """nx x + ny y + nz z >= d as typed: stored as the unit normal and the distance along it,
    and the planner keeps the arm on the same side as the formula says."""
    from service.pipelines import cell_for

    assert _put(fresh, [], [[-1.0, -1.0, 0.0, -1.0]]).status_code == 200
    (stored,) = fresh.get("/cell").json()["cell_planes"]
    half = 1 / np.sqrt(2)
    np.testing.assert_allclose(stored, [-half, -half, 0.0, -half], atol=1e-12)
    (plane,) = cell_for(None, None, None, [], [[-1.0, -1.0, 0.0, -1.0]]).planes
    for point in ([0.6, 0.6, 0.3], [0.3, 0.3, 0.3]):
        typed = -point[0] - point[1] - (-1.0)  # n . p - d as typed
        checked = float(plane.signed_distance_m(np.array(point)))
        assert np.sign(checked) == np.sign(typed)
        assert checked == pytest.approx(typed * half)
