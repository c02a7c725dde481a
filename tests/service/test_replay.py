"""``teachpath replay``: archived sessions re-run on a Dask LocalCluster of 2 workers (loopback),
compared with what they stored, reported as CSV and PNG, failing past the tolerance.

The bundles come from the service itself: the demo session (a synthetic scene, which keeps its
ground truth) reconstructed and planned, and the box-corner session; one bundle is damaged.
"""

from __future__ import annotations

import json
import shutil
import zipfile

import numpy as np
import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from service.cli import main
from service.replay import (
    FAILED,
    MOVED,
    SAME,
    Overrides,
    path_deviation_m,
    read_report,
    replay_bundle,
)
from tests.service.conftest import AUTH, T_BASE_TRACKER, make_settings, planned_session, wait

pytestmark = pytest.mark.timeout(600)


@pytest.fixture(scope="module")
def bundles(tmp_path_factory, scene_files):
    """A folder with the demo session (reconstructed twice, planned) and the box session."""
    data = tmp_path_factory.mktemp("replay_data")
    folder = tmp_path_factory.mktemp("bundles")
    with TestClient(create_app(make_settings(data, demo=True)), headers=AUTH) as client:
        demo = next(s for s in client.get("/sessions").json() if s["name"] == "demo")["id"]
        client.put(f"/sessions/{demo}/calibration", json={"T_base_tracker": T_BASE_TRACKER})
        first = wait(client, client.post(f"/sessions/{demo}/reconstructions", json={}).json())
        assert first["state"] == "succeeded", first
        alpha = {"alpha": 0.5}
        second = wait(client, client.post(f"/sessions/{demo}/reconstructions", json=alpha).json())
        assert second["state"] == "succeeded", second
        box, _ = planned_session(client, scene_files, [0.05], name="box")
        for sid, name in ((demo, "demo"), (box, "box")):
            (folder / f"{name}.zip").write_bytes(client.get(f"/sessions/{sid}/bundle").content)
    return folder


def test_replaying_unchanged_code_finds_every_result_the_same(bundles, tmp_path, capsys):
    report = tmp_path / "report.csv"
    code = main(["replay", str(bundles), "--workers", "2", "--report", str(report)])
    out = capsys.readouterr()
    assert code == 0, out.err
    rows = read_report(report)
    kinds = sorted((r["session_name"], r["kind"]) for r in rows)
    assert kinds == [
        ("box", "reconstruction"),
        ("box", "trajectory"),
        ("demo", "reconstruction"),
        ("demo", "reconstruction"),
    ]
    assert {r["status"] for r in rows} == {SAME}
    for row in rows:
        assert float(row["deviation_max_m"]) <= 1e-9, row
        assert float(row["run_time_s"]) > 0
    plan = next(r for r in rows if r["kind"] == "trajectory")
    assert plan["duration_replayed_s"] == plan["duration_stored_s"]
    # The demo is synthetic: its accuracy against the ground truth, before and after.
    demo = [r for r in rows if r["session_name"] == "demo"]
    for row in demo:
        assert 0 < float(row["truth_stored_max_m"]) == float(row["truth_replayed_max_m"]) < 3e-3
    assert all(r["truth_stored_max_m"] == "" for r in rows if r["session_name"] == "box")
    assert (tmp_path / "report.png").stat().st_size > 10_000
    assert "2 bundles, 4 results" in out.out and "0 moved" in out.out
    assert "local cluster of 2" in out.err and "2/2 bundles replayed" in out.err


def test_other_parameters_move_the_results_and_the_command_fails(bundles, tmp_path, capsys):
    params = tmp_path / "params.json"
    params.write_text(json.dumps({"reconstruction": {"alpha": 1.0}, "plan": {"speed_m_s": 0.1}}))
    report = tmp_path / "report.csv"
    code = main(
        ["replay", str(bundles / "demo.zip"), str(bundles / "box.zip"), "--params",
         str(params), "--workers", "2", "--report", str(report)]
    )  # fmt: skip
    assert code == 1
    rows = read_report(report)
    assert {r["status"] for r in rows} == {MOVED}
    recon = [r for r in rows if r["kind"] == "reconstruction"]
    # alpha = 1 is the trace alone: worse against the ground truth than the stored results.
    demo = [r for r in recon if r["session_name"] == "demo"]
    assert all(float(r["truth_replayed_mean_m"]) > float(r["truth_stored_mean_m"]) for r in demo)
    plan = next(r for r in rows if r["kind"] == "trajectory")
    assert float(plan["duration_replayed_s"]) < float(plan["duration_stored_s"])
    assert "moved more than" in capsys.readouterr().out


def test_a_damaged_bundle_is_reported_and_the_others_still_run(bundles, tmp_path, capsys):
    folder = tmp_path / "mixed"
    shutil.copytree(bundles, folder)
    # One byte of each reconstruction's arrays flipped, the manifest's checksums left as they
    # were (a byte in the middle of the zip may fall in a file replay never reads).
    with zipfile.ZipFile(folder / "box.zip") as bundle:
        entries = {info.filename: bundle.read(info) for info in bundle.infolist()}
    for name in [n for n in entries if n.startswith("arrays/rcn_") and n.endswith(".npz")]:
        data = bytearray(entries[name])
        data[len(data) // 2] ^= 0xFF
        entries[name] = bytes(data)
    with zipfile.ZipFile(folder / "box.zip", "w", zipfile.ZIP_DEFLATED) as bundle:
        for name, data in entries.items():
            bundle.writestr(name, data)
    (folder / "empty.zip").write_bytes(b"")
    report = tmp_path / "report.csv"
    assert main(["replay", str(folder), "--workers", "2", "--report", str(report)]) == 1
    rows = read_report(report)
    by_bundle = {}
    for row in rows:
        by_bundle.setdefault(row["bundle"].rsplit("/", 1)[-1], []).append(row)
    assert {r["status"] for r in by_bundle["demo.zip"]} == {SAME}
    assert len(by_bundle["demo.zip"]) == 2
    assert [r["status"] for r in by_bundle["empty.zip"]] == [FAILED]
    assert "not a readable zip" in by_bundle["empty.zip"][0]["error"]
    assert all(r["status"] == FAILED for r in by_bundle["box.zip"])
    assert "failed" in capsys.readouterr().err


def test_a_task_runs_the_same_in_this_process(bundles):
    """The task is a plain function: what the cluster ran, run here, gives the same rows."""
    rows = replay_bundle(str(bundles / "demo.zip"), Overrides.none(), 1e-4)
    assert [r["status"] for r in rows] == [SAME, SAME]
    assert rows[0]["n_stored"] == rows[0]["n_replayed"] > 100


def test_path_deviation_point_by_point_or_to_the_other_path():
    s = np.linspace(0, 0.1, 101)
    line = np.column_stack([s, 0 * s, 0 * s])
    np.testing.assert_allclose(path_deviation_m(line, line + [0, 0.001, 0]), 0.001)
    coarse = line[::2] + [0, 0.002, 0]  # other sampling: distance to the other curve
    deviation = path_deviation_m(line, coarse)
    np.testing.assert_allclose(deviation, 0.002, atol=1e-12)
    shorter = line[:51]  # a stretch missing counts (both ways)
    assert path_deviation_m(line, shorter).max() == pytest.approx(0.05, abs=1e-3)


@pytest.mark.parametrize(
    ("text", "words"),
    [
        ("[1, 2]", "must be a JSON object"),
        ("{nope", "not valid JSON"),
        ('{"alpha": 0.5}', "must be a JSON object"),
        ('{"reconstruction": {"alpah": 0.5}}', "has no parameter alpah"),
        ('{"reconstruction": {"alpha": 7}}', "alpha"),
        ('{"plan": {"speed_m_s": -1}}', "speed_m_s"),
        ('{"plan": []}', "must be an object"),
        ("[" * 100_000 + "]" * 100_000, "not valid JSON"),
    ],
)
def test_bad_parameter_files_are_refused_before_any_work(text, words, tmp_path, capsys):
    with pytest.raises(ValueError, match=words):
        Overrides.from_json(text)
    params = tmp_path / "p.json"
    params.write_text(text)
    bundle = tmp_path / "b.zip"
    bundle.write_bytes(b"x")
    args = ["replay", str(bundle), "--params", str(params), "--report", str(tmp_path / "r.csv")]
    assert main(args) == 1
    assert "teachpath replay: error" in capsys.readouterr().err
    assert not (tmp_path / "r.csv").exists()


def test_bad_sources_and_options_are_refused(tmp_path, capsys):
    report = str(tmp_path / "r.csv")
    cases = [
        (["replay", str(tmp_path / "none.zip"), "--report", report], "neither a bundle"),
        (["replay", str(tmp_path), "--report", report], "no bundles to replay"),
        (["replay", str(tmp_path), "--workers", "0", "--report", report], "at least 1"),
        (["replay", str(tmp_path), "--scheduler", "10.0.0.1:8786", "--report", report],
         "tcp://HOST:PORT"),
        (["replay", str(tmp_path), "--report", str(tmp_path / "r.txt")], "should end in .csv"),
    ]  # fmt: skip
    for argv, words in cases:
        assert main(argv) == 1, argv
        assert words in capsys.readouterr().err


def test_an_existing_cluster_runs_the_replay_by_its_address(bundles, tmp_path, capsys):
    """``--scheduler``: a cluster started elsewhere (here: one on loopback, its own processes)
    runs the tasks; the command only connects to it, and leaves it running."""
    from distributed import Client, LocalCluster

    with LocalCluster(
        n_workers=2, threads_per_worker=1, host="127.0.0.1", dashboard_address=None
    ) as cluster:
        report = tmp_path / "report.csv"
        argv = ["replay", str(bundles), "--scheduler", cluster.scheduler_address]
        assert main([*argv, "--report", str(report)]) == 0
        rows = read_report(report)
        assert len(rows) == 4 and {r["status"] for r in rows} == {SAME}
        assert all(r["bundle"].startswith("/") for r in rows)  # absolute: workers may be remote
        assert cluster.scheduler_address in capsys.readouterr().err
        with Client(cluster) as client:  # still up after the command
            assert len(client.scheduler_info()["workers"]) == 2


def test_a_move_to_a_plans_start_is_replayed_as_a_move(tmp_path, scene_files):
    """A plan that starts away from the arm (given joints), and the move to its start from the
    simulated arm's home: replayed, each is made again as what it is, the same."""
    from recon.kinematics import HOME_Q_RAD

    away = (np.array(HOME_Q_RAD) + [0.3, -0.1, 0.1, 0.0, 0.2, 0.4]).tolist()
    with TestClient(create_app(make_settings(tmp_path / "data")), headers=AUTH) as client:
        sid, plans = planned_session(client, scene_files, [0.05], start_q_rad=away)
        job = client.post(f"/sessions/{sid}/trajectories/{plans[0.05]}/move-to-start")
        job = wait(client, job.json())
        assert job["state"] == "succeeded", job
        move_id = job["result"]["trajectory_id"]
        bundle = tmp_path / "moved.zip"
        bundle.write_bytes(client.get(f"/sessions/{sid}/bundle").content)
    rows = replay_bundle(str(bundle), Overrides.none(), 1e-4)
    (row,) = [r for r in rows if r.get("artifact_id") == move_id]
    assert row["status"] == SAME, row
    assert row["n_stored"] == row["n_replayed"] > 100
    assert [r["status"] for r in rows] == [SAME] * 3, rows
