"""Regression replay: archived sessions (bundles) run again, compared with what they stored.

For each bundle, every stored reconstruction is run again through the pipeline the service and
the command line use (:func:`service.pipelines.reconstruct`), with its stored parameters or the
ones given, and compared with the stored result point by point; every stored plan is planned
again from its stored reconstruction (so a change of the planner shows alone) and compared by
duration, feasibility and the planned TCP. A synthetic recording keeps its ground truth
(:meth:`service.artifacts.RecordingCodec.truth`): its reconstructions also report their error
against it, before and after, so a change can be judged better or worse, not only different.

The work is one task per bundle on a Dask distributed cluster (a local one by default): tasks are
plain functions of a path and a dict, the results plain rows, so any cluster whose workers can
read the bundles runs them.
"""

from __future__ import annotations

import csv
import json
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, fields
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from recon.arrays import FloatArray
from service.artifacts import as_core_params
from service.bundles import ArtifactEntry, BundleError, BundleReader
from service.reconstructions import NOT_RECON_PARAMS

if TYPE_CHECKING:
    from distributed import Client

#: The report's columns, in order.
REPORT_COLUMNS = (
    "bundle",
    "session_id",
    "session_name",
    "kind",
    "artifact_id",
    "status",
    "n_stored",
    "n_replayed",
    "deviation_mean_m",
    "deviation_max_m",
    "truth_stored_mean_m",
    "truth_stored_max_m",
    "truth_replayed_mean_m",
    "truth_replayed_max_m",
    "duration_stored_s",
    "duration_replayed_s",
    "run_time_s",
    "error",
)
#: What a row's status says.
SAME, MOVED, FAILED = "same", "moved", "failed"

#: One report row: a value (text, count or number) for each of :data:`REPORT_COLUMNS`.
Row = dict[str, str | int | float]


@dataclass(frozen=True)
class Overrides:
    """Parameters that replace the stored ones: ``reconstruction`` (ReconParams fields) and
    ``plan`` (PlanParams fields)."""

    reconstruction: dict[str, Any]
    plan: dict[str, Any]

    @classmethod
    def none(cls) -> Overrides:
        return cls({}, {})

    @classmethod
    def from_json(cls, text: str, name: str = "the parameters") -> Overrides:
        """From ``{"reconstruction": {...}, "plan": {...}}`` (either may be left out), each
        field checked against its parameter set now, before any work is queued.

        Raises
        ------
        ValueError
            Not such an object, an unknown field, or a value out of its bounds.
        """
        from recon.plan_params import PlanParams
        from recon.recon_params import ReconParams

        try:
            document = json.loads(text)
        except (ValueError, RecursionError) as exc:
            raise ValueError(f"{name} is not valid JSON ({str(exc)[:200]})") from None
        if not isinstance(document, dict) or set(document) - {"reconstruction", "plan"}:
            raise ValueError(
                f'{name} must be a JSON object with "reconstruction" and/or "plan" objects of '
                'parameters, e.g. {"reconstruction": {"alpha": 0.5}}'
            )
        parts: dict[str, dict[str, Any]] = {}
        for section, params_class in (("reconstruction", ReconParams), ("plan", PlanParams)):
            values = document.get(section, {})
            if not isinstance(values, dict):
                raise ValueError(f'{name}: "{section}" must be an object of parameters')
            known = {f.name for f in fields(params_class)}
            unknown = sorted(set(values) - known)
            if unknown:
                raise ValueError(
                    f"{name}: {section} has no parameter {', '.join(unknown)[:200]}; known: "
                    f"{', '.join(sorted(known))}"
                )
            params_class(**values)  # raises ValueError for a value out of its bounds
            parts[section] = values
        return cls(parts["reconstruction"], parts["plan"])


def find_bundles(sources: Iterable[str | Path]) -> list[Path]:
    """The bundles named: files as given, folders as every ``*.zip`` in them (sorted).

    Raises
    ------
    ValueError
        A source that does not exist, or no bundle at all.
    """
    found: list[Path] = []
    for source in sources:
        path = Path(source)
        if path.is_dir():
            found += sorted(p.resolve() for p in path.glob("*.zip") if p.is_file())
        elif path.is_file():
            found.append(path.resolve())  # a remote worker resolves nothing against our folder
        else:
            raise ValueError(f"{source} is neither a bundle nor a folder of bundles")
    if not found:
        raise ValueError("no bundles to replay: give SESSION.zip files or folders holding them")
    return found


def _row(reader_or_path: BundleReader | str | Path, **values: str | int | float) -> Row:
    row: Row = dict.fromkeys(REPORT_COLUMNS, "")
    if isinstance(reader_or_path, BundleReader):
        session = reader_or_path.manifest.session
        row.update(
            bundle=str(reader_or_path.path), session_id=session.id, session_name=session.name
        )
    else:
        row.update(bundle=str(reader_or_path))
    row.update(values)
    return row


def replay_bundle(
    path: str, overrides: Overrides, tolerance_m: float, share_cores: int | None = None
) -> list[Row]:
    """Replay one bundle's reconstructions and plans (the task a worker runs).

    Parameters
    ----------
    path : str
    overrides : Overrides
    tolerance_m : float
    share_cores : int, optional
        On a local cluster, the number of workers sharing this machine's cores: the worker takes
        its share (see :func:`_take_share_of_cores`).

    Returns
    -------
    list of dict
        One report row per stored reconstruction or trajectory (one ``failed`` row for a bundle
        that cannot be read).
    """
    if share_cores:
        _take_share_of_cores(share_cores)
    try:
        reader = BundleReader(path)
    except BundleError as exc:
        return [_row(path, kind="bundle", status=FAILED, error=str(exc))]
    rows: list[Row] = []
    with reader:
        for artifact in reader.artifacts("reconstruction"):
            rows.append(_guarded(reader, artifact, _reconstruction, overrides, tolerance_m))
        for artifact in reader.artifacts("trajectory"):
            rows.append(_guarded(reader, artifact, _plan, overrides, tolerance_m))
    if not rows:
        rows.append(_row(reader, kind="session", status=SAME, error="nothing to replay"))
    return rows


_SHARE_TAKEN: list[bool] = []


def _take_share_of_cores(n_workers: int) -> None:
    """Keep this worker process on its share of the cores (once per process).

    The reconstruction runs its own threads (the per-point chunks, the k-d tree queries on every
    core): with one worker per core, each worker's threads would compete for all of them. Worker
    i of n takes cores i*k .. i*k+k-1 (k = cores // n, at least one); one worker keeps them all.
    """
    import os

    if _SHARE_TAKEN:
        return
    _SHARE_TAKEN.append(True)
    try:
        from distributed import get_worker

        index = int(get_worker().name)
    except (ImportError, ValueError, TypeError):  # not in a local cluster's worker: as it is
        return
    cores = sorted(os.sched_getaffinity(0))
    k = max(1, len(cores) // n_workers)
    start = (index * k) % len(cores)
    os.sched_setaffinity(0, cores[start : start + k])


#: How one stored artifact is replayed: (reader, artifact, overrides, tolerance_m) -> its row.
Replay = Callable[[BundleReader, ArtifactEntry, Overrides, float], Row]


def _guarded(
    reader: BundleReader,
    artifact: ArtifactEntry,
    replay: Replay,
    overrides: Overrides,
    tolerance_m: float,
) -> Row:
    """One artifact's row; what fails is reported in it and stops nothing else."""
    from drivers.errors import DriverError
    from recon.errors import ReconError

    start = time.perf_counter()
    try:
        return replay(reader, artifact, overrides, tolerance_m)
    except Exception as exc:  # one result's failure is its row; the others go on
        if not isinstance(exc, ReconError | DriverError | BundleError | ValueError | KeyError):
            exc = RuntimeError(f"unexpected {type(exc).__name__}: {exc}")
        return _row(
            reader,
            kind=artifact.kind,
            artifact_id=artifact.id,
            status=FAILED,
            run_time_s=round(time.perf_counter() - start, 3),
            error=f"{type(exc).__name__}: {exc}"[:500],
        )


def _reconstruction(
    reader: BundleReader, artifact: ArtifactEntry, overrides: Overrides, tolerance_m: float
) -> Row:
    from recon.recon_params import ReconParams
    from service import pipelines
    from service.artifacts import ReconstructionCodec, RecordingCodec, ScanCodec

    inputs = artifact.inputs
    params = dict(artifact.params)
    T_init = params.pop("T_scan_tracker_init", None)
    params = {k: v for k, v in params.items() if k not in NOT_RECON_PARAMS}
    params = as_core_params(params, overrides.reconstruction)
    ids = inputs.get("recording_ids") or [inputs["recording_id"]]
    recording_arrays = [reader.arrays(rid) for rid in ids]
    recordings = [RecordingCodec.decode(arrays) for arrays in recording_arrays]
    truth = RecordingCodec.truth(recording_arrays[0])
    scan_id, touches_id = inputs.get("scan_id"), inputs.get("touches_id")
    scan = ScanCodec.decode(reader.arrays(scan_id)) if scan_id else None
    touches = RecordingCodec.decode(reader.arrays(touches_id)) if touches_id else None
    stored = ReconstructionCodec.decode(reader.arrays(artifact.id)).points_m
    start = time.perf_counter()
    outcome = pipelines.reconstruct(
        recordings if len(recordings) > 1 else recordings[0],
        scan,
        params=ReconParams(**params),
        T_scan_tracker_init=T_init,
        touches=touches,
    )
    elapsed = time.perf_counter() - start
    replayed = np.asarray(outcome.reconstruction.points_m)
    deviation = path_deviation_m(stored, replayed)
    row = _row(
        reader,
        kind="reconstruction",
        artifact_id=artifact.id,
        status=SAME if _within(deviation, tolerance_m) else MOVED,
        n_stored=len(stored),
        n_replayed=len(replayed),
        deviation_mean_m=float(deviation.mean()),
        deviation_max_m=float(deviation.max()),
        run_time_s=round(elapsed, 3),
    )
    if truth is not None:
        from recon.metrics import distance_to_curve

        for label, points in (("stored", stored), ("replayed", replayed)):
            error = distance_to_curve(points, truth)
            row[f"truth_{label}_mean_m"] = float(error.mean())
            row[f"truth_{label}_max_m"] = float(error.max())
    return row


def _within(deviation: FloatArray, tolerance_m: float) -> bool:
    """Every deviation finite and within the tolerance (a NaN has moved, whatever it compares)."""
    return bool(len(deviation)) and bool(np.all(deviation <= tolerance_m))


def path_deviation_m(stored_m: FloatArray, replayed_m: FloatArray) -> FloatArray:
    """How far a replayed path lies from the stored one, per point (m).

    Point by point when both have the same points (the same parameters resample alike);
    otherwise each path's points' distance to the other path (both ways, so a stretch that
    one of them lacks counts).
    """
    stored_m, replayed_m = np.asarray(stored_m), np.asarray(replayed_m)
    if stored_m.shape == replayed_m.shape:
        per_point: FloatArray = np.linalg.norm(replayed_m - stored_m, axis=1)
        return per_point
    from recon.metrics import distance_to_curve

    return np.concatenate(
        [distance_to_curve(replayed_m, stored_m), distance_to_curve(stored_m, replayed_m)]
    )


def _plan(
    reader: BundleReader, artifact: ArtifactEntry, overrides: Overrides, tolerance_m: float
) -> Row:
    from recon.errors import CollisionError, InfeasibleTrajectoryError
    from recon.kinematics import DHCalibration
    from recon.plan_params import PlanParams
    from recon.recon_params import ReconParams
    from service import pipelines
    from service.artifacts import (
        ReconstructionCodec,
        ScanCodec,
        TrajectoryCodec,
        TrajectorySummary,
    )

    params = dict(artifact.params)
    T_base = params.pop("T_base_tracker", None)
    start_from = params.pop("start_from", "given")
    note = ""
    if "keep_out_boxes" not in params:
        note = "the stored plan does not record its cell's keep-out boxes and planes: none used"
    boxes = params.pop("keep_out_boxes", [])
    planes = params.pop("cell_planes", [])
    params = as_core_params(params, overrides.plan)
    recon_id = artifact.inputs["reconstruction_id"]
    recon_arrays = reader.arrays(recon_id)
    recon_params = {
        k: v for k, v in reader.artifact(recon_id).params.items() if k not in NOT_RECON_PARAMS
    }
    scan_id = artifact.inputs.get("scan_id")
    summary = TrajectorySummary.model_validate(artifact.summary)
    stored_duration = float(sum(summary.phase_durations_s.values()))
    stored_tcp = reader.arrays(artifact.id)["tcp_m"]
    start = time.perf_counter()
    move_of = artifact.inputs.get("move_to_start_of")
    calibration = (
        None if summary.calibration is None else DHCalibration.from_dict(summary.calibration)
    )  # the arm the stored plan was solved for, calibrated as it was
    scan = ScanCodec.decode(reader.arrays(scan_id)) if scan_id else None
    try:
        outcome: pipelines.MoveOutcome | pipelines.PlanOutcome
        if move_of is not None:  # a move to a plan's start: made again from the same joints
            outcome = pipelines.move_to_start(
                params["start_q_rad"],
                TrajectoryCodec.decode(
                    reader.arrays(move_of),
                    TrajectorySummary.model_validate(reader.artifact(move_of).summary),
                ),
                target_id=move_of,
                target_summary=reader.artifact(move_of).summary,
                params=PlanParams(**params),
                scan=scan,
                T_scan_tracker=ReconstructionCodec.decode(recon_arrays).T_scan_tracker,
                T_base_tracker=T_base,
                keep_out_boxes=boxes,
                cell_planes=planes,
                start_from=start_from,
                calibration=calibration,
            )
        else:
            outcome = pipelines.plan(
                ReconstructionCodec.decode(recon_arrays),
                params=PlanParams(**params),
                T_base_tracker=T_base,
                scan_model=ReconstructionCodec.scan_model(recon_arrays),
                recon_params=ReconParams(**as_core_params(recon_params, {})),
                scan=scan,
                keep_out_boxes=boxes,
                cell_planes=planes,
                start_from=start_from,
                calibration=calibration,
            )
    except (InfeasibleTrajectoryError, CollisionError) as exc:
        # The stored plan was feasible: that it no longer is, is the finding.
        return _row(
            reader,
            kind="trajectory",
            artifact_id=artifact.id,
            status=FAILED,
            duration_stored_s=round(stored_duration, 4),
            run_time_s=round(time.perf_counter() - start, 3),
            error=f"no longer feasible: {exc}"[:500],
        )
    elapsed = time.perf_counter() - start
    trajectory = outcome.trajectory
    duration = float(sum(trajectory.phase_durations_s().values()))  # as the summary adds them
    tcp = np.asarray(trajectory.tcp_m)
    deviation = path_deviation_m(stored_tcp, tcp)
    moved = not _within(deviation, tolerance_m) or not abs(duration - stored_duration) <= 1e-3
    return _row(
        reader,
        kind="trajectory",
        artifact_id=artifact.id,
        status=MOVED if moved else SAME,
        n_stored=len(stored_tcp),
        n_replayed=len(tcp),
        deviation_mean_m=float(deviation.mean()),
        deviation_max_m=float(deviation.max()),
        duration_stored_s=round(stored_duration, 4),
        duration_replayed_s=round(duration, 4),
        run_time_s=round(elapsed, 3),
        error=note,
    )


# -- running on a cluster ------------------------------------------------------------------------


@dataclass(frozen=True)
class ReplaySummary:
    n_bundles: int
    n_rows: int
    n_moved: int
    n_failed: int
    wall_s: float

    @property
    def passed(self) -> bool:
        return self.n_moved == 0 and self.n_failed == 0


def run_replay(
    bundles: list[Path],
    *,
    report_path: Path,
    overrides: Overrides,
    tolerance_m: float,
    workers: int | None = None,
    scheduler: str | None = None,
    on_result: Callable[[int, int, list[Row]], None] | None = None,
    on_cluster: Callable[[Client], None] | None = None,
) -> ReplaySummary:
    """Replay bundles on Dask, one task per bundle, and stream the rows to a CSV report.

    Parameters
    ----------
    bundles : list of Path
        Readable by the workers (on one machine: anywhere; on a cluster: a shared folder).
    report_path : Path
        The CSV, written as results arrive (complete when this returns; a PNG summary beside it
        is :func:`plot_report`'s).
    overrides : Overrides
    tolerance_m : float
        A result that moved more than this is ``moved``.
    workers : int, optional
        Workers of the local cluster started here (default: one per core), each one process
        with one thread (the numerical work holds the GIL in places).
    scheduler : str, optional
        ``tcp://HOST:PORT`` of an existing cluster instead.
    on_result : callable, optional
        ``(done, total, rows)`` after each bundle (progress).
    on_cluster : callable, optional
        Given the Dask client once connected (to show its dashboard link).
    """
    try:
        from distributed import Client, LocalCluster, as_completed
    except ImportError as error:
        from drivers.registry import missing_dependency

        raise missing_dependency(error, "replay (one Dask task per session)") from None

    start = time.perf_counter()
    cluster = None
    if scheduler is None:
        import os

        n = workers or len(os.sched_getaffinity(0))
        # Loopback only, no dashboard port on every interface: a replay serves nobody.
        # distributed's LocalCluster, Client, as_completed and Client.close are unannotated
        # (mypy's strict no-untyped-call).
        cluster = LocalCluster(  # type: ignore[no-untyped-call]
            n_workers=n,
            threads_per_worker=1,
            processes=True,
            host="127.0.0.1",
            dashboard_address=None,
        )
    try:
        client = Client(cluster if cluster is not None else scheduler)  # type: ignore[no-untyped-call]
    except BaseException:
        if cluster is not None:
            cluster.close()
        raise
    n_moved = n_failed = n_rows = 0
    try:
        if on_cluster is not None:
            on_cluster(client)
        share = len(cluster.workers) if cluster is not None else None
        futures = {
            client.submit(replay_bundle, str(path), overrides, tolerance_m, share, pure=False): path
            for path in bundles
        }
        with _report_writer(report_path) as write:
            for done, future in enumerate(as_completed(futures), start=1):  # type: ignore[no-untyped-call]
                try:
                    rows: list[Row] = future.result()
                except Exception as exc:  # a worker died or the task raised: report, go on
                    rows = [
                        _row(
                            futures[future],
                            kind="bundle",
                            status=FAILED,
                            error=f"the task failed: {type(exc).__name__}: {exc}"[:500],
                        )
                    ]
                for row in rows:
                    write(row)
                n_rows += len(rows)
                n_moved += sum(row["status"] == MOVED for row in rows)
                n_failed += sum(row["status"] == FAILED for row in rows)
                if on_result is not None:
                    on_result(done, len(futures), rows)
    finally:
        client.close()  # type: ignore[no-untyped-call]
        if cluster is not None:
            cluster.close()
    return ReplaySummary(len(bundles), n_rows, n_moved, n_failed, time.perf_counter() - start)


class _report_writer:
    """The report CSV, written under a temporary name, row by row as results arrive (flushed),
    renamed into place when complete."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self.tmp = self.path.with_name(f".{self.path.name}.partial")

    def __enter__(self) -> Callable[[Row], None]:
        self.handle = self.tmp.open("w", newline="")
        self.writer = csv.DictWriter(self.handle, fieldnames=REPORT_COLUMNS)
        self.writer.writeheader()
        return self._write

    def _write(self, row: Row) -> None:
        self.writer.writerow(
            {k: (f"{v:.9g}" if isinstance(v, float) else v) for k, v in row.items()}
        )
        self.handle.flush()

    def __exit__(self, kind: type[BaseException] | None, *_: object) -> None:
        self.handle.close()
        if kind is None:
            self.tmp.replace(self.path)
        else:
            self.tmp.unlink(missing_ok=True)


def read_report(path: Path) -> list[dict[str, str]]:
    with Path(path).open(newline="") as handle:
        return list(csv.DictReader(handle))


def plot_report(report_path: Path, png_path: Path, tolerance_m: float) -> None:
    """A PNG summary of a report: each result's largest deviation against the tolerance, and
    the error against the ground truth before and after where there is one."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = read_report(report_path)
    numbers = [r for r in rows if r["deviation_max_m"] not in ("", None)]
    truth = [r for r in numbers if r["truth_stored_max_m"] not in ("", None)]
    figure, axes = plt.subplots(1, 2 if truth else 1, figsize=(12 if truth else 7, 4.5))
    axes = np.atleast_1d(axes)
    deviation = np.array([float(r["deviation_max_m"]) for r in numbers]) * 1e3
    colours = ["tab:red" if r["status"] == MOVED else "tab:green" for r in numbers]
    floor = 1e-6  # mm: identical results (0) are drawn at this height
    axes[0].bar(np.arange(len(numbers)), np.maximum(deviation, floor), color=colours)
    axes[0].axhline(tolerance_m * 1e3, color="k", ls="--", label="tolerance")
    axes[0].set_yscale("log")
    axes[0].set_xlabel("result (report row)")
    axes[0].set_ylabel("largest deviation from the stored result (mm; 0 at 1e-6)")
    n_failed = sum(r["status"] == FAILED for r in rows)
    axes[0].set_title(
        f"{len(numbers)} results: {sum(r['status'] == MOVED for r in numbers)} moved, "
        f"{n_failed} failed"
    )
    axes[0].legend()
    if truth:
        before = np.array([float(r["truth_stored_max_m"]) for r in truth]) * 1e3
        after = np.array([float(r["truth_replayed_max_m"]) for r in truth]) * 1e3
        axes[1].scatter(before, after, s=12)
        top = max(before.max(), after.max()) * 1.1
        axes[1].plot([0, top], [0, top], "k--", lw=1, label="unchanged")
        axes[1].set_xlabel("stored: max error against the ground truth (mm)")
        axes[1].set_ylabel("replayed: max error (mm)")
        axes[1].set_title(
            f"ground truth: {int(np.sum(after < before))} better, "
            f"{int(np.sum(after > before))} worse"
        )
        axes[1].legend()
    figure.tight_layout()
    figure.savefig(png_path, dpi=100)
    plt.close(figure)
