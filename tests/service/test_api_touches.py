"""Touches and several demonstrations over REST: the touches upload, reconstructions that use it
(or not), `recording_ids`, and the bad inputs of each."""

from __future__ import annotations

import io

import numpy as np
import pytest

from drivers.scanning.pointcloud import write_scan
from recon import scenes
from recon.inputs import Recording
from recon.metrics import score_path
from tests.service.conftest import wait

MM = 1e-3
SEED = 1


def _csv(recording: Recording) -> bytes:
    buffer = io.StringIO()
    t = recording.t_s if recording.t_s is not None else np.arange(len(recording.points_m)) / 120.0
    np.savetxt(
        buffer, np.column_stack([t, recording.points_m]), delimiter=",", header="t,x,y,z",
        comments="",
    )  # fmt: skip
    return buffer.getvalue().encode()


def _two_rests() -> bytes:
    """A second at one point, a move, a second at another: one rest short of a registration."""
    rest = np.ones(120)
    x = np.concatenate([0.02 * rest, np.linspace(0.02, 0.06, 40), 0.06 * rest])
    points = np.column_stack([x, np.full_like(x, 0.02), np.zeros_like(x)])
    return _csv(Recording(points_m=points, t_s=np.arange(len(x)) / 120.0))


@pytest.fixture(scope="module")
def scene():
    return scenes.box_corner(SEED)


@pytest.fixture(scope="module")
def sid(client, scene, tmp_path_factory):
    sid = client.post("/sessions", json={"name": "touches"}).json()["id"]
    folder = tmp_path_factory.mktemp("scan")
    write_scan(folder / "scan.ply", scene.scan)
    response = client.put(
        f"/sessions/{sid}/scan", files={"file": ("scan.ply", (folder / "scan.ply").read_bytes())}
    )
    assert response.status_code == 201, response.text
    ids = []
    for k, recording in enumerate([scene.recording, *scene.traces(2, SEED)]):
        response = client.put(
            f"/sessions/{sid}/recording", files={"file": (f"trace{k}.csv", _csv(recording))}
        )
        assert response.status_code == 201, response.text
        ids.append(response.json()["id"])
    return sid, ids


def _reconstruct(client, sid, body) -> dict:
    job = client.post(f"/sessions/{sid}/reconstructions", json=body)
    assert job.status_code == 202, job.text
    return wait(client, job.json())


def test_several_recordings_are_fused_and_the_reconstruction_says_how(client, sid, scene):
    sid, ids = sid
    job = _reconstruct(client, sid, {"recording_ids": ids})
    assert job["state"] == "succeeded", job
    rid = job["result"]["reconstruction_id"]
    body = client.get(f"/sessions/{sid}/reconstructions/{rid}").json()
    assert body["inputs"]["recording_ids"] == ids
    summary = body["summary"]
    assert [d["used"] for d in summary["demonstrations"]] == [True, True, True]
    assert [d["reversed"] for d in summary["demonstrations"]] == [False, False, True]
    assert "3 of 3 demonstrations fused" in summary["notes"]
    assert summary["uncertainty_max_m"] > 0


def test_touches_are_uploaded_and_used_by_the_next_reconstruction(client, sid, scene):
    sid, ids = sid
    touch = scenes.touch_recording(scene, SEED)
    response = client.put(
        f"/sessions/{sid}/touches", files={"file": ("touches.csv", _csv(touch.recording))}
    )
    assert response.status_code == 201, response.text
    touches = response.json()
    assert touches["kind"] == "touches" and touches["summary"]["n_touches"] == 6
    np.testing.assert_allclose(touches["summary"]["touches_m"], touch.points_m, atol=0.3 * MM)
    listed = client.get(f"/sessions/{sid}/touches").json()
    assert [t["id"] for t in listed] == [touches["id"]]
    # The session's recording (the last upload) is the reversed third demonstration.
    job = _reconstruct(client, sid, {"recording_id": ids[0]})
    assert job["state"] == "succeeded", job
    rid = job["result"]["reconstruction_id"]
    body = client.get(f"/sessions/{sid}/reconstructions/{rid}").json()
    assert body["inputs"]["touches_id"] == touches["id"]
    registration = body["summary"]["registration"]
    assert registration["target"] == "touches" and registration["constrained_dof"] == 6
    csv = client.get(f"/sessions/{sid}/reconstructions/{rid}/csv").text
    table = np.genfromtxt(io.StringIO(csv), delimiter=",", names=True)
    points = np.column_stack([table["x"], table["y"], table["z"]])
    assert score_path(points, scene.truth_m).max_m < 0.5 * MM
    assert np.all(table["uncertainty_m"] > 0)
    # Frames trusted as given (registration off): the touches are not used unless named.
    job = _reconstruct(client, sid, {"recording_id": ids[0], "registration": False})
    body = client.get(
        f"/sessions/{sid}/reconstructions/{job['result']['reconstruction_id']}"
    ).json()
    assert "touches_id" not in body["inputs"] and body["summary"]["registration"] is None
    job = _reconstruct(
        client,
        sid,
        {"recording_id": ids[0], "registration": False, "touches_id": touches["id"]},
    )
    body = client.get(
        f"/sessions/{sid}/reconstructions/{job['result']['reconstruction_id']}"
    ).json()
    assert body["inputs"]["touches_id"] == touches["id"]
    assert body["summary"]["registration"]["target"] == "touches"
    # Opting out registers the scanner from the trace again.
    job = _reconstruct(client, sid, {"recording_id": ids[0], "use_touches": False})
    rid = job["result"]["reconstruction_id"]
    body = client.get(f"/sessions/{sid}/reconstructions/{rid}").json()
    assert "touches_id" not in body["inputs"]
    assert body["summary"]["registration"]["target"] == "edge"
    assert body["summary"]["registration"]["reason"]
    # What touches added now would mean to each: outdated where touches place the scan, not
    # where they were declined.
    assert body["params"]["touches_considered"] is False and body["outdated"] == []
    touch_again = client.put(
        f"/sessions/{sid}/touches", files={"file": ("touches.csv", _csv(touch.recording))}
    )
    assert touch_again.status_code == 201
    assert client.get(f"/sessions/{sid}/reconstructions/{rid}").json()["outdated"] == []
    first = client.get(f"/sessions/{sid}/reconstructions").json()[0]
    assert first["params"]["touches_considered"] is True
    assert any(reason.startswith("the touches") for reason in first["outdated"])


@pytest.mark.parametrize(
    "content, message",
    [
        (_two_rests(), "has 2 rests of the tip"),
        (b"x,y,z\n" + b"0.02,0.02,0\n" * 80 + b"0.05,0.02,0\n", "no sample times"),
        (b"\x00\x01garbage", ""),
    ],
    ids=["one-rest", "no-times", "garbage"],
)
def test_bad_touches_are_a_422_and_change_nothing(client, sid, content, message):
    sid, _ = sid
    before = client.get(f"/sessions/{sid}/touches").json()
    response = client.put(f"/sessions/{sid}/touches", files={"file": ("t.csv", content)})
    assert response.status_code == 422, response.text
    assert message in response.json()["message"]
    assert client.get(f"/sessions/{sid}/touches").json() == before


@pytest.mark.parametrize(
    "body, status",
    [
        ({"recording_ids": ["rec_nothere"]}, 404),
        ({"recording_ids": ["x" * 40]}, 422),
        ({"recording_ids": ["rec_a"] * 11}, 422),
        ({"recording_ids": "rec_a"}, 422),
        ({"touches_id": "tch_nothere"}, 404),
        ({"use_touches": "maybe"}, 422),
    ],
    ids=["unknown", "too-long", "too-many", "not-a-list", "unknown-touches", "not-a-bool"],
)
def test_bad_reconstruction_requests_are_refused_before_anything_runs(client, sid, body, status):
    sid, _ = sid
    before = client.get(f"/sessions/{sid}/reconstructions").json()
    response = client.post(f"/sessions/{sid}/reconstructions", json=body)
    assert response.status_code == status, response.text
    assert client.get(f"/sessions/{sid}/reconstructions").json() == before
