"""What the service does, between the routers and the store: the session flow.

Routers validate requests and call these methods; long work becomes a job (see ``jobs.py``),
uploads are parsed in a worker process, and every product is an immutable artifact naming its
inputs and parameters.
"""

from __future__ import annotations

import logging
import math
import threading
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from drivers.errors import InputFileError
from drivers.tracking.readers import RawTrace, trace_from_raw
from service import tasks
from service.captures import CaptureRunner, read_capture_file
from service.errors import ApiError, not_found
from service.executions import ExecutionRunner
from service.jobs import JobManager
from service.settings import Settings
from service.store import KINDS, ArtifactRow, SessionRow, Store, iso, new_id, now

log = logging.getLogger("teachpath.service")

#: Where the demo workpiece sits in front of a UR5e, metres (the demo session's calibration).
DEMO_T_BASE_TRACKER = [[1.0, 0, 0, 0.45], [0, 1.0, 0, 0.1], [0, 0, 1.0, 0.05], [0, 0, 0, 1.0]]


@dataclass
class AppContext:
    settings: Settings
    store: Store
    jobs: JobManager
    token: str
    executions: dict[str, ExecutionRunner] = field(default_factory=dict)
    execution_jobs: dict[str, str] = field(default_factory=dict)  # execution id -> job id
    captures: dict[str, CaptureRunner] = field(default_factory=dict)
    lock: threading.Lock = field(default_factory=threading.Lock)

    # -- lookups -----------------------------------------------------------------------------

    def session(self, session_id: str) -> SessionRow:
        row = self.store.session(session_id)
        if row is None:
            raise not_found("session", session_id)
        return row

    def artifact(self, session_id: str, kind: str, artifact_id: str) -> ArtifactRow:
        self.session(session_id)
        row = self.store.artifact(artifact_id, kind=kind, session_id=session_id)
        if row is None:
            raise not_found(kind, artifact_id)
        return row

    # -- uploads -----------------------------------------------------------------------------

    async def add_recording(
        self,
        session_id: str,
        content: bytes,
        filename: str,
        fmt: str | None,
        units: str | None,
        *,
        rigid_body: str | None = None,
        marker: str | None = None,
        piece: int | None = None,
    ) -> ArtifactRow:
        session = self.session(session_id)
        arrays, summary = await self.jobs.run(
            tasks.parse_recording_task,
            content,
            filename,
            fmt,
            units,
            rigid_body,
            marker,
            self._tip_for(session, marker),
            piece,
        )
        artifact_id = new_id(KINDS["recording"])
        row = self._store_arrays(
            session_id,
            "recording",
            artifact_id,
            arrays,
            params={
                "format": summary["format"],
                "units": summary.get("units") or units,
                "rigid_body": rigid_body,
                "marker": marker,
                "piece": summary.get("piece"),
                "tip_offset_m": session.tip_offset_m if summary["tip_offset_applied"] else None,
            },
            summary=summary,
            source_name=filename,
        )
        self._keep_upload(artifact_id, filename, content)
        self.store.update_session(session_id, recording_id=artifact_id)
        return row

    @staticmethod
    def _tip_for(session: SessionRow, marker: str | None):
        """The session's tip offset, for recordings of a rigid body (a single marker has no
        orientation to carry an offset)."""
        if session.tip_offset_m is None or marker is not None:
            return None
        return session.tip_offset_m

    async def add_scan(
        self,
        session_id: str,
        content: bytes,
        filename: str,
        fmt: str | None,
        units: str,
        options: dict | None = None,
    ) -> ArtifactRow:
        self.session(session_id)
        # A client may lower the reader's resource limits, not raise them past the server's.
        limits = {
            "max_unpacked_mb": self.settings.max_scan_unpacked_mb,
            "timeout_s": self.settings.max_scan_decode_s,
        }
        arrays, summary = await self.jobs.run(
            tasks.parse_scan_task, content, filename, fmt, units, options, limits
        )
        artifact_id = new_id(KINDS["scan"])
        row = self._store_arrays(
            session_id,
            "scan",
            artifact_id,
            arrays,
            params={"format": summary["format"], "units": units, "options": options},
            summary=summary,
            source_name=filename,
        )
        self._keep_upload(artifact_id, filename, content)
        self.store.update_session(session_id, scan_id=artifact_id)
        return row

    # -- calibrations ------------------------------------------------------------------------

    def set_calibration(self, session_id: str, request) -> SessionRow:
        """Set the calibrations named in the request (an explicit null clears one)."""
        self.session(session_id)
        fields = {name: getattr(request, name) for name in request.model_fields_set}
        return self.store.update_session(session_id, **fields)

    async def pivot_calibration(
        self,
        session_id: str,
        content: bytes,
        filename: str,
        fmt: str | None,
        units: str | None,
        rigid_body: str | None,
    ) -> tuple[SessionRow, dict]:
        self.session(session_id)
        result = await self.jobs.run(
            tasks.pivot_task, content, filename, fmt, units, rigid_body, None
        )
        row = self.store.record_calibration(
            session_id,
            "pivot",
            {**result, "source_name": filename, "at": now().isoformat()},
            tip_offset_m=result["tip_offset_m"],
        )
        return row, result

    def base_calibration(self, session_id: str, request) -> tuple[SessionRow, dict]:
        self.session(session_id)
        from recon.calibrate import fit_point_pairs

        scale = 1e-3 if request.units == "mm" else 1.0
        base = [pair.base for pair in request.pairs]
        tracker = [pair.tracker for pair in request.pairs]
        fit = fit_point_pairs(
            np.array(base) * scale, np.array(tracker) * scale, tolerance_m=request.tolerance_m
        )
        result = {
            "T_base_tracker": fit.T_a_b.tolist(),
            "residuals_m": fit.residuals_m.tolist(),
            "leave_one_out_m": [None if np.isnan(v) else float(v) for v in fit.leave_one_out_m],
            "residual_rms_m": fit.residual_rms_m,
            "suspect": fit.suspect.tolist(),
            "used": fit.used.tolist(),
            "tolerance_m": fit.tolerance_m,
            "report": fit.lines(),
        }
        row = self.store.record_calibration(
            session_id,
            "base",
            {**result, "at": now().isoformat()},
            T_base_tracker=result["T_base_tracker"],
        )
        return row, result

    def _keep_upload(self, artifact_id: str, filename: str, content: bytes) -> None:
        """The original bytes too: raw inputs are kept as they came."""
        safe = "".join(c if c.isalnum() or c in "._-" else "_" for c in Path(filename).name)
        self.store.write_bytes(f"uploads/{artifact_id}/{safe or 'upload'}", content)

    def _store_arrays(
        self,
        session_id,
        kind,
        artifact_id,
        arrays,
        *,
        inputs=None,
        params=None,
        summary=None,
        source_name=None,
    ) -> ArtifactRow:
        path, sha, size = self.store.write_arrays(artifact_id, arrays)
        return self.store.add_artifact(
            artifact_id=artifact_id,
            session_id=session_id,
            kind=kind,
            path=path,
            sha256=sha,
            size=size,
            inputs=inputs,
            params=params,
            summary=summary,
            source_name=source_name,
        )

    # -- jobs --------------------------------------------------------------------------------

    def reconstruct(self, session_id: str, request) -> dict:
        session = self.session(session_id)
        recording_id = request.recording_id or session.recording_id
        if recording_id is None:
            raise ApiError(
                409,
                "no_recording",
                "the session has no recording: upload one "
                "(PUT /sessions/{id}/recording) or capture one first",
            )
        recording = self.artifact(session_id, "recording", recording_id)
        scan = None
        if request.use_scan:
            scan_id = request.scan_id or session.scan_id
            if scan_id is not None:
                scan = self.artifact(session_id, "scan", scan_id)
        params = request.model_dump(
            exclude={"recording_id", "scan_id", "use_scan", "registration", "T_scan_tracker"}
        )
        params["register"] = request.registration
        T_init = request.T_scan_tracker or session.T_scan_tracker
        from recon.types import ReconParams

        ReconParams(**params)  # refuse bad combinations now, not in the worker
        out_id = new_id(KINDS["reconstruction"])
        inputs = {"recording_id": recording.id, "scan_id": scan.id if scan else None}
        stored_params = {**params, "T_scan_tracker_init": T_init if scan else None}

        def done(summary: dict) -> dict:
            self.store.add_file_artifact(
                artifact_id=out_id,
                session_id=session_id,
                kind="reconstruction",
                path=f"arrays/{out_id}.npz",
                inputs=inputs,
                params=stored_params,
                summary=summary,
            )
            return {"reconstruction_id": out_id}

        job = self.jobs.submit(
            session_id,
            "reconstruction",
            {**stored_params, **inputs},
            tasks.reconstruct_task,
            (
                str(self.store.path_of(recording)),
                str(self.store.path_of(scan)) if scan else None,
                params,
                str(self.store.data_dir / f"arrays/{out_id}.npz"),
                str(self.preview_path(out_id)),
                T_init if scan else None,
            ),
            done,
        )
        return job

    def preview_path(self, reconstruction_id: str) -> Path:
        return self.store.data_dir / "arrays" / f"{reconstruction_id}.png"

    def plan(self, session_id: str, request) -> dict:
        session = self.session(session_id)
        recon = self.artifact(session_id, "reconstruction", request.reconstruction_id)
        from recon.kinematics import model
        from recon.plan import PlanParams

        model(request.robot)
        T = request.T_base_tracker or session.T_base_tracker
        params = request.model_dump(exclude={"reconstruction_id", "T_base_tracker"})
        PlanParams(**params)
        scan = None
        scan_id = recon.inputs.get("scan_id")
        if scan_id:
            scan = self.store.artifact(scan_id, kind="scan")
        registration = recon.summary.get("registration") or {}
        T_scan_tracker = recon.summary.get("T_scan_tracker") or registration.get("T_scan_tracker")
        out_id = new_id(KINDS["trajectory"])
        inputs = {"reconstruction_id": recon.id, "scan_id": scan_id}
        stored_params = {**params, "T_base_tracker": T}

        def done(report: dict) -> dict:
            self.store.add_file_artifact(
                artifact_id=out_id,
                session_id=session_id,
                kind="trajectory",
                path=f"arrays/{out_id}.npz",
                inputs=inputs,
                params=stored_params,
                summary=report,
            )
            return {"trajectory_id": out_id}

        return self.jobs.submit(
            session_id,
            "trajectory",
            {**stored_params, **inputs},
            tasks.plan_task,
            (
                str(self.store.path_of(recon)),
                str(self.store.path_of(scan)) if scan else None,
                params,
                T,
                T_scan_tracker,
                str(self.store.data_dir / f"arrays/{out_id}.npz"),
            ),
            done,
        )

    def execute(self, session_id: str, request) -> dict:
        self.session(session_id)
        trajectory = self.artifact(session_id, "trajectory", request.trajectory_id)
        summary = trajectory.summary
        out_id = new_id(KINDS["execution"])
        inputs = {"trajectory_id": trajectory.id}
        params = {
            "backend": request.backend,
            "mode": request.mode,
            "tolerance_m": request.tolerance_m,
            "execution_id": out_id,
        }
        if request.backend == "sim":

            def done(report: dict) -> dict:
                self.store.add_file_artifact(
                    artifact_id=out_id,
                    session_id=session_id,
                    kind="execution",
                    path=f"arrays/{out_id}.npz",
                    inputs=inputs,
                    params={
                        "backend": "sim",
                        "dry_run": True,
                        "mode": request.mode,
                        "tolerance_m": request.tolerance_m,
                    },
                    summary=report,
                )
                return {"execution_id": out_id, "completed": report["completed"]}

            job = self.jobs.submit(
                session_id,
                "execution",
                {**params, **inputs},
                tasks.dry_run_task,
                (
                    str(self.store.path_of(trajectory)),
                    summary["robot"],
                    summary["requested_speed_m_s"],
                    summary["speed_drops"],
                    str(self.store.data_dir / f"arrays/{out_id}.npz"),
                    request.mode,
                    request.tolerance_m,
                ),
                done,
            )
            self.execution_jobs[out_id] = job.id
            return job
        return self._execute_on_arm(session_id, trajectory, request, out_id, inputs, params)

    def _execute_on_arm(self, session_id, trajectory, request, out_id, inputs, params):
        settings = self.settings
        if settings.ur_host is None:
            raise ApiError(
                409,
                "no_robot",
                "no real arm is configured (TEACHPATH_UR_HOST); use backend 'sim' for a dry run",
            )
        if trajectory.summary["robot"] != settings.ur_robot:
            raise ApiError(
                409,
                "trajectory_mismatch",
                f"the trajectory was planned for a {trajectory.summary['robot']}; the "
                f"configured arm is a {settings.ur_robot}",
            )
        if not request.confirm:
            raise ApiError(
                409,
                "confirmation_required",
                'moving a real arm needs "confirm": true in the request',
            )
        speed = trajectory.summary["requested_speed_m_s"]
        if speed > settings.max_speed_m_s:
            raise ApiError(
                409,
                "speed_cap",
                f"the trajectory runs at {speed} m/s; this "
                f"server allows at most {settings.max_speed_m_s} m/s on a real arm",
            )
        if not self._passed_dry_run(session_id, trajectory.id, request):
            raise ApiError(
                409,
                "dry_run_required",
                f"this trajectory has not passed a dry run in mode {request.mode!r}"
                + (" with the same tolerance_m" if request.mode == "movepath" else "")
                + ": execute it with backend 'sim' first",
            )
        from drivers.robot.base import create_backend
        from drivers.robot.ur_rtde import URRtdeConfig

        loaded = tasks.load_trajectory(
            str(self.store.path_of(trajectory)), trajectory.summary["robot"], speed
        )
        backend = create_backend(URRtdeConfig(host=settings.ur_host, robot=settings.ur_robot))
        job = self.store.create_job(session_id, "execution", {**params, **inputs})

        def record(execution_record, fault) -> dict:
            arrays = (
                {}
                if execution_record is None
                else {
                    "t_s": execution_record.t_s,
                    "q_planned_rad": execution_record.q_planned_rad,
                    "q_actual_rad": execution_record.q_actual_rad,
                }
            )
            summary = {
                "completed": bool(execution_record and execution_record.completed),
                "fault": fault or (execution_record.fault if execution_record else None),
                "samples": 0 if execution_record is None else len(execution_record),
            }
            self._store_arrays(
                session_id,
                "execution",
                out_id,
                arrays,
                inputs=inputs,
                params={
                    "backend": "ur_rtde",
                    "host": settings.ur_host,
                    "mode": request.mode,
                    "tolerance_m": request.tolerance_m,
                },
                summary=summary,
            )
            return {"execution_id": out_id, **summary}

        runner = ExecutionRunner(
            self.store,
            job.id,
            backend,
            loaded,
            record,
            mode=request.mode,
            tolerance_m=request.tolerance_m,
        )
        with self.lock:
            self.executions[out_id] = runner
            self.execution_jobs[out_id] = job.id
        runner.start()
        return self.store.job(job.id)

    def _passed_dry_run(self, session_id: str, trajectory_id: str, request) -> bool:
        """A completed, fault-free dry run of this trajectory, run the way it is to run now."""
        return any(
            row.inputs.get("trajectory_id") == trajectory_id
            and row.params.get("dry_run")
            and row.params.get("mode", "servoj") == request.mode
            and (
                request.mode == "servoj"
                or math.isclose(row.params.get("tolerance_m", 5e-4), request.tolerance_m)
            )
            and row.summary.get("completed")
            and not row.summary.get("faults")
            for row in self.store.artifacts(session_id, "execution")
        )

    def stop_execution(self, execution_id: str) -> dict:
        job_id = self.execution_jobs.get(execution_id)
        if job_id is None:
            job = next(
                (
                    j
                    for j in self.store.jobs()
                    if j.kind == "execution" and j.params.get("execution_id") == execution_id
                ),
                None,
            )
            if job is None:
                raise not_found("execution", execution_id)
            job_id = job.id
        runner = self.executions.get(execution_id)
        if runner is not None:
            runner.stop()
        else:
            job = self.store.job(job_id)
            if job.state in ("queued",):
                self.jobs.cancel(job_id)
        return self.store.job(job_id)

    # -- captures ----------------------------------------------------------------------------

    def start_capture(self, session_id: str, request) -> object:
        self.session(session_id)
        source_request = request.source
        from drivers.tracking.base import create_source

        if source_request.kind == "replay":
            from drivers.tracking.replay import ReplayConfig

            recording = self.artifact(session_id, "recording", source_request.recording_id)
            source = create_source(
                ReplayConfig(speed=source_request.speed),
                recording=tasks.recording_from(self.store.read_arrays(recording)),
            )
        else:
            from drivers.tracking.natnet_source import NatNetConfig

            # The receiver runs in a child process of its own (no frame lost to the GIL held
            # elsewhere here); it connects when the runner asks for the first batch, and a
            # server that does not answer fails the capture with a clear error.
            source = create_source(
                NatNetConfig(**source_request.model_dump(), stall_timeout_s=None)
            )
        row = self.store.create_capture(session_id, source_request.model_dump())
        runner = CaptureRunner(self.store, row.id, source, self.finish_capture)
        self.captures[row.id] = runner
        runner.start()
        return row

    def stop_capture(self, session_id: str, capture_id: str):
        row = self.store.capture(capture_id)
        if row is None or row.session_id != session_id:
            raise not_found("capture", capture_id)
        runner = self.captures.get(capture_id)
        if runner is not None:
            runner.stop()
            runner.thread.join(timeout=10)
        return self.store.capture(capture_id)

    def finish_capture(self, capture_id: str, state: str, error: str | None) -> None:
        """Turn a capture's file into a recording (also for one interrupted by a restart)."""
        row = self.store.capture(capture_id)
        session = self.store.session(row.session_id)
        recording_id = None
        try:
            raw = RawTrace(read_capture_file(self.store.data_dir / row.path), "capture")
            # A live feed tracks the rigid body: move it to the tip (when it has orientations).
            # A replayed recording is stored at the tip already.
            live = row.source.get("kind") == "natnet"
            tip = session.tip_offset_m if live else None
            trace = trace_from_raw(
                raw,
                tip_offset_m=None if tip is None else np.array(tip),
                tip_needs_orientations=False,
            )
            arrays = tasks.recording_arrays(trace.recording)
            recording_id = new_id(KINDS["recording"])
            summary = tasks.recording_summary(arrays, "capture")
            summary.update(trace.summary())
            self._store_arrays(
                row.session_id,
                "recording",
                recording_id,
                arrays,
                inputs={"capture_id": capture_id},
                params={
                    "format": "capture",
                    "tip_offset_m": tip if trace.tip_offset_applied else None,
                    "piece": trace.piece,
                },
                summary=summary,
            )
            self.store.update_session(row.session_id, recording_id=recording_id)
        except InputFileError as exc:
            # Nothing to keep is a failure whatever ended the capture; say both.
            recording_id = None
            reason = f"nothing usable was received: {exc}"
            state, error = "failed", (reason if error is None else f"{error}; {reason}")[:500]
        except (OSError, ValueError) as exc:
            recording_id = None
            state, error = "failed", f"the capture file could not be read: {exc}"
        self.store.update_capture(capture_id, state=state, recording_id=recording_id, error=error)
        self.captures.pop(capture_id, None)

    # -- start-up ----------------------------------------------------------------------------

    def recover(self) -> None:
        """After a restart: fail jobs that were running, keep what captures received."""
        failed = self.store.fail_interrupted_jobs()
        if failed:
            log.warning("marked %d interrupted job(s) failed", failed)
        for row in self.store.stop_interrupted_captures():
            self.finish_capture(
                row.id,
                "interrupted",
                "the service stopped during the capture; the samples received so far were kept",
            )

    def create_demo_session(self) -> SessionRow | None:
        """The demo session (the paper's Fig. 4 scene), unless one exists."""
        if any(s.name == "demo" for s in self.store.sessions()):
            return None
        from recon import scenes

        scene = scenes.cylinder_edge(0)
        session = self.store.create_session("demo")
        rec_id, scan_id = new_id(KINDS["recording"]), new_id(KINDS["scan"])
        rec = scene.recording
        self._store_arrays(
            session.id,
            "recording",
            rec_id,
            {"points_m": rec.points_m, "t_s": rec.t_s},
            params={"format": "synthetic"},
            summary=tasks.recording_summary(
                {"points_m": rec.points_m, "t_s": rec.t_s}, "synthetic"
            ),
            source_name="demo: cylinder edge trace",
        )
        self._store_arrays(
            session.id,
            "scan",
            scan_id,
            {"points_m": scene.scan.points_m},
            params={"format": "synthetic"},
            summary={"n_points": len(scene.scan), "format": "synthetic"},
            source_name="demo: cylinder scan",
        )
        return self.store.update_session(
            session.id, recording_id=rec_id, scan_id=scan_id, T_base_tracker=DEMO_T_BASE_TRACKER
        )


def artifact_json(row: ArtifactRow) -> dict:
    return {
        "id": row.id,
        "session_id": row.session_id,
        "kind": row.kind,
        "created_at": iso(row.created_at),
        "inputs": row.inputs,
        "params": row.params,
        "summary": row.summary,
        "sha256": row.sha256,
        "size": row.size,
        "source_name": row.source_name,
    }


def session_json(row: SessionRow) -> dict:
    return {
        "id": row.id,
        "name": row.name,
        "created_at": iso(row.created_at),
        "recording_id": row.recording_id,
        "scan_id": row.scan_id,
        "T_base_tracker": row.T_base_tracker,
        "T_scan_tracker": row.T_scan_tracker,
        "tip_offset_m": row.tip_offset_m,
        "calibration_report": row.calibration_report,
    }


def capture_json(row) -> dict:
    return {
        "id": row.id,
        "session_id": row.session_id,
        "source": row.source,
        "state": row.state,
        "created_at": iso(row.created_at),
        "n_samples": row.n_samples,
        "recording_id": row.recording_id,
        "error": row.error,
    }
