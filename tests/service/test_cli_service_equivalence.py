"""The command line and the service run one pipeline: same inputs and parameters, same outputs.

Compared: the reconstruction CSV (every value), the preview picture (the scan drawn in the same
frame), and the plan (the trajectory's samples), with registration and with a calibrated scanner
(``--no-register --scan-from-tracker``).
"""

from __future__ import annotations

import io

import numpy as np
import pytest
from fastapi.testclient import TestClient

from drivers.calibration import read_calibration, write_calibration
from drivers.scanning.pointcloud import write_scan
from drivers.tracking.canonical_csv import write_trace_csv
from recon import scenes
from recon.transforms import apply_transform, invert_transform
from service import pipelines
from service.app import create_app
from service.cli import main
from service.tasks import load_arrays
from tests.service.conftest import AUTH, T_BASE_TRACKER, make_settings, wait


@pytest.fixture(scope="module")
def scene_folder(tmp_path_factory):
    folder = tmp_path_factory.mktemp("same")
    scene = scenes.box_corner(0)
    write_trace_csv(folder / "trace.csv", scene.recording)
    write_scan(folder / "scan.ply", scene.scan)
    write_calibration(folder / "T_scan.json", "T_scan_tracker", scene.T_scan_tracker)
    write_calibration(folder / "T_base.json", "T_base_tracker", np.array(T_BASE_TRACKER))
    return folder


@pytest.fixture(scope="module")
def client(tmp_path_factory):
    app = create_app(make_settings(tmp_path_factory.mktemp("data")))
    with TestClient(app, headers=AUTH) as test_client:
        yield test_client


def service_session(client, folder, *, T_scan_tracker=None) -> str:
    sid = client.post("/sessions", json={"name": "same"}).json()["id"]
    for route, name in (("recording", "trace.csv"), ("scan", "scan.ply")):
        response = client.put(
            f"/sessions/{sid}/{route}", files={"file": (name, (folder / name).read_bytes())}
        )
        assert response.status_code == 201, response.text
    calibration = {"T_base_tracker": T_BASE_TRACKER}
    if T_scan_tracker is not None:
        calibration["T_scan_tracker"] = np.asarray(T_scan_tracker).tolist()
    assert client.put(f"/sessions/{sid}/calibration", json=calibration).status_code == 200
    return sid


def service_reconstruction(client, sid, **body) -> tuple[str, bytes, bytes]:
    job = wait(client, client.post(f"/sessions/{sid}/reconstructions", json=body).json())
    assert job["state"] == "succeeded", job
    rid = job["result"]["reconstruction_id"]
    csv = client.get(f"/sessions/{sid}/reconstructions/{rid}/csv").content
    png = client.get(f"/sessions/{sid}/reconstructions/{rid}/preview.png").content
    return rid, csv, png


def cli_reconstruction(folder, out_dir, *options) -> tuple[bytes, bytes]:
    args = [
        "reconstruct",
        str(folder / "trace.csv"),
        "--scan",
        str(folder / "scan.ply"),
        "--out",
        str(out_dir / "r.csv"),
        "--plot",
        str(out_dir / "r.png"),
        *options,
    ]
    assert main(args) == 0
    return (out_dir / "r.csv").read_bytes(), (out_dir / "r.png").read_bytes()


def trajectory_columns(content: bytes) -> np.ndarray:
    """The numbers of a trajectory CSV (after its metadata and header lines; not the phase)."""
    return np.loadtxt(io.BytesIO(content), delimiter=",", skiprows=2, usecols=range(13))


def test_reconstruction_preview_and_plan_are_the_same(client, scene_folder, tmp_path):
    sid = service_session(client, scene_folder)
    rid, service_csv, service_png = service_reconstruction(client, sid)
    cli_csv, cli_png = cli_reconstruction(scene_folder, tmp_path)
    assert cli_csv == service_csv
    assert cli_png == service_png

    # The registration the reconstruction used is what the service stored and the CLI wrote
    # beside its CSV.
    stored = client.get(f"/sessions/{sid}/reconstructions/{rid}").json()["summary"]
    used = load_arrays(tmp_path / "r.npz")["T_scan_tracker"]
    np.testing.assert_allclose(used, stored["T_scan_tracker"], atol=1e-12)

    job = wait(
        client,
        client.post(
            f"/sessions/{sid}/trajectories", json={"reconstruction_id": rid, "speed_m_s": 0.05}
        ).json(),
    )
    assert job["state"] == "succeeded", job
    tid = job["result"]["trajectory_id"]
    trajectory = client.get(f"/sessions/{sid}/trajectories/{tid}").json()
    np.testing.assert_allclose(trajectory["summary"]["T_scan_tracker"], used, atol=1e-12)
    service_traj = trajectory_columns(client.get(f"/sessions/{sid}/trajectories/{tid}/csv").content)
    plan_args = [
        "plan",
        str(tmp_path / "r.csv"),
        "--scan",
        str(scene_folder / "scan.ply"),
        "--base-from-tracker",
        str(scene_folder / "T_base.json"),
        "--speed-m-s",
        "0.05",
        "--out",
        str(tmp_path / "traj.csv"),
    ]
    assert main(plan_args) == 0
    cli_traj = trajectory_columns((tmp_path / "traj.csv").read_bytes())
    # The command line reuses the arrays it wrote beside the CSV as the service reuses its
    # stored ones: the same transform, the same scan model, the same plan.
    np.testing.assert_array_equal(cli_traj, service_traj)


def test_a_calibrated_scanner_without_registration(client, scene_folder, tmp_path):
    """--no-register --scan-from-tracker: the preview draws the scan in the tracker frame."""
    T = read_calibration(scene_folder / "T_scan.json", expect="T_scan_tracker").matrix
    sid = service_session(client, scene_folder, T_scan_tracker=T)
    rid, service_csv, service_png = service_reconstruction(client, sid, registration=False)
    cli_csv, cli_png = cli_reconstruction(
        scene_folder,
        tmp_path,
        "--no-register",
        "--scan-from-tracker",
        str(scene_folder / "T_scan.json"),
    )
    assert cli_csv == service_csv
    assert cli_png == service_png
    summary = client.get(f"/sessions/{sid}/reconstructions/{rid}").json()["summary"]
    assert summary["registration"] is None
    np.testing.assert_allclose(summary["T_scan_tracker"], T, atol=1e-12)
    np.testing.assert_allclose(load_arrays(tmp_path / "r.npz")["T_scan_tracker"], T, atol=1e-12)


def test_the_preview_moves_the_scan_into_the_tracker_frame():
    scene = scenes.box_corner(0)
    from recon.recon_params import ReconParams

    outcome = pipelines.reconstruct(
        scene.recording,
        scene.scan,
        params=ReconParams(register=False),
        T_scan_tracker_init=scene.T_scan_tracker,
    )
    expected = apply_transform(invert_transform(scene.T_scan_tracker), scene.scan.points_m)
    np.testing.assert_allclose(outcome.scan_tracker_m, expected, atol=1e-12)
    # ... and the scan sits under the trace there (not millimetres off in the scan's frame).
    from scipy.spatial import cKDTree

    gap, _ = cKDTree(outcome.scan_tracker_m).query(scene.truth_m)
    assert np.median(gap) < 2e-3
