"""Stored calibration files loaded into a session (POST /sessions/{id}/calibration/file): the
files ``teachpath calibrate`` writes are taken as the CLI reads them; anything else is a 422
that changes nothing."""

from __future__ import annotations

import json

import numpy as np
import pytest

from drivers.calibration import write_calibration, write_tip_calibration


def _rigid(angle_deg: float = 30.0, shift_m=(0.4, -0.1, 0.05)) -> np.ndarray:
    a = np.radians(angle_deg)
    T = np.eye(4)
    T[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    T[:3, 3] = shift_m
    return T


def _load(client, session, content: bytes, name: str = "calibration.json"):
    return client.post(
        f"/sessions/{session}/calibration/file",
        files={"file": (name, content, "application/json")},
    )


@pytest.fixture
def fresh(client):
    return client.post("/sessions", json={"name": "calibration files"}).json()["id"]


def test_a_base_calibration_written_by_the_cli_sets_the_sessions_transform(client, fresh, tmp_path):
    T = _rigid()
    path = tmp_path / "T_base_tracker.json"
    write_calibration(path, "T_base_tracker", T, residual_rms_m=0.0004)
    answer = _load(client, fresh, path.read_bytes(), "T_base_tracker.json")
    assert answer.status_code == 200, answer.text
    session = answer.json()
    assert np.allclose(session["T_base_tracker"], T)
    entry = session["calibration_report"]["file:T_base_tracker"]
    assert entry["source_name"] == "T_base_tracker.json" and entry["residual_rms_m"] == 0.0004


def test_a_file_in_millimetres_and_a_tip_offset_are_read_as_the_cli_reads_them(
    client, fresh, tmp_path
):
    T = _rigid(shift_m=(0.2, 0.3, -0.1))
    in_mm = T.copy()
    in_mm[:3, 3] *= 1000
    content = {"name": "T_scan_tracker", "matrix": in_mm.tolist(), "units": "mm"}
    answer = _load(client, fresh, json.dumps(content).encode())
    assert answer.status_code == 200, answer.text
    assert np.allclose(answer.json()["T_scan_tracker"], T)
    path = tmp_path / "tip.json"
    write_tip_calibration(path, np.array([0.0, 0.01, 0.12]))
    answer = _load(client, fresh, path.read_bytes(), "tip.json")
    assert answer.status_code == 200, answer.text
    assert np.allclose(answer.json()["tip_offset_m"], [0.0, 0.01, 0.12])


NOT_RIGID = np.diag([2.0, 1.0, 1.0, 1.0]).tolist()


@pytest.mark.parametrize(
    ("content", "says"),
    [
        (b"", "empty"),
        (b"not json", "not a readable JSON"),
        (b"[1, 2, 3]", "not a JSON object"),
        (json.dumps({"name": "T_flange_tool", "matrix": np.eye(4).tolist()}).encode(), "holds"),
        (
            json.dumps({"name": "T_base_tracker", "matrix": NOT_RIGID}).encode(),
            "not a proper rotation",
        ),
        (json.dumps({"name": "T_base_tracker"}).encode(), 'no "matrix"'),
        (
            json.dumps(
                {"name": "T_base_tracker", "matrix": np.eye(4).tolist(), "units": "yd"}
            ).encode(),
            "unit",
        ),
        (
            b'{"name": "T_base_tracker", "matrix": [[1' + b"0" * 400 + b", 0, 0, 0]]}",
            "too large to convert",
        ),
        (b'{"name": "T_base_tracker", "matrix": [[NaN, 0, 0, 0]]}', "matrix"),
        (b"[" * 100_000 + b"]" * 100_000, "few hundred bytes"),
        (b'{"a": ' * 5000 + b"1" + b"}" * 5000, "readable JSON"),
        (json.dumps({"name": "tip_offset", "offset": [0, 0, 5.0]}).encode(), "are the units right"),
        (b" " * 70_000 + b"{}", "a calibration file is a few hundred bytes"),
    ],
)
def test_bad_calibration_files_are_422_and_change_nothing(client, fresh, content, says):
    before = client.get(f"/sessions/{fresh}").json()
    answer = _load(client, fresh, content)
    assert answer.status_code == 422, answer.text
    body = answer.json()
    assert body["code"] == "invalid_file"
    assert says.lower() in body["message"].lower(), body["message"]
    assert client.get(f"/sessions/{fresh}").json() == before


def test_a_calibration_file_for_no_session_is_404(client):
    answer = _load(client, "ses_nope", b"{}")
    assert answer.status_code == 404 and answer.json()["code"] == "not_found"
