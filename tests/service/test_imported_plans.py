"""Trust nothing stored: a trajectory imported with a bundle (forged or genuine, from another
cell) reaches the real arm only through the checks of this process, on its own samples.

The arm is configured at 127.0.0.9, where nothing listens: a request that passed every check of
the gate is refused last for the arm's state (``robot_unavailable``), one the gate stopped is
refused for what it found, and nothing is ever sent.
"""

from __future__ import annotations

import io
import json

import numpy as np
import pytest
from fastapi.testclient import TestClient

from recon import kinematics
from recon.kinematics import HOME_Q_RAD
from service.app import create_app
from service.bundles import MANIFEST_NAME
from tests.service.conftest import AUTH, make_settings, planned_session, wait
from tests.service.test_bundles import _entries, _npz, _recomputed

pytestmark = pytest.mark.timeout(300)


@pytest.fixture(scope="module")
def bundle(tmp_path_factory, scene_files):
    """A session planned (from the arm's home) and dry-run in another data folder; its bundle,
    the trajectory's id and its TCP path (base frame)."""
    with TestClient(
        create_app(make_settings(tmp_path_factory.mktemp("site_a"))), headers=AUTH
    ) as a:
        sid, trajectories = planned_session(
            a, scene_files, [0.05], name="site a", start_q_rad=HOME_Q_RAD
        )
        trajectory_id = trajectories[0.05]
        dry = a.post(f"/sessions/{sid}/executions", json={"trajectory_id": trajectory_id})
        assert wait(a, dry.json())["result"]["completed"]
        content = a.get(f"/sessions/{sid}/bundle").content
    return {"zip": content, "sid": sid, "trajectory_id": trajectory_id}


def _trajectory_arrays(content: bytes, trajectory_id: str) -> tuple[str, dict]:
    entries = _entries(content)
    manifest = json.loads(entries[MANIFEST_NAME])
    artifact = next(a for a in manifest["artifacts"] if a["id"] == trajectory_id)
    path = artifact["data"]["path"]
    with np.load(io.BytesIO(entries[path])) as npz:
        return path, {name: npz[name] for name in npz.files}


def _forged(content: bytes, trajectory_id: str, factor: float) -> bytes:
    """The bundle with the trajectory's samples run ``factor`` times faster on the same grid
    (summary untouched: it still says 0.05 m/s) and every checksum recomputed to match."""
    path, arrays = _trajectory_arrays(content, trajectory_id)
    t = arrays["t_s"] / factor
    grid = np.arange(int(np.floor(t[-1] * 500)) + 1) / 500
    resampled = {"t_s": grid}
    for name, values in arrays.items():
        if name == "t_s":
            continue
        if values.ndim == 2:
            resampled[name] = np.stack(
                [np.interp(grid, t, values[:, j]) for j in range(values.shape[1])], axis=1
            )
        elif np.issubdtype(values.dtype, np.integer):
            resampled[name] = values[np.searchsorted(t, grid).clip(0, len(t) - 1)]
        else:
            resampled[name] = np.interp(grid, t, values)
    return _recomputed(content, lambda entries, manifest: entries.update({path: _npz(resampled)}))


def _site_b(tmp_path, **settings):
    return TestClient(
        create_app(make_settings(tmp_path, ur_host="127.0.0.9", ur_robot="ur5e", **settings)),
        headers=AUTH,
    )


def _import(client, content: bytes) -> str:
    response = client.post(
        "/sessions/import", files={"file": ("bundle.zip", content, "application/zip")}
    )
    assert response.status_code in (200, 201), response.text
    return response.json()["session"]["id"]


def _run(client, sid, trajectory_id):
    return client.post(
        f"/sessions/{sid}/executions",
        json={"trajectory_id": trajectory_id, "backend": "ur_rtde", "confirm": True},
    )


def test_a_forged_fast_trajectory_is_refused_on_its_samples(bundle, tmp_path):
    """Arrays 12x faster than planned, a summary that still says 0.05 m/s, an imported "passed"
    dry run: the gate refuses on the samples, naming the limit."""
    forged = _forged(bundle["zip"], bundle["trajectory_id"], 12.0)
    with _site_b(tmp_path, max_speed_m_s=0.25) as client:
        sid = _import(client, forged)
        response = _run(client, sid, bundle["trajectory_id"])
    assert response.status_code == 409, response.text
    body = response.json()
    assert body["code"] == "samples_outside_limits"
    assert "tcp_speed" in body["detail"]["checks"]
    assert "plan it again here" in body["message"].lower()


def test_a_genuine_plan_from_another_cell_is_checked_against_this_cells_keep_out_box(
    bundle, tmp_path
):
    """Planned where there was no box; here a keep-out box sits on its path: outdated (the
    cell), and picked explicitly, refused for the box (checked against this cell's)."""
    _, arrays = _trajectory_arrays(bundle["zip"], bundle["trajectory_id"])
    arm = kinematics.model("ur5e")
    T_flange_tcp = np.eye(4)
    T_flange_tcp[2, 3] = 0.1  # the default TCP, 100 mm along the flange's z
    tcp = (kinematics.forward(arm, arrays["q_rad"]) @ T_flange_tcp)[:, :3, 3]
    middle = tcp[len(tcp) // 2]
    box = [*(middle - [0.05, 0.05, 0.02]), *(middle + [0.05, 0.05, 0.02])]
    with _site_b(tmp_path, max_speed_m_s=0.25, keep_out_boxes=[box]) as client:
        sid = _import(client, bundle["zip"])
        outdated = _run(client, sid, bundle["trajectory_id"])
        assert outdated.status_code == 409 and outdated.json()["code"] == "outdated_inputs"
        (reason,) = outdated.json()["detail"]["changed"]
        assert reason.startswith("the cell: planned with 0 keep-out boxes"), reason
        response = client.post(
            f"/sessions/{sid}/executions",
            json={
                "trajectory_id": bundle["trajectory_id"],
                "backend": "ur_rtde",
                "confirm": True,
                "accept_outdated": True,
            },
        )
    assert response.status_code == 409, response.text
    assert response.json()["code"] == "collides_here"
    assert "keep-out box 1" in response.json()["message"]


def test_an_imported_dry_run_does_not_count_and_one_made_here_does(bundle, tmp_path):
    with _site_b(tmp_path, max_speed_m_s=0.25) as client:
        sid = _import(client, bundle["zip"])
        refused = _run(client, sid, bundle["trajectory_id"])
        assert refused.status_code == 409 and refused.json()["code"] == "dry_run_required"
        assert "imported" in refused.json()["message"]
        dry = client.post(
            f"/sessions/{sid}/executions", json={"trajectory_id": bundle["trajectory_id"]}
        )
        assert wait(client, dry.json())["result"]["completed"]
        # Past every check of the gate: only the arm's state, unknown at 127.0.0.9, is left.
        response = _run(client, sid, bundle["trajectory_id"])
    assert response.status_code == 409 and response.json()["code"] == "robot_unavailable"


def test_a_plan_made_with_another_calibration_than_the_sessions_is_refused(bundle, tmp_path):
    """The workpiece is checked where this cell's calibration puts it: a plan made with another
    tracker-to-base transform (the cell recalibrated since, or a forged copy that moves the
    workpiece away from the motion) is refused, not checked in the wrong place."""
    with _site_b(tmp_path, max_speed_m_s=0.25) as client:
        sid = _import(client, bundle["zip"])
        calibration = np.array(client.get(f"/sessions/{sid}").json()["T_base_tracker"])
        calibration[0, 3] += 0.05  # recalibrated: the tracker 50 mm elsewhere
        client.put(f"/sessions/{sid}/calibration", json={"T_base_tracker": calibration.tolist()})
        outdated = _run(client, sid, bundle["trajectory_id"])
        # Picked explicitly, outdated as it is: still not checked in the wrong place.
        response = client.post(
            f"/sessions/{sid}/executions",
            json={
                "trajectory_id": bundle["trajectory_id"],
                "backend": "ur_rtde",
                "confirm": True,
                "accept_outdated": True,
            },
        )
    assert outdated.status_code == 409 and outdated.json()["code"] == "outdated_inputs"
    assert "the tracker-to-base calibration" in outdated.json()["message"]
    assert "50.0 mm" in outdated.json()["detail"]["changed"][0]
    assert response.status_code == 409 and response.json()["code"] == "cell_unknown"
    assert "another tracker-to-base calibration" in response.json()["message"]
    assert "50.0 mm" in response.json()["message"]


def test_a_plan_made_for_another_mount_is_refused(bundle, tmp_path):
    """A plan's tool comes at the work from above its mount: on an arm hanging from a ceiling a
    plan made for a floor mount would come from below. The cell's mount is a setting
    (TEACHPATH_MOUNT_UP), plans default to it, and the gate refuses a plan made for another."""
    with _site_b(tmp_path, max_speed_m_s=0.25, mount_up=(0.0, 0.0, -1.0)) as client:
        sid = _import(client, bundle["zip"])
        assert client.get("/robot").json()["mount_up"] == [0.0, 0.0, -1.0]
        response = _run(client, sid, bundle["trajectory_id"])
    assert response.status_code == 409 and response.json()["code"] == "cell_unknown"
    assert "another mount" in response.json()["message"], response.json()
