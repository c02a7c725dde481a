"""The inputs over REST: calibrations (set, pivot, point pairs), cleaned uploads, stored
registration guesses, and a database from an earlier version."""

from __future__ import annotations

import io
import sqlite3

import numpy as np
import pytest
from fastapi.testclient import TestClient
from scipy.spatial.transform import Rotation

from drivers.errors import InputFileError
from recon import scenes
from recon.inputs import Recording
from service.app import create_app
from service.capture_runner import HEADER, read_capture_file
from tests.recon.test_calibrate import PIVOT_M, TIP_M, pivot_recording
from tests.service.conftest import AUTH, make_settings, wait


def _csv(recording: Recording) -> bytes:
    buffer = io.StringIO()
    columns = ["t", "x", "y", "z"] + (
        ["qx", "qy", "qz", "qw"] if recording.orientations_xyzw is not None else []
    )
    parts = [recording.t_s[:, None], recording.points_m]
    if recording.orientations_xyzw is not None:
        parts.append(recording.orientations_xyzw)
    np.savetxt(buffer, np.hstack(parts), delimiter=",", header=",".join(columns), comments="")
    return buffer.getvalue().encode()


@pytest.fixture()
def sid(client):
    return client.post("/sessions", json={"name": "inputs"}).json()["id"]


def test_calibrations_are_set_partially_and_cleared_explicitly(client, sid):
    T = np.eye(4)
    T[:3, 3] = [0.1, 0.2, 0.3]
    body = client.put(f"/sessions/{sid}/calibration", json={"T_scan_tracker": T.tolist()}).json()
    assert body["T_scan_tracker"] == T.tolist() and body["T_base_tracker"] is None
    body = client.put(f"/sessions/{sid}/calibration", json={"tip_offset_m": [0, 0, 0.12]}).json()
    assert body["T_scan_tracker"] == T.tolist() and body["tip_offset_m"] == [0, 0, 0.12]
    body = client.put(f"/sessions/{sid}/calibration", json={"T_scan_tracker": None}).json()
    assert body["T_scan_tracker"] is None and body["tip_offset_m"] == [0, 0, 0.12]


@pytest.mark.parametrize(
    "body",
    [
        {},
        {"tip_offset_m": [0, 0, 5]},
        {"tip_offset_m": [0, 0]},
        {"T_scan_tracker": [[1, 0]]},
        {"T_scan_tracker": (2 * np.eye(4)).tolist()},
        {"tip": [0, 0, 0.1]},
    ],
    ids=["empty", "tip-too-long", "tip-short", "not-4x4", "not-rigid", "unknown-field"],
)
def test_bad_calibrations_change_nothing(client, sid, body):
    before = client.get(f"/sessions/{sid}").json()
    response = client.put(f"/sessions/{sid}/calibration", json=body)
    assert response.status_code == 422 and response.json()["code"] == "invalid_request"
    assert client.get(f"/sessions/{sid}").json() == before


def test_pivot_calibration_sets_the_tip_and_later_uploads_use_it(client, sid):
    position, quat = pivot_recording(0)
    t = np.arange(len(position)) / 240.0
    pivot = Recording(points_m=position, t_s=t, orientations_xyzw=quat)
    response = client.post(
        f"/sessions/{sid}/calibration/pivot", files={"file": ("pivot.csv", _csv(pivot))}
    )
    assert response.status_code == 200, response.text
    body = response.json()
    assert np.linalg.norm(np.array(body["result"]["tip_offset_m"]) - TIP_M) < 2e-4
    assert np.linalg.norm(np.array(body["result"]["pivot_point_m"]) - PIVOT_M) < 2e-4
    assert body["session"]["tip_offset_m"] == body["result"]["tip_offset_m"]
    assert body["session"]["calibration_report"]["pivot"]["source_name"] == "pivot.csv"
    # A trace of the rigid body uploaded now lands on the tip: the pen held upright and moved.
    upright = Rotation.from_euler("x", 180, degrees=True)
    s = np.linspace(0, 0.1, 400)
    tip_path = np.column_stack([0.3 + s, 0.2 + 0 * s, 0.05 + 0 * s])
    body_path = tip_path - upright.apply(np.array(body["result"]["tip_offset_m"]))
    trace = Recording(
        points_m=body_path,
        t_s=np.arange(len(s)) / 240.0,
        orientations_xyzw=np.tile(upright.as_quat(), (len(s), 1)),
    )
    artifact = client.put(f"/sessions/{sid}/recording", files={"file": ("t.csv", _csv(trace))})
    assert artifact.status_code == 201, artifact.text
    assert artifact.json()["summary"]["tip_offset_applied"]
    stored = client.get(f"/sessions/{sid}/recordings/{artifact.json()['id']}/csv").text
    xyz = np.loadtxt(io.StringIO(stored), delimiter=",", skiprows=1)[:, 1:4]
    np.testing.assert_allclose(xyz, tip_path, atol=1e-9)
    # Replaying that recording into a capture keeps it at the tip (no second offset).
    cid = client.post(
        f"/sessions/{sid}/captures",
        json={"source": {"kind": "replay", "recording_id": artifact.json()["id"], "speed": None}},
    ).json()["id"]
    captured = _wait_capture(client, sid, cid, timeout_s=20.0)
    assert captured["state"] == "stopped", captured
    replayed = client.get(f"/sessions/{sid}/recordings/{captured['recording_id']}/csv").text
    xyz = np.loadtxt(io.StringIO(replayed), delimiter=",", skiprows=1)[:, 1:4]
    np.testing.assert_allclose(xyz, tip_path, atol=1e-6)
    # A position-only file holds tip positions already: used as it is, and the summary says so.
    plain = Recording(points_m=tip_path, t_s=trace.t_s)
    artifact = client.put(f"/sessions/{sid}/recording", files={"file": ("p.csv", _csv(plain))})
    assert artifact.status_code == 201, artifact.text
    summary = artifact.json()["summary"]
    assert not summary["tip_offset_applied"]
    assert any("tip offset was not applied" in note for note in summary["notes"])


def _capture_lines(t_s):
    return "".join(f"{t:.6f},{0.01 * t:.9g},0,0,0,0,0,1,1\n" for t in t_s)


def test_a_capture_file_with_a_torn_last_line_keeps_the_rest(tmp_path):
    path = tmp_path / "cap.csv"
    t = np.arange(100) / 240.0
    path.write_text(HEADER + _capture_lines(t) + "0.42083,0.0042")  # died mid-write
    batch = read_capture_file(path)
    np.testing.assert_allclose(batch.t_s, np.round(t, 6))
    assert batch.orientation_xyzw is not None and batch.valid.all()


def test_a_capture_across_a_stream_restart_keeps_the_first_stream(tmp_path):
    path = tmp_path / "cap.csv"
    first, second = np.arange(100) / 240.0, np.arange(50) / 240.0  # the clock starts again
    path.write_text(HEADER + _capture_lines(first) + _capture_lines(second))
    batch = read_capture_file(path)
    assert len(batch) == 100 and np.all(np.diff(batch.t_s) > 0)


def test_a_damaged_capture_file_is_a_clear_error(tmp_path):
    path = tmp_path / "cap.csv"
    path.write_text(HEADER + "0.1,0.2,oops,0,0,0,0,1,1\n" + _capture_lines([0.2]))
    with pytest.raises(InputFileError, match="line 2"):
        read_capture_file(path)


def test_pivot_calibration_bad_input_changes_nothing(client, sid):
    before = client.get(f"/sessions/{sid}").json()
    position, _quat = pivot_recording(0)
    t = np.arange(len(position)) / 240.0
    for name, content, code in (
        ("p.csv", _csv(Recording(points_m=position, t_s=t)), "invalid_file"),  # no quaternions
        ("p.csv", b"x,y,z\n", "invalid_file"),
        ("p.trc", b"...", "unknown_format"),
    ):
        response = client.post(
            f"/sessions/{sid}/calibration/pivot", files={"file": (name, content)}
        )
        assert response.status_code == 422 and response.json()["code"] == code, response.text
    # The pen turned about one axis only: degenerate.
    angle = np.linspace(-0.5, 0.5, 300)
    pen = Rotation.from_rotvec(np.column_stack([angle, 0 * angle, 0 * angle]))
    one_axis = Recording(
        points_m=PIVOT_M - pen.apply(TIP_M),
        t_s=np.arange(300) / 240.0,
        orientations_xyzw=pen.as_quat(),
    )
    response = client.post(
        f"/sessions/{sid}/calibration/pivot", files={"file": ("p.csv", _csv(one_axis))}
    )
    assert response.status_code == 422 and "several directions" in response.json()["message"]
    assert client.get(f"/sessions/{sid}").json() == before


def _pairs(outlier_at=None):
    rng = np.random.default_rng(3)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("z", 90, degrees=True).as_matrix()
    T[:3, 3] = [0.5, -0.1, 0.02]
    tracker = rng.uniform(-0.2, 0.2, (6, 3))
    base = tracker @ T[:3, :3].T + T[:3, 3] + rng.normal(0, 5e-5, (6, 3))
    if outlier_at is not None:
        base[outlier_at] += [0.004, 0, 0]
    return T, [
        {"base": b.tolist(), "tracker": t.tolist()} for b, t in zip(base, tracker, strict=True)
    ]


def test_base_calibration_from_point_pairs_flags_an_outlier(client, sid):
    T, pairs = _pairs(outlier_at=2)
    response = client.post(f"/sessions/{sid}/calibration/base", json={"pairs": pairs})
    assert response.status_code == 200, response.text
    result = response.json()["result"]
    assert result["suspect"] == [False, False, True, False, False, False]
    assert not result["used"][2] and "re-measure" in result["report"][1]
    np.testing.assert_allclose(response.json()["session"]["T_base_tracker"], T, atol=3e-4)
    # In millimetres, the same.
    mm = [
        {"base": [v * 1e3 for v in p["base"]], "tracker": [v * 1e3 for v in p["tracker"]]}
        for p in _pairs()[1]
    ]
    response = client.post(f"/sessions/{sid}/calibration/base", json={"pairs": mm, "units": "mm"})
    np.testing.assert_allclose(response.json()["result"]["T_base_tracker"], T, atol=3e-4)


@pytest.mark.parametrize(
    "body, code",
    [
        ({"pairs": _pairs()[1][:2]}, "invalid_request"),
        ({"pairs": [{"base": [0, 0, 0], "tracker": [0, 0, float("nan")]}] * 3}, "invalid_request"),
        (
            {"pairs": [{"base": [i, 2 * i, 0], "tracker": [i, 2 * i, 0]} for i in range(4)]},
            "degenerate_input",
        ),
        ({"pairs": _pairs()[1], "tolerance_m": 0}, "invalid_request"),
    ],
    ids=["two-pairs", "nan", "collinear", "zero-tolerance"],
)
def test_bad_point_pairs_change_nothing(client, sid, body, code):
    import json

    before = client.get(f"/sessions/{sid}").json()
    response = client.post(
        f"/sessions/{sid}/calibration/base",
        content=json.dumps(body, allow_nan=True),
        headers={**AUTH, "Content-Type": "application/json"},
    )
    assert response.status_code == 422 and response.json()["code"] == code, response.text
    assert client.get(f"/sessions/{sid}").json() == before


def test_a_trace_with_a_long_dropout_is_split_and_a_piece_can_be_chosen(client, sid):
    t = np.concatenate([np.arange(240), np.arange(360, 840)]) / 240.0  # 0.5 s lost after 1 s
    points = np.column_stack([0.05 * t, 0.0 * t, 0.0 * t])
    content = _csv(Recording(points_m=points, t_s=t))
    first = client.put(f"/sessions/{sid}/recording", files={"file": ("t.csv", content)}).json()
    assert first["summary"]["n_pieces"] == 2 and first["summary"]["piece"] == 1
    assert first["summary"]["n_samples"] == 480
    assert any("split" in line for line in first["summary"]["gap_report"])
    chosen = client.put(
        f"/sessions/{sid}/recording", files={"file": ("t.csv", content)}, data={"piece": "0"}
    ).json()
    assert chosen["summary"]["piece"] == 0 and chosen["summary"]["n_samples"] == 240
    response = client.put(
        f"/sessions/{sid}/recording", files={"file": ("t.csv", content)}, data={"piece": "5"}
    )
    assert response.status_code == 422 and "piece 5 does not exist" in response.json()["message"]
    assert client.get(f"/sessions/{sid}").json()["recording_id"] == chosen["id"]
    for bad in ("-1", "first", "1.5", "9" * 40, "all; drop"):
        response = client.put(
            f"/sessions/{sid}/recording", files={"file": ("t.csv", content)}, data={"piece": bad}
        )
        assert response.status_code == 422 and response.json()["code"] == "invalid_request", bad
    assert client.get(f"/sessions/{sid}").json()["recording_id"] == chosen["id"]
    both = client.put(
        f"/sessions/{sid}/recording", files={"file": ("t.csv", content)}, data={"piece": "all"}
    ).json()
    assert both["summary"]["piece"] == "all" and both["summary"]["n_pieces"] == 2
    assert both["summary"]["n_samples"] == 720
    # The traced length, not the untraced half second between the pieces.
    assert both["summary"]["length_m"] == pytest.approx(0.05 * (239 + 479) / 240.0, rel=1e-6)


def test_a_trace_in_two_pieces_is_reconstructed_planned_and_dry_run_with_a_lift_between(
    client, scene_files
):
    """The box-corner trace with 0.4 s lost at 30 %, uploaded whole (piece=all)."""
    from tests.service.conftest import T_BASE_TRACKER, wait

    scene = scenes.box_corner(0)
    rec = scene.recording
    cut = rec.t_s[int(0.3 * len(rec))]
    keep = (rec.t_s < cut - 0.2) | (rec.t_s > cut + 0.2)
    content = _csv(Recording(points_m=rec.points_m[keep], t_s=rec.t_s[keep]))
    sid = client.post("/sessions", json={"name": "two pieces"}).json()["id"]
    recording = client.put(
        f"/sessions/{sid}/recording", files={"file": ("t.csv", content)}, data={"piece": "all"}
    ).json()
    assert recording["summary"]["n_pieces"] == 2
    client.put(f"/sessions/{sid}/scan", files={"file": ("scan.ply", scene_files["scan"])})
    client.put(f"/sessions/{sid}/calibration", json={"T_base_tracker": T_BASE_TRACKER})
    job = wait(client, client.post(f"/sessions/{sid}/reconstructions", json={}).json())
    assert job["state"] == "succeeded", job
    rid = job["result"]["reconstruction_id"]
    summary = client.get(f"/sessions/{sid}/reconstructions/{rid}").json()["summary"]
    assert summary["n_pieces"] == 2
    csv = client.get(f"/sessions/{sid}/reconstructions/{rid}/csv").text.splitlines()
    piece = csv[0].split(",").index("piece")
    assert csv[1].split(",")[piece] == "0" and csv[-1].split(",")[piece] == "1"
    job = wait(
        client,
        client.post(
            f"/sessions/{sid}/trajectories", json={"reconstruction_id": rid, "speed_m_s": 0.05}
        ).json(),
    )
    assert job["state"] == "succeeded", job
    tid = job["result"]["trajectory_id"]
    planned = client.get(f"/sessions/{sid}/trajectories/{tid}").json()["summary"]
    assert planned["n_pieces"] == 2 and "in 2 pieces" in planned["report"][0]
    phases = [
        row.split(",")[-1]
        for row in client.get(f"/sessions/{sid}/trajectories/{tid}/csv").text.splitlines()[2:]
    ]
    runs = [p for i, p in enumerate(phases) if i == 0 or phases[i - 1] != p]
    assert runs == ["transit", "approach", "process", "retract"] * 2
    program = client.get(f"/sessions/{sid}/trajectories/{tid}/urscript").text
    assert program.count("movel(") == 4 and program.count("# transit") == 2
    job = wait(
        client, client.post(f"/sessions/{sid}/executions", json={"trajectory_id": tid}).json()
    )
    assert job["state"] == "succeeded", job
    dry = client.get(f"/sessions/{sid}/executions/{job['result']['execution_id']}").json()
    assert dry["summary"]["completed"]
    # Both transits executed, as planned (a completed run got through every phase).
    assert dry["summary"]["executed_phase_durations_s"]["transit"] == pytest.approx(
        planned["phase_durations_s"]["transit"], abs=0.02
    )
    assert dry["summary"]["executed_phase_durations_s"]["process"] == pytest.approx(
        planned["phase_durations_s"]["process"], abs=0.02
    )


def test_reconstruction_starts_from_the_sessions_scan_calibration(client, scene_files):
    sid = client.post("/sessions", json={"name": "calibrated"}).json()["id"]
    client.put(f"/sessions/{sid}/recording", files={"file": ("trace.csv", scene_files["trace"])})
    client.put(f"/sessions/{sid}/scan", files={"file": ("scan.ply", scene_files["scan"])})
    from recon import scenes

    T_true = scenes.box_corner(0).T_scan_tracker
    client.put(f"/sessions/{sid}/calibration", json={"T_scan_tracker": np.asarray(T_true).tolist()})
    job = wait(
        client, client.post(f"/sessions/{sid}/reconstructions", json={"registration": False}).json()
    )
    assert job["state"] == "succeeded", job
    recon = client.get(
        f"/sessions/{sid}/reconstructions/{job['result']['reconstruction_id']}"
    ).json()
    np.testing.assert_allclose(recon["params"]["T_scan_tracker_init"], T_true)
    np.testing.assert_allclose(recon["summary"]["T_scan_tracker"], T_true)


def test_a_database_from_an_earlier_version_is_upgraded(tmp_path):
    """Sessions made before the calibration columns existed keep working."""
    data = tmp_path / "data"
    data.mkdir()
    with sqlite3.connect(data / "teachpath.db") as db:
        db.execute(
            "CREATE TABLE sessions (id VARCHAR(32) PRIMARY KEY, name VARCHAR(200), "
            "created_at DATETIME, deleted_at DATETIME, recording_id VARCHAR(32), "
            "scan_id VARCHAR(32), T_base_tracker JSON)"
        )
        db.execute(
            "INSERT INTO sessions VALUES ('ses_old', 'old', '2026-11-01 10:00:00.000000', "
            "NULL, NULL, NULL, NULL)"
        )
    # An SQLite file of its own, also when the suite runs on PostgreSQL (test_database.py
    # upgrades earlier PostgreSQL databases).
    settings = make_settings(data, database_url=f"sqlite:///{data / 'teachpath.db'}")
    with TestClient(create_app(settings), headers=AUTH) as client:
        body = client.get("/sessions/ses_old").json()
        assert body["name"] == "old" and body["tip_offset_m"] is None
        body = client.put("/sessions/ses_old/calibration", json={"tip_offset_m": [0, 0, 0.1]})
        assert body.status_code == 200 and body.json()["tip_offset_m"] == [0, 0, 0.1]


def test_motive_and_c3d_uploads_with_their_options(client, sid, tmp_path):
    from tests.drivers.tracking_fixtures import helix, write_c3d, write_motive_csv

    t, position, quat = helix(720)
    lost = np.zeros(len(t), bool)
    lost[100:105] = True
    write_motive_csv(
        tmp_path / "take.csv",
        t,
        np.stack([position, position + 0.3]),
        np.stack([quat, quat]),
        rigid_bodies=["pen", "fixture"],
        lost=np.stack([lost, lost]),
    )
    content = (tmp_path / "take.csv").read_bytes()
    response = client.put(f"/sessions/{sid}/recording", files={"file": ("take.csv", content)})
    assert response.status_code == 422 and "pen" in response.json()["message"]
    response = client.put(
        f"/sessions/{sid}/recording",
        files={"file": ("take.csv", content)},
        data={"rigid_body": "pen"},
    )
    assert response.status_code == 201, response.text
    summary = response.json()["summary"]
    assert summary["format"] == "motive" and summary["rigid_body"] == "pen"
    assert summary["gaps"]["n_bridged"] == 5 and summary["has_orientations"]
    assert response.json()["params"]["units"] == "Millimeters"

    write_c3d(tmp_path / "take.c3d", ["tip", "tail"], np.stack([position, position], 1), 240.0)
    content = (tmp_path / "take.c3d").read_bytes()
    response = client.put(
        f"/sessions/{sid}/recording",
        files={"file": ("take.c3d", content)},
        data={"marker": "nose"},
    )
    assert response.status_code == 422 and "tip" in response.json()["message"]
    response = client.put(
        f"/sessions/{sid}/recording",
        files={"file": ("take.c3d", content)},
        data={"marker": "tip"},
    )
    assert response.status_code == 201 and response.json()["summary"]["format"] == "c3d"


def test_a_still_pen_and_an_rtde_recording_uploaded(client, sid, tmp_path):
    from tests.drivers.test_readers import _still_pen
    from tests.drivers.test_rtde_csv import rtde_recording
    from tests.drivers.tracking_fixtures import helix, write_motive_csv

    before = client.get(f"/sessions/{sid}").json()
    t, position, quat = _still_pen()
    content = write_motive_csv(tmp_path / "still.csv", t, position, quat).read_bytes()
    response = client.put(f"/sessions/{sid}/recording", files={"file": ("still.csv", content)})
    assert response.status_code == 422 and response.json()["code"] == "invalid_file"
    assert "the pen did not move (extent 0.04 mm)" in response.json()["message"]
    assert client.get(f"/sessions/{sid}").json() == before
    t, position, quat = helix(500, 125.0)
    rotvec = Rotation.from_quat(quat).as_rotvec()
    content = rtde_recording(t, position, rotvec, ",")
    response = client.put(f"/sessions/{sid}/recording", files={"file": ("arm.csv", content)})
    assert response.status_code == 201, response.text
    summary = response.json()["summary"]
    assert summary["format"] == "rtde" and summary["has_orientations"]
    assert summary["frame"] == "robot base"


def _wait_capture(client, sid, cid, timeout_s=60.0):
    import time

    deadline = time.monotonic() + timeout_s
    while True:
        body = client.get(f"/sessions/{sid}/captures/{cid}").json()
        if body["state"] != "running" or time.monotonic() > deadline:
            return body
        time.sleep(0.1)


@pytest.mark.timeout(120)
def test_a_live_natnet_capture_records_every_frame(client, sid):
    from drivers.tracking.natnet_server import NatNetReplayServer
    from tests.drivers.test_natnet import synthetic

    recording = synthetic(2.0)  # 720 frames at 360 Hz
    with NatNetReplayServer(recording, rigid_body="Pen", command_port=0) as server:
        cid = client.post(
            f"/sessions/{sid}/captures",
            json={
                "source": {
                    "kind": "natnet",
                    "server": "127.0.0.1",
                    "rigid_body": "Pen",
                    "command_port": server.command_port,
                }
            },
        ).json()["id"]
        server.wait_done(30.0)
        # No pause: stopping hands the receiver's last frames to the capture before it ends.
        stopped = client.post(f"/sessions/{sid}/captures/{cid}/stop").json()
    assert stopped["state"] == "stopped" and stopped["n_samples"] == len(recording), stopped
    stored = client.get(f"/sessions/{sid}/recordings/{stopped['recording_id']}").json()
    assert stored["summary"]["n_samples"] == len(recording)
    assert stored["summary"]["has_orientations"]
    csv_text = client.get(f"/sessions/{sid}/recordings/{stopped['recording_id']}/csv").text
    xyz = np.loadtxt(io.StringIO(csv_text), delimiter=",", skiprows=1)[:, 1:4]
    np.testing.assert_allclose(xyz, recording.points_m, atol=1e-6)  # float32 on the wire


@pytest.mark.timeout(120)
def test_natnet_captures_that_cannot_work_fail_with_a_reason(client, sid):
    from drivers.tracking.natnet_server import NatNetReplayServer
    from tests.drivers.test_natnet import synthetic

    with NatNetReplayServer(synthetic(1.0), rigid_body="Pen", command_port=0) as server:
        cid = client.post(
            f"/sessions/{sid}/captures",
            json={
                "source": {
                    "kind": "natnet",
                    "server": "127.0.0.1",
                    "rigid_body": "Stylus",
                    "command_port": server.command_port,
                }
            },
        ).json()["id"]
        body = _wait_capture(client, sid, cid)
    assert body["state"] == "failed" and "Stylus" in body["error"] and "Pen" in body["error"]
    assert body["recording_id"] is None
    # Nobody answers on this port.
    import socket

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind(("127.0.0.1", 0))
        free_port = probe.getsockname()[1]
    cid = client.post(
        f"/sessions/{sid}/captures",
        json={
            "source": {
                "kind": "natnet",
                "server": "127.0.0.1",
                "rigid_body": "Pen",
                "command_port": free_port,
                "timeout_s": 1.0,
            }
        },
    ).json()["id"]
    body = _wait_capture(client, sid, cid)
    assert body["state"] == "failed" and "no NatNet server answered" in body["error"]
    for source in (
        {"kind": "natnet", "server": "127.0.0.1"},
        {"kind": "natnet", "server": "127.0.0.1", "rigid_body": "Pen", "command_port": 0},
        {"kind": "vicon", "server": "127.0.0.1"},
    ):
        response = client.post(f"/sessions/{sid}/captures", json={"source": source})
        assert response.status_code == 422 and response.json()["code"] == "invalid_request"


def test_e57_and_rgbd_zip_scans_upload(client, sid, tmp_path):
    from tests.drivers.test_scan_readers import make_sequence, write_e57, zip_folder

    rng = np.random.default_rng(0)
    points = rng.uniform(-0.1, 0.1, (2000, 3))
    write_e57(tmp_path / "scan.e57", [(points, [1.0, 0, 0, 0], [0.0, 0.0, 0.5], None)])
    response = client.put(
        f"/sessions/{sid}/scan", files={"file": ("scan.e57", (tmp_path / "scan.e57").read_bytes())}
    )
    assert response.status_code == 201, response.text
    assert response.json()["summary"]["format"] == "e57"
    assert response.json()["summary"]["n_points"] == 2000

    make_sequence(tmp_path / "frames", 3)
    archive = zip_folder(tmp_path / "frames", tmp_path / "frames.zip").read_bytes()
    response = client.put(
        f"/sessions/{sid}/scan",
        files={"file": ("frames.zip", archive)},
        data={"options": '{"fusion": "points"}'},
    )
    assert response.status_code == 201, response.text
    body = response.json()
    assert body["summary"]["format"] == "rgbd" and body["summary"]["n_points"] > 10_000
    assert body["params"]["options"] == {"fusion": "points"} and body["summary"]["notes"]
    assert client.get(f"/sessions/{sid}").json()["scan_id"] == body["id"]


@pytest.mark.parametrize(
    "name, data, code, message",
    [
        ("frames.zip", {"options": "{not json"}, "invalid_request", "not valid JSON"),
        ("frames.zip", {"options": "[1, 2]"}, "invalid_request", "JSON object"),
        ("frames.zip", {"options": '{"depht_scale": 1000}'}, "invalid_value", "depht_scale"),
        (
            "frames.zip",
            {"options": '{"max_unpacked_mb": 1e6}'},
            "invalid_value",
            "max_unpacked_mb=1e+06 exceeds the limit of 2048",
        ),
        ("frames.zip", {"options": '{"voxel_m": 1e-5}'}, "invalid_value", "voxel_m"),
        ("scan.bag", {"options": '{"timeout_s": 86400}'}, "invalid_value", "timeout_s=86400"),
        ("scan.e57", {"units": "mm"}, "invalid_value", "fixes its own length unit"),
        ("frames.zip", {}, "invalid_file", "intrinsics"),
    ],
    ids=[
        "bad-json",
        "not-object",
        "typo",
        "unpack-past-limit",
        "tiny-voxels",
        "decode-past-limit",
        "units-on-e57",
        "zip-without-frames",
    ],
)
def test_bad_scan_uploads_change_nothing(client, sid, tmp_path, name, data, code, message):
    import zipfile

    from tests.drivers.test_scan_readers import write_e57

    if name.endswith(".e57"):
        write_e57(
            tmp_path / name,
            [(np.random.default_rng(0).random((100, 3)), [1.0, 0, 0, 0], [0.0, 0.0, 0.0], None)],
        )
    else:
        with zipfile.ZipFile(tmp_path / name, "w") as archive:
            archive.writestr("frames/readme.txt", "no frames here")
    before = client.get(f"/sessions/{sid}").json()
    response = client.put(
        f"/sessions/{sid}/scan", files={"file": (name, (tmp_path / name).read_bytes())}, data=data
    )
    assert response.status_code == 422, response.text
    assert response.json()["code"] == code and message in response.json()["message"]
    assert client.get(f"/sessions/{sid}").json() == before


def test_a_replay_capture_as_fast_as_possible(client, sid):
    t = np.arange(2400) / 240.0  # 10 s of recording
    points = np.column_stack([0.02 * t, 0 * t, 0 * t])
    rec = client.put(
        f"/sessions/{sid}/recording",
        files={"file": ("t.csv", _csv(Recording(points_m=points, t_s=t)))},
    ).json()
    cid = client.post(
        f"/sessions/{sid}/captures",
        json={"source": {"kind": "replay", "recording_id": rec["id"], "speed": None}},
    ).json()["id"]
    body = _wait_capture(client, sid, cid, timeout_s=8.0)  # far less than the 10 s recorded
    assert body["state"] == "stopped" and body["n_samples"] == 2400, body
