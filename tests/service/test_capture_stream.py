"""A capture's samples while it runs (``GET /sessions/{id}/captures/{cid}/samples``): what the
pendant draws as the operator traces, tracking loss included, checked against the samples sent."""

from __future__ import annotations

import json

import numpy as np
import pytest

from drivers.errors import InputFileError
from drivers.tracking.natnet_server import NatNetReplayServer
from recon.inputs import Recording
from service.capture_runner import HEADER
from service.capture_stream import CaptureTail
from tests.drivers.test_natnet import synthetic
from tests.service.test_api_inputs import _csv


def _events(client, url: str) -> list[tuple[str, dict]]:
    """Every event of a server-sent event stream, read to its end."""
    out, kind = [], None
    with client.stream("GET", url) as response:
        assert response.status_code == 200, response.read()
        assert response.headers["content-type"].startswith("text/event-stream")
        for line in response.iter_lines():
            if line.startswith("event: "):
                kind = line[len("event: ") :]
            elif line.startswith("data: "):
                out.append((kind, json.loads(line[len("data: ") :])))
    return out


def _samples(events) -> tuple[list[int], list, list[bool]]:
    firsts, points, valid = [], [], []
    for kind, body in events:
        if kind == "samples":
            firsts.append(body["first"])
            points += body["points_m"]
            valid += body["valid"]
    return firsts, points, valid


def test_the_tail_returns_complete_lines_only_and_from_any_sample(tmp_path):
    path = tmp_path / "cap.csv"
    path.write_text(HEADER + "0.0,1,2,3,0,0,0,1,1\n0.1,4,5,6,0,0,0,1,0\n0.2,7,8")
    tail = CaptureTail(path)
    first, batch = tail.read()
    assert first == 0 and batch.position_m.tolist() == [[1, 2, 3], [4, 5, 6]]
    assert batch.valid.tolist() == [True, False]
    assert tail.read() is None  # the torn line waits
    with path.open("a") as handle:
        handle.write(",9,0,0,0,1,1\n")
    first, batch = tail.read()
    assert first == 2 and batch.position_m.tolist() == [[7, 8, 9]]
    # From sample 1 on: the first is read past.
    first, batch = CaptureTail(path, from_sample=1).read()
    assert first == 1 and len(batch.t_s) == 2
    assert CaptureTail(path, from_sample=5).read() is None
    assert CaptureTail(tmp_path / "missing.csv").read() is None


def test_a_late_start_in_a_long_capture_is_found_at_once(tmp_path):
    """Resuming at sample 30 000 of a 40 000-sample file (several read chunks before it)."""
    path = tmp_path / "cap.csv"
    n = 40_000
    rows = [f"{i / 240:.6f},{i * 1e-4:.9g},0,0,0,0,0,1,1" for i in range(n)]
    path.write_text(HEADER + "\n".join(rows) + "\n")
    tail = CaptureTail(path, from_sample=30_000)
    first, batch = tail.read()
    assert first == 30_000 and batch.position_m[0, 0] == pytest.approx(3.0)
    expected, total = first, 0
    while True:
        total += len(batch.t_s)
        expected += len(batch.t_s)
        read = tail.read()
        if read is None:
            break
        first, batch = read
        assert first == expected  # each read carries on where the last stopped
    assert total == n - 30_000


def test_the_tail_moves_a_live_feed_to_the_tip_and_refuses_a_changed_file(tmp_path):
    path = tmp_path / "cap.csv"
    # A quarter turn about z: the tip 0.1 m along the body's x lies along the tracker's y.
    q = np.sin(np.pi / 4)
    path.write_text(HEADER + f"0.0,0.5,0,0,0,0,{q},{q},1\n")
    _, batch = CaptureTail(path, tip_offset_m=[0.1, 0, 0]).read()
    np.testing.assert_allclose(batch.position_m, [[0.5, 0.1, 0]], atol=1e-12)
    path.write_text(HEADER + "0.0,1,2,3\n")
    with pytest.raises(InputFileError, match="line 2: 4 fields"):
        CaptureTail(path).read()


def test_a_replay_is_streamed_sample_by_sample_until_it_ends(client, sid):
    t = np.arange(480) / 240.0  # 2 s
    points = np.column_stack([0.3 + 0.05 * t, 0.01 * np.sin(t), 0 * t])
    rec = client.put(
        f"/sessions/{sid}/recording",
        files={"file": ("t.csv", _csv(Recording(points_m=points, t_s=t)))},
    ).json()
    cid = client.post(
        f"/sessions/{sid}/captures",
        json={"source": {"kind": "replay", "recording_id": rec["id"], "speed": 1.0}},
    ).json()["id"]
    events = _events(client, f"/sessions/{sid}/captures/{cid}/samples")
    firsts, streamed, valid = _samples(events)
    # In real time: many events, each carrying on where the last stopped.
    assert len(firsts) >= 5 and firsts[0] == 0
    np.testing.assert_allclose(np.array(streamed), points, atol=1e-6)
    assert all(valid)
    last = [body for kind, body in events if kind == "capture"][-1]
    assert last["state"] == "stopped" and last["recording_id"] and last["n_samples"] == 480
    # A page that reloads follows on from the samples it has.
    _, again, _ = _samples(
        _events(client, f"/sessions/{sid}/captures/{cid}/samples?from_sample=400")
    )
    np.testing.assert_allclose(np.array(again), points[400:], atol=1e-6)


@pytest.mark.timeout(120)
def test_tracking_loss_in_a_live_feed_is_streamed_where_it_happens(client, sid):
    recording = synthetic(1.0)  # 360 frames
    lost = np.zeros(len(recording), dtype=bool)
    lost[100:140] = True
    tip_m = [0.0, 0.0, -0.12]
    client.put(f"/sessions/{sid}/calibration", json={"tip_offset_m": tip_m})
    with NatNetReplayServer(recording, rigid_body="Pen", command_port=0, valid=~lost) as server:
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
        client.post(f"/sessions/{sid}/captures/{cid}/stop")
    _, streamed, valid = _samples(_events(client, f"/sessions/{sid}/captures/{cid}/samples"))
    assert len(streamed) == len(recording)
    assert np.array_equal(~np.array(valid), lost)
    assert all(streamed[i] is None for i in range(100, 140))
    # At the tip: the rigid body's origin moved by the offset, turned by its orientation.
    from scipy.spatial.transform import Rotation

    tip = recording.points_m + Rotation.from_quat(recording.orientations_xyzw).apply(tip_m)
    kept = np.flatnonzero(~lost)
    np.testing.assert_allclose(np.array([streamed[i] for i in kept]), tip[kept], atol=1e-5)


@pytest.mark.parametrize(
    "query",
    ["from_sample=-1", "from_sample=1e99", "from_sample=x", "from_sample=99999999999999999999"],
)
def test_bad_starts_are_refused(client, sid, query):
    t = np.arange(240) / 240.0
    points = np.column_stack([0.05 * t, 0 * t, 0 * t])
    rec = client.put(
        f"/sessions/{sid}/recording",
        files={"file": ("t.csv", _csv(Recording(points_m=points, t_s=t)))},
    ).json()
    cid = client.post(
        f"/sessions/{sid}/captures",
        json={"source": {"kind": "replay", "recording_id": rec["id"], "speed": None}},
    ).json()["id"]
    assert client.get(f"/sessions/{sid}/captures/{cid}/samples?{query}").status_code == 422


def test_an_unknown_capture_is_a_404(client, sid):
    response = client.get(f"/sessions/{sid}/captures/cap_000000000000/samples")
    assert response.status_code == 404 and response.json()["code"] == "not_found"


@pytest.fixture()
def sid(client):
    return client.post("/sessions", json={"name": "capture stream"}).json()["id"]
