"""What the pendant animates: a plan's preview (``GET .../trajectories/{id}/preview``) and an
execution's review (``GET .../executions/{id}/review``), checked against the plan's own file
and the arm's geometry, not against the code that made them."""

from __future__ import annotations

import numpy as np
import pytest

from recon import kinematics
from recon.paths import Phase
from service.preview import thinned, trajectory_preview, window_min
from service.tasks import load_trajectory
from tests.service.conftest import planned_session, wait


@pytest.fixture(scope="module")
def planned(client, scene_files):
    sid, trajectories = planned_session(client, scene_files, (0.05,), name="preview")
    return sid, trajectories[0.05]


@pytest.fixture(scope="module")
def preview(client, planned):
    sid, tid = planned
    response = client.get(f"/sessions/{sid}/trajectories/{tid}/preview?max_samples=400")
    assert response.status_code == 200, response.text
    assert response.headers["content-type"] == "application/json"
    return response.json()


def _csv(client, sid, tid):
    lines = [
        line
        for line in client.get(f"/sessions/{sid}/trajectories/{tid}/csv").text.splitlines()
        if line and not line.startswith("#")
    ]
    header = lines[0].split(",")
    numeric = [i for i, name in enumerate(header) if name != "phase"]
    cells = [line.split(",") for line in lines[1:]]
    values = np.array([[float(row[i]) for i in numeric] for row in cells])
    return [header[i] for i in numeric], values


def test_thinning_keeps_the_ends_and_every_phase_start():
    phases = np.r_[np.zeros(997), 1, np.full(1000, 2), np.full(2, 3)].astype(np.int8)
    keep = thinned(len(phases), 20, phases)
    assert keep[0] == 0 and keep[-1] == len(phases) - 1
    for start in (997, 998, 1998):
        assert start in keep
    assert len(keep) <= 24


def test_a_thinned_margin_keeps_the_dip_between_the_samples_sent():
    values = np.ones(100)
    values[57] = -0.5  # not a kept sample
    keep = np.arange(0, 100, 10)
    assert window_min(values, keep).min() == -0.5
    assert window_min(values, keep)[5] == -0.5


def test_the_preview_follows_the_plan_file(client, planned, preview):
    sid, tid = planned
    header, values = _csv(client, sid, tid)
    t_file = values[:, header.index("t")]
    t = np.array(preview["t_s"])
    assert t[0] == pytest.approx(t_file[0]) and t[-1] == pytest.approx(t_file[-1], abs=1e-4)
    assert np.all(np.diff(t) > 0) and len(t) <= 410
    assert preview["duration_s"] == pytest.approx(t_file[-1] - t_file[0], abs=1e-4)
    rows = np.searchsorted(t_file, t - 1e-6)
    tcp_file = values[rows][:, [header.index(c) for c in ("x", "y", "z")]]
    q_file = values[rows][:, [header.index(f"q{j}") for j in range(6)]]
    joints = np.array(preview["joints_m"])
    assert joints.shape == (len(t), 8, 3)
    # The TCP the arm figure ends in is the planned TCP of the file, and the joints are the file's.
    assert np.abs(joints[:, 7] - tcp_file).max() < 2e-5
    assert np.abs(np.array(preview["q_deg"]) - np.degrees(q_file)).max() < 2e-3
    # The tool axis glyphs point along the file's TCP orientation (its rotation vector's z).
    from scipy.spatial.transform import Rotation

    rotvec = values[rows][:, [header.index(c) for c in ("rx", "ry", "rz")]]
    axis_file = Rotation.from_rotvec(rotvec).apply([0.0, 0.0, 1.0])
    assert np.abs(np.array(preview["tool_axis"]) - axis_file).max() < 2e-4
    # Every phase of the plan is in the preview, in order.
    names = [preview["phases"][p] for p in preview["phase"]]
    assert list(dict.fromkeys(names))[:3] == ["transit", "approach", "process"]
    assert set(names) >= {"transit", "approach", "process", "retract"}


def test_the_arm_figure_is_rigid(preview):
    """Base to shoulder is d1 and the upper arm |a2| in every pose: the figure is the arm's."""
    arm = kinematics.model(preview["robot"])
    joints = np.array(preview["joints_m"])
    base, shoulder = joints[:, 0], joints[:, 1]
    assert np.allclose(np.linalg.norm(shoulder - base, axis=1), arm.d[0], atol=2e-5)
    assert np.allclose(np.linalg.norm(joints[:, 2] - shoulder, axis=1), abs(arm.a[1]), atol=2e-5)
    assert np.allclose(
        np.linalg.norm(joints[:, 3] - joints[:, 2], axis=1), abs(arm.a[2]), atol=2e-5
    )


def test_the_margins_per_waypoint_agree_with_the_plans_summary(client, planned, preview):
    sid, tid = planned
    summary = client.get(f"/sessions/{sid}/trajectories/{tid}").json()["summary"]
    assert min(preview["limit_margin_deg"]) == pytest.approx(
        np.degrees(summary["min_limit_margin_rad"]), abs=1e-2
    )
    assert summary["min_clearance_m"] is not None
    assert min(preview["clearance_m"]) == pytest.approx(summary["min_clearance_m"], abs=1e-5)
    process = np.array(preview["phase"]) == int(Phase.PROCESS)
    wrist = np.array(preview["wrist_singularity"])[process]
    # The preview rounds to four decimals (half a unit of 1e-4 either way), the plan's samples
    # lie between the preview's.
    assert wrist.min() >= summary["min_wrist_singularity"] - 1.5e-4
    speed = np.array(preview["speed_m_s"])[process]
    assert np.median(speed) == pytest.approx(preview["requested_speed_m_s"], rel=0.1)
    for drop in preview["speed_drops"]:
        assert 0 <= drop["start_s"] <= drop["end_s"] <= preview["duration_s"] + 1e-9
        assert drop["cause"]


def test_the_review_of_a_dry_run_is_where_the_arm_went(client, planned, preview):
    sid, tid = planned
    job = wait(
        client, client.post(f"/sessions/{sid}/executions", json={"trajectory_id": tid}).json()
    )
    assert job["state"] == "succeeded", job
    eid = job["result"]["execution_id"]
    summary = client.get(f"/sessions/{sid}/executions/{eid}").json()["summary"]
    response = client.get(f"/sessions/{sid}/executions/{eid}/review?max_samples=300")
    assert response.status_code == 200, response.text
    review = response.json()
    assert len(review["t_s"]) <= 310
    assert review["max_off_path_m"] >= summary["max_path_deviation_m"] - 1e-9
    assert max(review["off_path_m"]) == pytest.approx(review["max_off_path_m"], abs=1e-6)
    # Independently of the review's code: the executed joints of the CSV through the arm's
    # kinematics, against every sample of the planned TCP in the plan's file.
    from scipy.spatial import cKDTree

    header, values = _csv(client, sid, tid)
    planned_tcp = values[:, [header.index(c) for c in ("x", "y", "z")]]
    lines = client.get(f"/sessions/{sid}/executions/{eid}/csv").text.splitlines()
    executed = np.array([[float(v) for v in line.split(",")[7:13]] for line in lines[1:]])
    arm = kinematics.model(preview["robot"])
    flange = kinematics.forward(arm, executed)
    plan_q = values[:, [header.index(f"q{j}") for j in range(6)]]
    plan_flange = kinematics.forward(arm, plan_q)
    # The TCP rides rigidly on the flange: carry the plan's first offset to the executed poses.
    offset = np.linalg.solve(plan_flange[0], np.r_[planned_tcp[0], 1.0])
    executed_tcp = (flange @ offset)[:, :3]
    gap, _ = cKDTree(planned_tcp).query(executed_tcp)
    spacing = np.linalg.norm(np.diff(planned_tcp, axis=0), axis=1).max()
    assert gap.max() <= review["max_off_path_m"] + spacing / 2 + 1e-5
    actual = np.array(review["actual_tcp_m"])
    gap_sent, _ = cKDTree(executed_tcp).query(actual)
    assert gap_sent.max() < 1e-4  # the review's TCP is where the executed joints put it


@pytest.mark.parametrize(
    "query",
    [
        "max_samples=0",
        "max_samples=9",
        "max_samples=1e99",
        "max_samples=99999999999999999999",
        "max_samples=x",
    ],
)
def test_bad_sample_counts_are_refused(client, planned, query):
    sid, tid = planned
    response = client.get(f"/sessions/{sid}/trajectories/{tid}/preview?{query}")
    assert response.status_code == 422


def test_unknown_artifacts_are_404(client, planned):
    sid, _ = planned
    for path in ("trajectories/trj_000000000000/preview", "executions/exe_000000000000/review"):
        response = client.get(f"/sessions/{sid}/{path}")
        assert response.status_code == 404 and response.json()["code"] == "not_found"


def test_the_difference_of_two_reconstructions_is_measured_point_by_point(client, planned):
    """A reconstruction against itself differs by nothing; against one made with another
    radius by what the two CSVs say (an independent nearest-neighbour search)."""
    from scipy.spatial import cKDTree

    sid, _ = planned
    first = client.get(f"/sessions/{sid}/reconstructions").json()[0]["id"]
    job = wait(
        client, client.post(f"/sessions/{sid}/reconstructions", json={"radius_m": 0.004}).json()
    )
    second = job["result"]["reconstruction_id"]
    same = client.get(f"/sessions/{sid}/reconstructions/{first}/difference?against={first}").json()
    assert same["max_m"] < 2e-5  # the reference polyline is resampled at 20 um
    response = client.get(f"/sessions/{sid}/reconstructions/{second}/difference?against={first}")
    assert response.status_code == 200
    body = response.json()

    def xyz(rid):
        text = client.get(f"/sessions/{sid}/reconstructions/{rid}/csv").text
        return np.loadtxt(text.splitlines()[1:], delimiter=",", usecols=(0, 1, 2))

    a, b = xyz(first), xyz(second)
    assert np.allclose(body["points_m"], b, atol=1e-6)
    # The distance to the other's polyline is at most that to its nearest vertex, and at least
    # the nearest vertex distance less half the spacing's chord sag (1 mm spacing).
    nearest, _ = cKDTree(a).query(b)
    difference = np.array(body["difference_m"])
    assert np.all(difference <= nearest + 2e-5)
    assert np.all(difference >= nearest - 0.6e-3)
    assert body["max_m"] == pytest.approx(difference.max(), abs=1e-7) and body["max_m"] > 0
    assert difference[body["at_index"]] == pytest.approx(body["max_m"], abs=1e-7)


@pytest.mark.parametrize(
    "query", ["", "?against=", "?against=rcn_000000000000", "?against=" + "x" * 65]
)
def test_a_difference_needs_an_existing_other(client, planned, query):
    sid, _ = planned
    first = client.get(f"/sessions/{sid}/reconstructions").json()[0]["id"]
    response = client.get(f"/sessions/{sid}/reconstructions/{first}/difference{query}")
    assert response.status_code in (404, 422) and "code" in response.json()


def test_an_endless_joint_and_an_empty_cell_are_null_not_infinite(client, planned):
    """A UR3e's wrist 3 turns without end and a sample with nothing of the cell in reach has
    no clearance: JSON has no inf, so both are null (the route would refuse the numbers)."""
    import dataclasses
    import json

    _sid, tid = planned
    row = client.app.state.services.store.artifact(tid, kind="trajectory")
    path = client.app.state.services.store.path_of(row)
    trajectory = dataclasses.replace(load_trajectory(path, row.summary), robot="ur3e")
    clearance = np.full(len(trajectory.t_s), np.inf)
    clearance[:10] = 0.02
    body = trajectory_preview(trajectory, clearance, max_samples=50)
    json.dumps(body, allow_nan=False)
    assert body["q_max_deg"][5] is None and body["q_min_deg"][5] is None
    assert body["q_max_deg"][0] == pytest.approx(360.0)
    assert body["clearance_m"][0] == pytest.approx(0.02) and body["clearance_m"][-1] is None


def test_a_client_that_takes_no_gzip_gets_plain_json(client, planned):
    sid, tid = planned
    url = f"/sessions/{sid}/trajectories/{tid}/preview?max_samples=20"
    plain = client.get(url, headers={"Accept-Encoding": "identity"})
    assert "content-encoding" not in plain.headers and plain.headers["vary"] == "Accept-Encoding"
    zipped = client.get(url, headers={"Accept-Encoding": "gzip"})
    assert zipped.headers["content-encoding"] == "gzip"
    assert plain.json() == zipped.json()
