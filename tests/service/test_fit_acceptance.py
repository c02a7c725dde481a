"""Fits and numbers that must not be stored: calibrations worse than their tolerance unless
accepted, absurd values, and traces whose size says the units are wrong."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from fastapi.testclient import TestClient

from recon.inputs import Recording
from service.app import create_app
from tests.recon.test_calibrate import pivot_recording
from tests.service.conftest import AUTH, make_settings
from tests.service.test_api_inputs import _csv, _pairs


@pytest.fixture(scope="module")
def client(tmp_path_factory):
    app = create_app(make_settings(tmp_path_factory.mktemp("fits")))
    with TestClient(app, headers=AUTH) as test_client:
        yield test_client


@pytest.fixture()
def sid(client):
    sid = client.post("/sessions", json={"name": "fits"}).json()["id"]
    _T, pairs = _pairs()
    assert (
        client.post(f"/sessions/{sid}/calibration/base", json={"pairs": pairs}).status_code == 200
    )
    return sid


def _scaled_pairs(factor_tracker: float = 1.0, factor_base: float = 1.0):
    _, pairs = _pairs()
    return [
        {
            "base": [v * factor_base for v in p["base"]],
            "tracker": [v * factor_tracker for v in p["tracker"]],
        }
        for p in pairs
    ]


def test_pairs_that_disagree_are_refused_with_their_figures_and_change_nothing(client, sid):
    before = client.get(f"/sessions/{sid}").json()
    # The tracker points twice the base points (a scale error): every pair disagrees.
    body = {"pairs": _scaled_pairs(factor_tracker=2.0)}
    response = client.post(f"/sessions/{sid}/calibration/base", json=body)
    assert response.status_code == 422, response.text
    error = response.json()
    assert error["code"] == "poor_fit"
    assert "was not stored" in error["message"] and "accept_poor_fit" in error["message"]
    assert error["detail"]["residual_rms_m"] > 0.01 and all(error["detail"]["suspect"])
    assert client.get(f"/sessions/{sid}").json() == before


def test_a_poor_fit_is_stored_when_explicitly_accepted(client, sid):
    body = {"pairs": _scaled_pairs(factor_tracker=2.0), "accept_poor_fit": True}
    response = client.post(f"/sessions/{sid}/calibration/base", json=body)
    assert response.status_code == 200, response.text
    assert response.json()["result"]["residual_rms_m"] > 0.01
    # Only the JSON boolean accepts.
    body["accept_poor_fit"] = "yes"
    assert client.post(f"/sessions/{sid}/calibration/base", json=body).status_code == 422


def test_a_good_fit_with_one_bad_pair_leaves_it_out_and_is_stored(client, sid):
    _T, pairs = _pairs(outlier_at=2)
    response = client.post(f"/sessions/{sid}/calibration/base", json={"pairs": pairs})
    assert response.status_code == 200
    result = response.json()["result"]
    assert not result["used"][2] and result["suspect"][2]
    # No pair the fit used is suspect.
    assert not any(s and u for s, u in zip(result["suspect"], result["used"], strict=True))


@pytest.mark.parametrize(
    "body, words",
    [
        ({"pairs": _scaled_pairs(factor_base=1e300)}, "check the units"),
        ({"pairs": _scaled_pairs(factor_base=1e3)}, "check the units"),  # mm sent as metres
    ],
    ids=["1e300", "mm-as-metres"],
)
def test_absurd_pairs_are_refused(client, sid, body, words):
    before = client.get(f"/sessions/{sid}").json()
    response = client.post(f"/sessions/{sid}/calibration/base", json=body)
    assert response.status_code == 422 and words in response.json()["message"], response.text
    assert client.get(f"/sessions/{sid}").json() == before


@pytest.mark.parametrize("translation_m", [1e308, 11.0, -50.0])
def test_a_calibration_beyond_the_cell_is_refused(client, sid, translation_m):
    before = client.get(f"/sessions/{sid}").json()
    T = np.eye(4)
    T[0, 3] = translation_m
    for field in ("T_base_tracker", "T_scan_tracker"):
        response = client.put(f"/sessions/{sid}/calibration", json={field: T.tolist()})
        assert response.status_code == 422, response.text
        assert "robot cell" in response.json()["message"]
    assert client.get(f"/sessions/{sid}").json() == before


def test_a_pivot_that_wandered_is_refused_unless_accepted(client, sid):
    before = client.get(f"/sessions/{sid}").json()
    position, quat = pivot_recording(0, position_noise_m=3e-3)  # the tip slid about 5 mm RMS
    t = np.arange(len(position)) / 240.0
    content = _csv(Recording(points_m=position, t_s=t, orientations_xyzw=quat))
    url = f"/sessions/{sid}/calibration/pivot"
    response = client.post(url, files={"file": ("p.csv", content)})
    assert response.status_code == 422 and response.json()["code"] == "poor_fit", response.text
    assert "pivot again" in response.json()["message"]
    assert response.json()["detail"]["residual_rms_m"] > 1e-3
    assert client.get(f"/sessions/{sid}").json() == before
    accepted = client.post(
        url, files={"file": ("p.csv", content)}, data={"accept_poor_fit": "true"}
    )
    assert accepted.status_code == 200, accepted.text
    loose = client.post(url, files={"file": ("p.csv", content)}, data={"tolerance_m": "0.01"})
    assert loose.status_code == 200, loose.text


def _line(n=480, length_m=0.1, offset_m=(0.4, 0.1, 0.05)):
    t = np.arange(n) / 240.0
    points = np.column_stack([np.linspace(0, length_m, n), 0 * t, 0 * t]) + offset_m
    return Recording(points_m=points, t_s=t)


@pytest.mark.parametrize(
    "recording, units, words",
    [
        # A 100 mm trace written in metres, uploaded as millimetres: 0.1 mm.
        (_line(), "mm", "units set to m (units=m"),
        # The same trace written in millimetres, uploaded as metres: 100 m.
        (
            Recording(points_m=_line().points_m * 1e3, t_s=_line().t_s),
            "m",
            "units set to mm (units=mm",
        ),
    ],
    ids=["metres-as-mm", "mm-as-metres"],
)
def test_a_trace_in_the_other_unit_is_refused_naming_the_units(
    client, sid, recording, units, words
):
    before = client.get(f"/sessions/{sid}").json()
    response = client.put(
        f"/sessions/{sid}/recording",
        files={"file": ("t.csv", _csv(recording))},
        data={"units": units},
    )
    assert response.status_code == 422, response.text
    assert response.json()["code"] == "units_mismatch" and words in response.json()["message"]
    assert client.get(f"/sessions/{sid}").json() == before


def test_the_cli_refuses_a_poor_base_fit_unless_accepted(tmp_path):
    pairs = tmp_path / "pairs.csv"
    rows = ["base_x,base_y,base_z,tracker_x,tracker_y,tracker_z"]
    rows += [",".join(map(str, p["base"] + p["tracker"])) for p in _scaled_pairs(2.0)]
    pairs.write_text("\n".join(rows) + "\n")
    out = tmp_path / "T.json"

    def run(*extra):
        return subprocess.run(
            [sys.executable, "-m", "service.cli", "calibrate", "base", str(pairs)]
            + ["--out", str(out), *extra],
            capture_output=True,
            text=True,
            timeout=120,
        )

    refused = run()
    assert refused.returncode == 1 and "was not stored" in refused.stderr, refused.stderr
    assert "--accept-poor-fit" in refused.stderr and not out.exists()
    accepted = run("--accept-poor-fit")
    assert accepted.returncode == 0, accepted.stderr
    assert json.loads(out.read_text())["name"] == "T_base_tracker"


def test_no_override_stores_a_pivot_that_no_pen_makes(client, sid):
    """accept_poor_fit stored a 996 mm RMS pivot: the override widens the tolerance up to what a
    pivot can be (10 mm RMS), never beyond."""
    before = client.get(f"/sessions/{sid}").json()
    position, quat = pivot_recording(0, position_noise_m=0.03)  # the tip all over the place
    t = np.arange(len(position)) / 240.0
    content = _csv(Recording(points_m=position, t_s=t, orientations_xyzw=quat))
    url = f"/sessions/{sid}/calibration/pivot"
    response = client.post(
        url, files={"file": ("p.csv", content)}, data={"accept_poor_fit": "true"}
    )
    assert response.status_code == 422 and response.json()["code"] == "poor_fit", response.text
    assert "No override stores it" in response.json()["message"]
    assert client.get(f"/sessions/{sid}").json() == before


@pytest.mark.parametrize("offset", [(0.9, 0.0, 0.0), (0.3, 0.3, 0.3)])
def test_a_tip_offset_beyond_a_pen_is_refused(client, sid, offset):
    """0.9 m was accepted though a pen's tip lies within 0.5 m of its rigid body."""
    before = client.get(f"/sessions/{sid}").json()
    response = client.put(f"/sessions/{sid}/calibration", json={"tip_offset_m": list(offset)})
    assert response.status_code == 422 and "500 mm" in response.json()["message"], response.text
    assert client.get(f"/sessions/{sid}").json() == before
