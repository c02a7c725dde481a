"""Speed as a user times it: whole commands, start-up included (``make bench``).

Every figure is a whole process (``teachpath reconstruct TRACE.csv --scan SCAN.ply --out
OUT.csv``, as typed), run ``TEACHPATH_BENCH_RUNS`` times (default 5), reported as hyperfine
does: median, min and max, with the process's peak resident memory (GNU time). Beside them, in
the same run: the same command with the per-point stage a straightforward per-point loop of the
paper's Eq. (4) (``loop_command.py``) and the ratio; a stage-by-stage profile of the 10k / 1M
case; the service's upload-to-result time; planning a 10k-point result.

The reconstruction scenes are :func:`recon.scenes.long_edge` (a step edge wound into a spiral,
a trace at 1 mm per point, a scan of 100k or 1M points); planning uses
:func:`recon.scenes.serpentine_plate` (a spiral around the arm's base would turn joint 1 by
more than its limits). Nothing here asserts a time: timings on a shared machine are noisy; the
tables are read by people.
"""

from __future__ import annotations

import cProfile
import os
import pstats
import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from datetime import datetime
from pathlib import Path

import numpy as np
import pytest

from drivers.scanning.pointcloud import write_scan
from drivers.tracking.canonical_csv import write_trace_csv
from recon import scenes

pytestmark = [pytest.mark.bench, pytest.mark.timeout(3600)]

#: Runs of each whole command (median, min, max).
RUNS = int(os.environ.get("TEACHPATH_BENCH_RUNS", "5"))
#: A checkout of another version (``git worktree add /tmp/base COMMIT``): its ``reconstruct``
#: runs alternate with this one's in the same run, for a before/after that shares the machine's
#: moods (timings here vary by a third between runs minutes apart).
BASELINE = os.environ.get("TEACHPATH_BENCH_BASELINE")
#: (trace points at 1 mm, scan points), with the issue's targets for the whole command (s).
CASES = ((1_000, 100_000, 0.5), (10_000, 1_000_000, 1.5), (100_000, 1_000_000, 5.0))
#: The per-point loop baseline runs on paths up to this many points (longer ones take minutes).
LOOP_POINTS = 10_000
TEACHPATH = str(Path(sys.executable).with_name("teachpath"))


@pytest.fixture(scope="module")
def case_folder(tmp_path_factory) -> Path:
    """Where the scenes' files are written once for every test of the module."""
    return tmp_path_factory.mktemp("cases")


def _case_files(folder: Path, n_path: int, n_scan: int) -> tuple[Path, Path]:
    trace, scan = folder / f"trace_{n_path}.csv", folder / f"scan_{n_path}_{n_scan}.ply"
    if not trace.exists():
        scene = scenes.long_edge(n_path, n_scan)
        write_trace_csv(trace, scene.recording)
        write_scan(scan, scene.scan)
    return trace, scan


#: GNU time (Debian's ``time``, which ``make bench`` installs): the child's own peak RSS. (The
#: rusage of a child forked from this large pytest process counts the pages it shared before exec.)
GNU_TIME = "/usr/bin/time"


def timed_runs(
    argv: list[str], runs: int = RUNS, *, pythonpath: str | None = None
) -> tuple[list[float], list[float]]:
    """Wall-clock seconds and peak RSS (MiB) of ``runs`` runs of a command, each checked to
    succeed (its stderr shown if not); the RSS is NaN without GNU time. ``pythonpath`` runs
    another checkout's code with this environment's packages."""
    seconds, peak_mib = [], []
    measure = [GNU_TIME, "-f", "peak-kib %M"] if Path(GNU_TIME).exists() else []
    env = {**os.environ, "PYTHONPATH": pythonpath} if pythonpath else None
    for _ in range(runs):
        start = time.perf_counter()
        done = subprocess.run(
            measure + argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env
        )
        seconds.append(time.perf_counter() - start)
        error = done.stderr.decode(errors="replace")
        assert done.returncode == 0, f"{' '.join(argv)} failed: {error}"
        peak = [line for line in error.splitlines() if line.startswith("peak-kib ")]
        peak_mib.append(int(peak[-1].split()[1]) / 1024 if peak else float("nan"))
    return seconds, peak_mib


def _row(label: str, seconds: list[float], peak_mib: list[float], extra: str = "") -> str:
    return (
        f"| {label} | {statistics.median(seconds):.2f} | {min(seconds):.2f} | "
        f"{max(seconds):.2f} | {max(peak_mib):.0f} |{extra}"
    )


def _loop_command(trace: Path, scan: Path, out: Path) -> list[str]:
    """The baseline: the same files through a per-point loop of Eq. (4) (loop_command.py)."""
    return [sys.executable, "-m", "tests.bench.loop_command", str(trace), str(scan), str(out)]


#: Runs of the per-point loop (it takes 10-20 s on the 10k case).
LOOP_RUNS = min(RUNS, 3)


def test_whole_command_speed(case_folder):
    folder = case_folder
    out = folder / "out.csv"
    print(
        f"\n## Whole command, start-up included (seconds over {RUNS} runs; peak RSS of the "
        "process)\n"
    )
    print("| command | median | min | max | peak MiB | target | per-point loop | loop / median |")
    print("|---|---:|---:|---:|---:|---:|---:|---:|")
    for n_path, n_scan, target in CASES:
        trace, scan = _case_files(folder, n_path, n_scan)
        argv = [TEACHPATH, "reconstruct", str(trace), "--scan", str(scan), "--out", str(out)]
        seconds, peak = timed_runs(argv)
        if n_path <= LOOP_POINTS:
            loop = statistics.median(timed_runs(_loop_command(trace, scan, out), LOOP_RUNS)[0])
            ratio = loop / statistics.median(seconds)
            extra = f" {target:.1f} | {loop:.1f} | {ratio:.1f}x |"
        else:
            extra = f" {target:.1f} | - | - |"
        label = f"`reconstruct` {n_path:,}-point trace, {n_scan:,}-point scan"
        print(_row(label, seconds, peak, extra))
    for label, argv in (
        ("`teachpath --help`", [TEACHPATH, "--help"]),
        ("`teachpath reconstruct --help`", [TEACHPATH, "reconstruct", "--help"]),
        ("`teachpath plan --help`", [TEACHPATH, "plan", "--help"]),
    ):
        seconds, peak = timed_runs(argv)
        print(_row(label, seconds, peak, " 0.3 | - | - |"))
    print(
        f"\nThe per-point loop is the same command with the per-point stage a loop of the "
        f"paper's Eq. (4), one neighbourhood at a time (tests/bench/loop_command.py; median of "
        f"{LOOP_RUNS} runs in this run); the ratio is loop over `reconstruct`. Peak MiB: GNU "
        "time's maximum resident set of the process."
    )


#: Stages of the profile: (label, function names whose cumulative times it adds up). Names that
#: exist in older versions too, so the same table can be made of the code before a change.
STAGES = (
    ("read the trace", ("read_trace_for",)),
    ("read the scan", ("read_scan_for",)),
    ("scan preparation: crop, voxels, outliers, normals", ("prepare_scan",)),
    ("... of which normals and curvature", ("covariance_features",)),
    ("edge lines (thinning)", ("thin_edges",)),
    ("registration (edge and surface ICP)", ("register_to_model",)),
    ("corners", ("judge_corners", "with_corner_edges")),
    ("classify", ("classify_segments",)),
    ("per-point fits", ("anchored_segment",)),
    ("uncertainty, assembly", ("_assemble",)),
    ("write the CSV", ("write_reconstruction_csv",)),
    ("write the .npz beside it", ("save_arrays",)),
)


#: The stages of ``teachpath plan``, as :data:`STAGES`.
PLAN_STAGES = (
    ("read the reconstruction and its arrays", ("_reconstruction",)),
    ("read the scan", ("read_scan_for",)),
    ("the scan's normals along the path", ("normals_from_scan",)),
    ("tool poses", ("tool_path",)),
    ("inverse kinematics along the path", ("follow_path",)),
    ("time-optimal timing (toppra)", ("time_parameterize",)),
    ("collision checks", ("check_cell",)),
    ("write the trajectory CSV", ("write_trajectory_csv",)),
)


def _stage_profile(argv: list[str], stages=STAGES) -> tuple[dict[str, float], float]:
    """Cumulative seconds per stage of one in-process run of the CLI, and the total."""
    from service.cli import main

    profiler = cProfile.Profile()
    start = time.perf_counter()
    profiler.runcall(main, argv)
    total = time.perf_counter() - start
    stats = pstats.Stats(profiler).stats
    by_name: dict[str, float] = {}
    for (_, _, name), (_, _, _, cumulative, _) in stats.items():
        by_name[name] = max(by_name.get(name, 0.0), cumulative)
    return {label: sum(by_name.get(n, 0.0) for n in names) for label, names in stages}, total


def _import_seconds() -> float:
    """Seconds a fresh interpreter spends importing what ``reconstruct`` needs."""
    code = (
        "import time; t = time.perf_counter(); "
        "import service.cli, service.pipelines, service.tasks, drivers.scanning.pointcloud, "
        "drivers.tracking.readers, drivers.export, recon.reconstruct; "
        "print(time.perf_counter() - t)"
    )
    runs = [
        float(subprocess.run([sys.executable, "-c", code], capture_output=True, text=True).stdout)
        for _ in range(RUNS)
    ]
    return statistics.median(runs)


def test_stage_profile_of_the_10k_1m_case(case_folder):
    folder = case_folder
    trace, scan = _case_files(folder, 10_000, 1_000_000)
    argv = ["reconstruct", str(trace), "--scan", str(scan), "--out", str(folder / "out.csv")]
    _stage_profile(argv)  # warm the file cache and numpy's first calls
    stages, total = _stage_profile(argv)
    print(
        "\n## Stages of `teachpath reconstruct`, 10k-point trace, 1M-point scan (one run in "
        "this process under cProfile, which adds a little; imports in a fresh interpreter)\n"
    )
    print("| stage | seconds |")
    print("|---|---:|")
    print(f"| imports (fresh interpreter, median) | {_import_seconds():.2f} |")
    for label, seconds in stages.items():
        print(f"| {label} | {seconds:.2f} |")
    print(f"| everything in the process after imports | {total:.2f} |")


def test_service_upload_to_result(tmp_path_factory, case_folder):
    from tests.e2e.test_server_flow import TOKEN, Server

    folder = tmp_path_factory.mktemp("service")
    trace, scan = _case_files(case_folder, 10_000, 1_000_000)
    trace_bytes, scan_bytes = trace.read_bytes(), scan.read_bytes()
    server = Server(folder / "data", token=TOKEN)
    rows = []
    try:
        client = server.client
        for _ in range(RUNS):
            sid = client.post("/sessions", json={"name": "bench"}).json()["id"]
            client.put(f"/sessions/{sid}/recording", files={"file": ("trace.csv", trace_bytes)})
            start = time.perf_counter()
            client.put(f"/sessions/{sid}/scan", files={"file": ("scan.ply", scan_bytes)})
            uploaded = time.perf_counter()
            job = client.post(f"/sessions/{sid}/reconstructions", json={}).json()
            while job["state"] not in ("succeeded", "failed", "cancelled"):
                time.sleep(0.05)  # a pendant polls or listens; faster polls take CPU from the job
                job = client.get(f"/jobs/{job['id']}").json()
            assert job["state"] == "succeeded", job["error"]
            artifact = job["result"]["reconstruction_id"]
            csv = client.get(f"/sessions/{sid}/reconstructions/{artifact}/csv")
            assert csv.status_code == 200
            server_side = datetime.fromisoformat(job["finished_at"]) - datetime.fromisoformat(
                job["created_at"]
            )
            rows.append(
                (uploaded - start, server_side.total_seconds(), time.perf_counter() - uploaded)
            )
    finally:
        server.stop()
    upload, server_job, job_s = np.array(rows).T
    total = upload + job_s
    print(
        f"\n## Through the service: 1M-point PLY uploaded, reconstruction job, CSV fetched "
        f"(seconds over {RUNS} runs; client and server share this machine)\n"
    )
    print("| step | median | min | max |")
    print("|---|---:|---:|---:|")
    for label, values in (
        ("upload the scan (24 MB)", upload),
        ("the job in the server (queued to finished)", server_job),
        ("job submitted to CSV fetched", job_s),
        ("upload to result (target 2.5)", total),
    ):
        print(f"| {label} | {np.median(values):.2f} | {values.min():.2f} | {values.max():.2f} |")


def test_plan_speed(tmp_path_factory):
    """``teachpath plan`` of a 10k-point reconstruction (10 m in rows on a plate within a UR10e's
    reach, 1M-point scan): the whole command, and its stages."""
    folder = tmp_path_factory.mktemp("plan")
    scene = scenes.serpentine_plate(10_000, 1_000_000)
    trace, scan, recon = folder / "trace.csv", folder / "scan.ply", folder / "recon.csv"
    write_trace_csv(trace, scene.recording)
    write_scan(scan, scene.scan)
    reconstruct = [TEACHPATH, "reconstruct", str(trace), "--scan", str(scan), "--out", str(recon)]
    reconstruct_s, reconstruct_peak = timed_runs(reconstruct)
    args = ["plan", str(recon), "--scan", str(scan), "--robot", "ur10e", "--speed-m-s", "0.1"]
    args += ["--out", str(folder / "trajectory.csv")]
    plan_s, plan_peak = timed_runs([TEACHPATH, *args])
    print(
        f"\n## Planning a 10k-point reconstruction: 10 m in rows on a plate, 1M-point scan, "
        f"UR10e, 0.1 m/s (seconds over {RUNS} runs)\n"
    )
    print("| command | median | min | max | peak MiB |")
    print("|---|---:|---:|---:|---:|")
    print(_row("`reconstruct` (surface)", reconstruct_s, reconstruct_peak))
    print(_row("`plan` (IK, timing, collision checks; target 0.5)", plan_s, plan_peak))
    if BASELINE is not None:
        print(f"\n## Before and after: {BASELINE} against this checkout, runs alternating\n")
        print("| case | version | median | min | max | peak MiB | before / after |")
        print("|---|---|---:|---:|---:|---:|---:|")
        _alternating(
            "`plan` 10k", [TEACHPATH, *args[:-2]], lambda w: ["--out", str(folder / f"{w}.csv")]
        )
    _stage_profile(args, PLAN_STAGES)  # warm
    stages, total = _stage_profile(args, PLAN_STAGES)
    print("\n| stage of `plan` (cProfile, one run in this process) | seconds |")
    print("|---|---:|")
    for label, seconds in stages.items():
        print(f"| {label} | {seconds:.2f} |")
    print(f"| everything in the process after imports | {total:.2f} |")


def _alternating(label: str, argv: list[str], out_of: Callable[[str], list[str]]) -> None:
    """Rows "before" and "after" of one command, this checkout's runs alternating with
    TEACHPATH_BENCH_BASELINE's (``out_of(which)`` gives each its own output arguments)."""
    runs: dict[str, tuple[list, list]] = {"before": ([], []), "after": ([], [])}
    for _ in range(RUNS):
        for which, path in (("before", BASELINE), ("after", None)):
            seconds, peak = timed_runs(argv + out_of(which), 1, pythonpath=path)
            runs[which][0].extend(seconds)
            runs[which][1].extend(peak)
    ratio = statistics.median(runs["before"][0]) / statistics.median(runs["after"][0])
    for which, (seconds, peak) in runs.items():
        extra = f" {ratio:.2f}x |" if which == "after" else " |"
        print(_row(f"{label} | {which}", seconds, peak, extra))


@pytest.mark.skipif(BASELINE is None, reason="set TEACHPATH_BENCH_BASELINE to a checkout")
def test_against_a_baseline_checkout(case_folder):
    """``reconstruct`` of this checkout and of TEACHPATH_BENCH_BASELINE, run after run."""
    folder = case_folder
    print(f"\n## Before and after: {BASELINE} against this checkout, runs alternating\n")
    print("| case | version | median | min | max | peak MiB | before / after |")
    print("|---|---|---:|---:|---:|---:|---:|")
    for n_path, n_scan, _ in CASES[:2]:
        trace, scan = _case_files(folder, n_path, n_scan)
        argv = [TEACHPATH, "reconstruct", str(trace), "--scan", str(scan)]
        _alternating(
            f"`reconstruct` {n_path:,} / {n_scan:,}",
            argv,
            lambda which: ["--out", str(folder / f"{which}.csv")],
        )
