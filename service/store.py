"""Persistence: sessions, artifacts, jobs and captures in a database, arrays in files.

SQLite through SQLAlchemy is the embedded default; a ``postgresql://`` URL works too. Arrays
are ``.npz`` files next to the database, written atomically (write, fsync, rename) with their
SHA-256 in the database and checked when read. Artifacts are immutable: a recording is never
changed, and every later stage (scan, reconstruction, trajectory, execution) is a new artifact
that names its inputs and parameters, so any session can be replayed and compared.

Only the service's main process writes the database; the worker processes read and write
files only.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import json
import os
import secrets
import shutil
import socket
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, TypedDict, TypeVar, Unpack, cast, overload

import numpy as np
from sqlalchemy import (
    JSON,
    BigInteger,
    DateTime,
    Float,
    ForeignKey,
    Integer,
    String,
    create_engine,
    event,
    select,
)
from sqlalchemy.engine import CursorResult, Engine, make_url
from sqlalchemy.engine.interfaces import DBAPIConnection
from sqlalchemy.orm import DeclarativeBase, Mapped, Session, mapped_column, sessionmaker
from sqlalchemy.pool import ConnectionPoolEntry

from drivers.files import atomic_path
from service.parsing import load_arrays, save_arrays

JOB_STATES = ("queued", "running", "succeeded", "failed", "cancelled")
FINISHED = ("succeeded", "failed", "cancelled")


def new_id(prefix: str) -> str:
    """A short random id with a prefix that says what it names (``ses_3f9a...``)."""
    return f"{prefix}_{secrets.token_hex(6)}"


def now() -> datetime:
    return datetime.now(UTC)


def _aware(moment: datetime) -> datetime:
    """A stored moment as an aware UTC datetime (SQLite returns naive ones, stored as UTC)."""
    return moment.replace(tzinfo=UTC) if moment.tzinfo is None else moment


def iso(moment: datetime | None) -> str | None:
    """ISO 8601 in UTC (SQLite returns naive datetimes: they were stored as UTC)."""
    if moment is None:
        return None
    if moment.tzinfo is None:
        moment = moment.replace(tzinfo=UTC)
    return moment.isoformat()


class Base(DeclarativeBase):
    type_annotation_map = {dict[str, Any]: JSON, list[Any]: JSON}  # noqa: RUF012 - SQLAlchemy's way


class SessionRow(Base):
    __tablename__ = "sessions"
    id: Mapped[str] = mapped_column(String(32), primary_key=True)
    name: Mapped[str] = mapped_column(String(200))
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True))
    deleted_at: Mapped[datetime | None] = mapped_column(DateTime(timezone=True), nullable=True)
    recording_id: Mapped[str | None] = mapped_column(String(32), nullable=True)
    scan_id: Mapped[str | None] = mapped_column(String(32), nullable=True)
    T_base_tracker: Mapped[list[Any] | None] = mapped_column(JSON, nullable=True)
    T_scan_tracker: Mapped[list[Any] | None] = mapped_column(JSON, nullable=True)
    tip_offset_m: Mapped[list[float] | None] = mapped_column(JSON, nullable=True)
    #: How the calibrations were obtained (residuals of the fits, dates).
    calibration_report: Mapped[dict[str, Any] | None] = mapped_column(JSON, nullable=True)


class ArtifactRow(Base):
    __tablename__ = "artifacts"
    id: Mapped[str] = mapped_column(String(32), primary_key=True)
    session_id: Mapped[str] = mapped_column(ForeignKey("sessions.id"), index=True)
    kind: Mapped[str] = mapped_column(String(20), index=True)
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True))
    inputs: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)
    params: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)
    summary: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)
    path: Mapped[str] = mapped_column(String(300))
    sha256: Mapped[str] = mapped_column(String(64))
    size: Mapped[int] = mapped_column(BigInteger)
    source_name: Mapped[str | None] = mapped_column(String(300), nullable=True)


class JobRow(Base):
    __tablename__ = "jobs"
    id: Mapped[str] = mapped_column(String(32), primary_key=True)
    session_id: Mapped[str] = mapped_column(ForeignKey("sessions.id"), index=True)
    kind: Mapped[str] = mapped_column(String(20))
    state: Mapped[str] = mapped_column(String(12), index=True)
    progress: Mapped[float] = mapped_column(Float, default=0.0)
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True))
    started_at: Mapped[datetime | None] = mapped_column(DateTime(timezone=True), nullable=True)
    finished_at: Mapped[datetime | None] = mapped_column(DateTime(timezone=True), nullable=True)
    params: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)
    result: Mapped[dict[str, Any] | None] = mapped_column(JSON, nullable=True)
    error: Mapped[dict[str, Any] | None] = mapped_column(JSON, nullable=True)
    #: The instance (``InstanceRow.id``) that runs it; None: made before instances were kept.
    owner: Mapped[str | None] = mapped_column(String(64), nullable=True, index=True)


class CaptureRow(Base):
    __tablename__ = "captures"
    id: Mapped[str] = mapped_column(String(32), primary_key=True)
    session_id: Mapped[str] = mapped_column(ForeignKey("sessions.id"), index=True)
    source: Mapped[dict[str, Any]] = mapped_column(JSON)
    state: Mapped[str] = mapped_column(String(12))
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True))
    n_samples: Mapped[int] = mapped_column(Integer, default=0)
    path: Mapped[str] = mapped_column(String(300))
    recording_id: Mapped[str | None] = mapped_column(String(32), nullable=True)
    error: Mapped[str | None] = mapped_column(String(500), nullable=True)
    owner: Mapped[str | None] = mapped_column(String(64), nullable=True)


class InstanceRow(Base):
    """A running service process (``teachpath serve``) on this database."""

    __tablename__ = "instances"
    id: Mapped[str] = mapped_column(String(64), primary_key=True)
    host: Mapped[str] = mapped_column(String(200))
    pid: Mapped[int] = mapped_column(Integer)
    started_at: Mapped[datetime] = mapped_column(DateTime(timezone=True))
    heartbeat_at: Mapped[datetime] = mapped_column(DateTime(timezone=True))


class CellRow(Base):
    """An arm's cell as edited in the pendant (``PUT /cell``), under the arm's name.

    ``keep_out_boxes`` and ``cell_planes`` None: the start-up settings apply (``DELETE /cell``).
    ``revision`` counts the changes, so that an edit made from an older view is refused.
    """

    __tablename__ = "cells"
    name: Mapped[str] = mapped_column(String(200), primary_key=True)
    keep_out_boxes: Mapped[list[Any] | None] = mapped_column(JSON, nullable=True)
    cell_planes: Mapped[list[Any] | None] = mapped_column(JSON, nullable=True)
    revision: Mapped[int] = mapped_column(Integer)
    updated_at: Mapped[datetime] = mapped_column(DateTime(timezone=True))


class StorageError(Exception):
    """A stored file is missing or does not match its checksum."""


#: The folders of a data folder; the service's own user alone may enter them or read a file.
FOLDERS = ("arrays", "uploads", "captures", "journals")
PRIVATE_DIR = 0o700
PRIVATE_FILE = 0o600


class CellChangedError(Exception):
    """A cell was edited from a view older than the stored cell (``revision``: the stored one)."""

    def __init__(self, revision: int) -> None:
        super().__init__(f"the cell is at revision {revision}")
        self.revision = revision


class SessionDeletedError(Exception):
    """Work finished for a session that was deleted meanwhile: nothing is added to it."""


_Row = TypeVar("_Row", bound=Base)


class ArtifactFields(TypedDict, total=False):
    """What :meth:`Store.add_artifact` takes besides the artifact's id, session, kind and file."""

    inputs: dict[str, Any] | None
    params: dict[str, Any] | None
    summary: dict[str, Any] | None
    source_name: str | None
    session_fields: Mapping[str, object] | None


class RowGoneError(LookupError):
    """A row to update is gone (deleted, with its session, since it was read)."""


def _row_to_update(db: Session, table: type[_Row], key: str, *, lock: bool = False) -> _Row:
    """The row of ``table`` with primary key ``key`` in ``db`` (locked for the update when
    ``lock``), or :class:`RowGoneError` naming it."""
    row = db.get(table, key, with_for_update=lock)
    if row is None:
        raise RowGoneError(f"{table.__tablename__} {key!r} no longer exists")
    return row


#: An instance refreshes its heartbeat this often (s) ...
HEARTBEAT_S = 2.0
#: ... and one whose heartbeat is older than this has stopped (its jobs are failed, its captures
#: ended). Generous: a process busy in a long GIL-holding call still beats within it.
STALE_S = 20.0


def file_digest(path: Path) -> tuple[str, int]:
    """A file's SHA-256 (hex) and size, read in blocks."""
    digest = hashlib.sha256()
    with Path(path).open("rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest(), Path(path).stat().st_size


def _process_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's process: alive
        return True
    return True


@functools.cache
def machine_identity() -> str:
    """This machine and process namespace: host name, boot id and pid namespace. Two instances
    with the same identity see each other's processes (a pid check means something); machines
    cloned from one image share a host name, not a boot id."""
    try:
        boot = Path("/proc/sys/kernel/random/boot_id").read_text().strip()
        namespace = os.stat("/proc/self/ns/pid").st_ino
    except OSError:  # not Linux: no shortcut (the heartbeat alone decides)
        return f"{socket.gethostname()[:60]} {secrets.token_hex(8)}"
    return f"{socket.gethostname()[:60]} {boot} {namespace}"


def database_url(url: str) -> str:
    """A SQLAlchemy URL with the driver teachpath ships: ``postgresql://`` means psycopg 3
    (SQLAlchemy's default for it is psycopg2, which is not installed)."""
    for plain in ("postgresql://", "postgres://"):
        if url.startswith(plain):
            return "postgresql+psycopg://" + url[len(plain) :]
    return url


class RecentFaults:
    """When each kind of storage fault (a full disk, a busy database) was last met by this
    store's requests and jobs, for ``/health`` to report for a while after.

    One per :class:`Store`, so that one service instance's faults are its own (a test's app or a
    second instance in the same process never sees another's).
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._last_seen_s: dict[str, float] = {}  # code -> time.monotonic() when last met

    def note(self, code: str) -> None:
        """Record that a request or a job met the storage fault ``code`` now."""
        with self._lock:
            self._last_seen_s[code] = time.monotonic()

    def within(self, window_s: float, now_s: float | None = None) -> list[str]:
        """The codes met within the last ``window_s`` seconds, sorted."""
        now_s = time.monotonic() if now_s is None else now_s
        with self._lock:
            return sorted(c for c, at in self._last_seen_s.items() if now_s - at <= window_s)


class Store:
    """The database and the array files of one data folder.

    Several service instances may share one (PostgreSQL) database and one data folder: each
    has an ``instance_id``, owns the jobs and captures it starts, and keeps a heartbeat
    (:meth:`heartbeat`); start-up recovery only touches what stopped instances left.

    Parameters
    ----------
    data_dir : Path
    url : str
        SQLAlchemy database URL (``postgresql://`` uses psycopg 3).
    instance_id : str, optional
        This process's id among the instances (default: host, process id and a random part).
    """

    def __init__(self, data_dir: Path, url: str, *, instance_id: str | None = None) -> None:
        self.data_dir = Path(data_dir)
        self.faults = RecentFaults()
        # Uploads, calibrations and the token are the site's: only the service's user reads them.
        for folder in (self.data_dir, *(self.data_dir / name for name in FOLDERS)):
            folder.mkdir(mode=PRIVATE_DIR, parents=True, exist_ok=True)
            os.chmod(folder, PRIVATE_DIR)
        url = database_url(url)
        sqlite = url.startswith("sqlite")
        database = make_url(url).database if sqlite else None
        if database not in (None, "", ":memory:"):
            # Made private before SQLite opens it: its -wal and -shm files take its mode.
            os.close(os.open(database, os.O_CREAT | os.O_WRONLY, PRIVATE_FILE))
            os.chmod(database, PRIVATE_FILE)
            for suffix in ("-wal", "-shm"):
                if os.path.exists(database + suffix):
                    os.chmod(database + suffix, PRIVATE_FILE)
        try:
            self.engine = create_engine(
                url,
                connect_args={"check_same_thread": False, "timeout": 30} if sqlite else {},
                pool_pre_ping=not sqlite,  # a restarted database server: reconnect, do not fail
            )
        except ImportError as error:  # the database's driver (psycopg: the postgres extra)
            from drivers.registry import missing_dependency

            raise missing_dependency(error, f"the database {make_url(url).drivername}") from None
        if sqlite:

            @event.listens_for(self.engine, "connect")
            def _pragmas(conn: DBAPIConnection, _record: ConnectionPoolEntry) -> None:
                # WAL: readers do not wait for the writer
                cursor = conn.cursor()
                cursor.execute("PRAGMA journal_mode=WAL")
                cursor.execute("PRAGMA synchronous=NORMAL")
                cursor.execute("PRAGMA foreign_keys=ON")
                cursor.close()

        migrate(self.engine, lock_path=None if database in (None, "", ":memory:") else database)
        self.db = sessionmaker(self.engine, expire_on_commit=False)
        self._calibration_lock = threading.Lock()
        self._cell_lock = threading.Lock()
        self.instance_id = instance_id or (
            f"{socket.gethostname()[:40]}:{os.getpid()}:{secrets.token_hex(3)}"
        )

    # -- instances -------------------------------------------------------------------------------

    def _db_now(self, db: Session) -> datetime:
        """The database's clock (PostgreSQL's ``now()``): instances on several hosts compare
        heartbeats on one clock, whatever their own clocks say. SQLite is one host's: its clock."""
        if self.engine.dialect.name == "postgresql":
            from sqlalchemy import func

            moment = db.scalar(select(func.now()))
            assert isinstance(moment, datetime)  # now() is never NULL
            return _aware(moment)
        return now()

    def heartbeat(self, instance_id: str | None = None) -> None:
        """Say this instance (or ``instance_id``, a stand-in of it) is alive; registers it on the
        first call."""
        instance_id = instance_id or self.instance_id
        with self.db.begin() as db:
            moment = self._db_now(db)
            row = db.get(InstanceRow, instance_id)
            if row is None:
                db.add(
                    InstanceRow(
                        id=instance_id,
                        host=machine_identity(),
                        pid=os.getpid(),
                        started_at=moment,
                        heartbeat_at=moment,
                    )
                )
            else:
                row.heartbeat_at = moment

    @contextlib.contextmanager
    def presence(self, what: str) -> Iterator[Callable[[], None]]:
        """Count as a live instance while a block runs (a bundle import from the command line
        writes files before it records them: a service starting meanwhile must not take them for
        a crash's leftovers). Yields a function that refreshes the heartbeat (call it now and
        then in long work)."""
        stand_in = f"{self.instance_id}:{what}:{secrets.token_hex(3)}"[:64]
        self.heartbeat(stand_in)
        try:
            yield lambda: self.heartbeat(stand_in)
        finally:
            self.leave(stand_in)

    def leave(self, instance_id: str | None = None) -> None:
        """This instance (or its stand-in) stops: its row goes (what it owns is recovered by the
        next start)."""
        with self.db.begin() as db:
            row = db.get(InstanceRow, instance_id or self.instance_id)
            if row is not None:
                db.delete(row)

    def live_instances(self, db: Session | None = None) -> set[str]:
        """Ids of the instances whose heartbeat is fresh on the database's clock (this one
        included once it beat), read in ``db`` if given (a transaction under way)."""
        if db is None:
            with self.db() as own:
                return self.live_instances(own)
        from datetime import timedelta

        horizon = self._db_now(db) - timedelta(seconds=STALE_S)
        here = machine_identity()
        rows = list(db.scalars(select(InstanceRow)))
        return {
            row.id
            for row in rows
            if _aware(row.heartbeat_at) >= horizon
            # In this very machine and process namespace (same boot, same pid namespace), a
            # process that is gone is known at once: a crash, then a restart within the stale
            # time, must not wait for the heartbeat to age. Anywhere else: the heartbeat alone.
            and (row.host != here or row.id == self.instance_id or _process_alive(row.pid))
        }

    def forget_stopped_instances(self) -> int:
        """Remove the rows of instances that stopped long ago (ten times the stale time)."""
        from datetime import timedelta

        with self.db.begin() as db:
            horizon = self._db_now(db) - timedelta(seconds=10 * STALE_S)
            rows = [r for r in db.scalars(select(InstanceRow)) if _aware(r.heartbeat_at) < horizon]
            for row in rows:
                db.delete(row)
            return len(rows)

    # -- files -----------------------------------------------------------------------------------

    def write_arrays(
        self, artifact_id: str, arrays: Mapping[str, np.ndarray]
    ) -> tuple[str, str, int]:
        """Store arrays as ``arrays/<id>.npz``. Returns (relative path, sha256, size)."""
        relative = f"arrays/{artifact_id}.npz"
        target = self.data_dir / relative
        save_arrays(target, arrays)
        return relative, *file_digest(target)

    def write_bytes(self, relative: str, content: bytes) -> tuple[str, int]:
        target = self.data_dir / relative
        target.parent.mkdir(mode=PRIVATE_DIR, parents=True, exist_ok=True)
        with atomic_path(target) as tmp:
            tmp.write_bytes(content)
            os.chmod(tmp, PRIVATE_FILE)
        return file_digest(target)

    def read_arrays(self, artifact: ArtifactRow) -> dict[str, np.ndarray]:
        """The arrays of an artifact, after checking the file against its checksum."""
        return load_arrays(self.path_of(artifact))

    def path_of(self, artifact: ArtifactRow) -> Path:
        path = self.data_dir / artifact.path
        if not path.is_file():
            raise StorageError(f"the file of {artifact.id} is missing")
        if file_digest(path)[0] != artifact.sha256:
            raise StorageError(f"the file of {artifact.id} does not match its checksum")
        return path

    def remove_unnamed_files(self) -> list[str]:
        """Remove files of ``arrays/`` and ``uploads/`` that no artifact names (called on start,
        when no job runs): the output of a job whose server died before it recorded it, or the
        temporary file of a write cut short. Returns what was removed (relative paths)."""
        with self.db() as db:
            named = set(db.scalars(select(ArtifactRow.id)))
        removed = []
        folders = (self.data_dir / "arrays", self.data_dir / "uploads")
        for entry in [path for folder in folders for path in folder.iterdir()]:
            # arrays/<id>.npz, arrays/<id>.png (a preview), uploads/<id>/<name>; temporary
            # files start with a dot.
            artifact_id = entry.name.split(".", 1)[0]
            if artifact_id in named and not entry.name.startswith("."):
                continue
            if entry.is_dir():
                shutil.rmtree(entry, ignore_errors=True)
            else:
                entry.unlink(missing_ok=True)
            removed.append(str(entry.relative_to(self.data_dir)))
        return removed

    # -- sessions --------------------------------------------------------------------------------

    def create_session(self, name: str) -> SessionRow:
        row = SessionRow(id=new_id("ses"), name=name, created_at=now())
        with self.db.begin() as db:
            db.add(row)
        return row

    def sessions(self, *, include_deleted: bool = False) -> list[SessionRow]:
        with self.db() as db:
            query = select(SessionRow).order_by(SessionRow.created_at)
            if not include_deleted:
                query = query.where(SessionRow.deleted_at.is_(None))
            return list(db.scalars(query))

    def session(self, session_id: str) -> SessionRow | None:
        with self.db() as db:
            row = db.get(SessionRow, session_id)
            return None if row is None or row.deleted_at is not None else row

    def update_session(self, session_id: str, **fields: object) -> SessionRow:
        with self.db.begin() as db:
            row = _row_to_update(db, SessionRow, session_id, lock=True)
            for key, value in fields.items():
                setattr(row, key, value)
            return row

    def record_calibration(
        self, session_id: str, name: str, entry: dict[str, Any], **fields: object
    ) -> SessionRow:
        """Set calibration fields and file ``entry`` under ``name`` in the session's calibration
        report, in one step (two calibrations landing together both stay in the report)."""
        # The row is locked (PostgreSQL: SELECT ... FOR UPDATE) so that two instances' updates
        # are applied one after the other; within this process the lock does the same on SQLite.
        with self._calibration_lock, self.db.begin() as db:
            row = _row_to_update(db, SessionRow, session_id, lock=True)
            row.calibration_report = {**(row.calibration_report or {}), name: entry}
            for key, value in fields.items():
                setattr(row, key, value)
            return row

    # -- cells -----------------------------------------------------------------------------------

    def cell(self, name: str) -> CellRow | None:
        """The cell stored under ``name`` (None: never edited, the start-up settings apply)."""
        with self.db() as db:
            return db.get(CellRow, name)

    def set_cell(
        self,
        name: str,
        *,
        boxes: list[list[float]] | None,
        planes: list[list[float]] | None,
        expected_revision: int,
    ) -> None:
        """Store the cell ``name`` (None, None: back to the start-up settings) if its revision
        is still ``expected_revision`` (0: never stored).

        Parameters
        ----------
        name : str
            The arm's name (``Settings.cell_key``).
        boxes, planes : list of list of float, or None
            As :func:`service.cell.check_shapes` returns them (each box and plane a list).
        expected_revision : int
            The revision the edit was made from.

        Raises
        ------
        CellChangedError
            Another edit came first: the caller's view of the cell is older than the stored one.
        """
        import sqlalchemy.exc
        from sqlalchemy import update

        values = {
            "keep_out_boxes": None if boxes is None else _jsonable(boxes),
            "cell_planes": None if planes is None else _jsonable(planes),
            "revision": expected_revision + 1,
            "updated_at": now(),
        }
        try:
            with self._cell_lock, self.db.begin() as db:
                if expected_revision == 0:  # the first edit: an insert, refused if one came first
                    db.add(CellRow(name=name, **values))
                    db.flush()
                    return
                # One statement that compares and sets: of two edits from the same revision,
                # on PostgreSQL or SQLite, in one process or two, exactly one matches.
                done = db.execute(
                    update(CellRow)
                    .where(CellRow.name == name, CellRow.revision == expected_revision)
                    .values(**values)
                )
                # An UPDATE's result is a CursorResult (Session.execute says Result).
                if cast("CursorResult[*tuple[Any, ...]]", done).rowcount == 1:
                    return
        except sqlalchemy.exc.IntegrityError:
            pass
        row = self.cell(name)
        raise CellChangedError(0 if row is None else row.revision)

    # -- artifacts -------------------------------------------------------------------------------

    def add_artifact(
        self,
        *,
        artifact_id: str,
        session_id: str,
        kind: str,
        path: str,
        sha256: str,
        size: int,
        inputs: dict[str, Any] | None = None,
        params: dict[str, Any] | None = None,
        summary: dict[str, Any] | None = None,
        source_name: str | None = None,
        session_fields: Mapping[str, object] | None = None,
    ) -> ArtifactRow:
        """Record an artifact whose file is written; ``session_fields`` (``recording_id``, ...)
        are set on its session in the same transaction.

        Raises
        ------
        SessionDeletedError
            The session is gone or deleted (then nothing is recorded).
        """
        row = ArtifactRow(
            id=artifact_id,
            session_id=session_id,
            kind=kind,
            created_at=now(),
            inputs=inputs or {},
            params=_jsonable(params or {}),
            summary=_jsonable(summary or {}),
            path=path,
            sha256=sha256,
            size=size,
            source_name=source_name,
        )
        with self.db.begin() as db:
            # In the transaction that adds the row: a delete that lands first wins. The session's
            # row is locked, so uploads to one session from several instances land one by one.
            session = db.get(SessionRow, session_id, with_for_update=True)
            if session is None or session.deleted_at is not None:
                raise SessionDeletedError(
                    f"session {session_id} was deleted; its new {kind} was discarded"
                )
            row.created_at = now()  # under the lock: the newest artifact is the one set last
            db.add(row)
            for key, value in (session_fields or {}).items():
                setattr(session, key, value)
        return row

    def add_upload_artifact(
        self,
        *,
        artifact_id: str,
        session_id: str,
        kind: str,
        arrays: Mapping[str, np.ndarray] | None,
        upload_path: str,
        content: bytes,
        session_fields: Mapping[str, object],
        inputs: dict[str, Any] | None = None,
        params: dict[str, Any] | None = None,
        summary: dict[str, Any] | None = None,
        source_name: str | None = None,
    ) -> ArtifactRow:
        """Record a parsed upload, all or nothing: its arrays (unless its parse wrote them at
        ``arrays/<id>.npz`` already) and its original bytes are written first, then the artifact
        and the session's update are committed in one transaction.

        If anything fails (a full disk, the database), nothing is recorded and the files written
        are removed, so a failed upload leaves no artifact behind.

        Parameters
        ----------
        artifact_id, session_id, kind : str
        arrays : dict of arrays, or None
            None: the parse wrote them at ``arrays/<id>.npz``.
        upload_path : str
            Where the bytes go, relative to the data folder (``uploads/<id>/<name>``).
        content : bytes
        session_fields : dict
            Fields of the session set in the same transaction (``recording_id``, ...).
        inputs, params, summary, source_name
            As for :meth:`add_artifact`.

        Raises
        ------
        SessionDeletedError
            The session was deleted while the upload was parsed (its files are removed).
        """
        written: list[Path] = []
        try:
            path = f"arrays/{artifact_id}.npz"
            written.append(self.data_dir / path)
            if arrays is None:
                sha, size = file_digest(self.data_dir / path)
            else:
                path, sha, size = self.write_arrays(artifact_id, arrays)
            written.append(self.data_dir / upload_path)
            self.write_bytes(upload_path, content)
            row = self.add_artifact(
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
                session_fields=session_fields,
            )
        except BaseException:
            for file in written:
                file.unlink(missing_ok=True)
            folder = (self.data_dir / upload_path).parent
            with contextlib.suppress(OSError):
                folder.rmdir()  # only if empty: it is this artifact's own folder
            raise
        return row

    def add_arrays_artifact(
        self,
        *,
        artifact_id: str,
        session_id: str,
        kind: str,
        arrays: Mapping[str, np.ndarray],
        **fields: Unpack[ArtifactFields],
    ) -> ArtifactRow:
        """Write ``arrays`` and record them as a new artifact (fields: inputs, params, summary,
        source_name)."""
        path, sha, size = self.write_arrays(artifact_id, arrays)
        try:
            return self.add_artifact(
                artifact_id=artifact_id,
                session_id=session_id,
                kind=kind,
                path=path,
                sha256=sha,
                size=size,
                **fields,
            )
        except BaseException:
            (self.data_dir / path).unlink(missing_ok=True)  # no file that no artifact names
            raise

    def add_file_artifact(
        self,
        *,
        artifact_id: str,
        session_id: str,
        kind: str,
        path: str,
        **fields: Unpack[ArtifactFields],
    ) -> ArtifactRow:
        """Record an artifact whose file a worker already wrote at ``path`` (relative)."""
        os.chmod(self.data_dir / path, PRIVATE_FILE)
        sha, size = file_digest(self.data_dir / path)
        return self.add_artifact(
            artifact_id=artifact_id,
            session_id=session_id,
            kind=kind,
            path=path,
            sha256=sha,
            size=size,
            **fields,
        )

    def artifact(
        self, artifact_id: str, *, kind: str | None = None, session_id: str | None = None
    ) -> ArtifactRow | None:
        with self.db() as db:
            row = db.get(ArtifactRow, artifact_id)
        if (
            row is None
            or (kind and row.kind != kind)
            or (session_id and row.session_id != session_id)
        ):
            return None
        return row

    def artifacts(self, session_id: str, kind: str | None = None) -> list[ArtifactRow]:
        """The session's artifacts of one kind (or of every kind), oldest first."""
        query = select(ArtifactRow).where(ArtifactRow.session_id == session_id)
        if kind is not None:
            query = query.where(ArtifactRow.kind == kind)
        with self.db() as db:
            return list(db.scalars(query.order_by(ArtifactRow.created_at)))

    # -- jobs ------------------------------------------------------------------------------------

    def create_job(self, session_id: str, kind: str, params: dict[str, Any]) -> JobRow:
        row = JobRow(
            id=new_id("job"),
            session_id=session_id,
            kind=kind,
            state="queued",
            progress=0.0,
            created_at=now(),
            params=_jsonable(params),
            owner=self.instance_id,
        )
        with self.db.begin() as db:
            db.add(row)
        return row

    def delete_job(self, job_id: str) -> None:
        """Remove a job row (for work that was never submitted)."""
        with self.db.begin() as db:
            row = db.get(JobRow, job_id)
            if row is not None:
                db.delete(row)

    def job(self, job_id: str) -> JobRow | None:
        with self.db() as db:
            return db.get(JobRow, job_id)

    def jobs(self, session_id: str | None = None) -> list[JobRow]:
        with self.db() as db:
            query = select(JobRow).order_by(JobRow.created_at)
            if session_id:
                query = query.where(JobRow.session_id == session_id)
            return list(db.scalars(query))

    def count_jobs(self, state: str) -> int:
        from sqlalchemy import func

        with self.db() as db:
            count = db.scalar(select(func.count()).select_from(JobRow).where(JobRow.state == state))
            return count or 0

    def update_job(self, job_id: str, **fields: object) -> JobRow:
        with self.db.begin() as db:
            row = _row_to_update(db, JobRow, job_id)
            for key, value in fields.items():
                setattr(row, key, _jsonable(value) if isinstance(value, dict) else value)
        return row

    def fail_interrupted_jobs(self, *, unowned: bool = True) -> int:
        """Mark failed the jobs that stopped instances left queued or running (called on start
        and with each heartbeat): those of instances whose heartbeat is stale, and (``unowned``,
        on start) those made before instances were kept. A live instance's jobs are never
        touched.

        The jobs are locked first and the instances read after, in one transaction: a job whose
        row is visible was created after its instance registered, so its instance is seen too.
        """
        with self.db.begin() as db:
            query = select(JobRow).where(JobRow.state.in_(("queued", "running")))
            candidates = list(db.scalars(query.with_for_update()))
            live = self.live_instances(db) | {self.instance_id}
            rows = [
                r
                for r in candidates
                if (r.owner is None and unowned) or (r.owner is not None and r.owner not in live)
            ]
            for row in rows:
                row.state = "failed"
                row.finished_at = now()
                row.error = {
                    "code": "interrupted",
                    "message": "the service stopped while this "
                    "job was pending or running; submit it again",
                    "detail": None,
                }
            return len(rows)

    def is_live(self, owner: str | None) -> bool:
        """Whether the instance ``owner`` runs (this one, or a fresh heartbeat)."""
        return owner is not None and (owner == self.instance_id or owner in self.live_instances())

    # -- captures --------------------------------------------------------------------------------

    def create_capture(self, session_id: str, source: dict[str, Any]) -> CaptureRow:
        capture_id = new_id("cap")
        row = CaptureRow(
            id=capture_id,
            session_id=session_id,
            source=_jsonable(source),
            state="running",
            created_at=now(),
            n_samples=0,
            path=f"captures/{capture_id}.csv",
            owner=self.instance_id,
        )
        with self.db.begin() as db:
            db.add(row)
        return row

    def capture(self, capture_id: str) -> CaptureRow | None:
        with self.db() as db:
            return db.get(CaptureRow, capture_id)

    def update_capture(self, capture_id: str, **fields: object) -> CaptureRow:
        with self.db.begin() as db:
            row = _row_to_update(db, CaptureRow, capture_id)
            for key, value in fields.items():
                setattr(row, key, value)
            return row

    def stop_interrupted_captures(self) -> list[CaptureRow]:
        """Captures stopped instances left running (their samples are on disk); a live
        instance's are not."""
        live = self.live_instances() | {self.instance_id}
        with self.db() as db:
            rows = db.scalars(select(CaptureRow).where(CaptureRow.state == "running"))
            return [row for row in rows if row.owner not in live]


@overload
def _jsonable(value: Mapping[str, Any]) -> dict[str, Any]: ...
@overload
def _jsonable(value: list[Any]) -> list[Any]: ...
def _jsonable(value: Mapping[str, Any] | list[Any]) -> dict[str, Any] | list[Any]:
    """Plain JSON types (numpy scalars and arrays become floats and lists)."""
    plain: dict[str, Any] | list[Any] = json.loads(json.dumps(value, default=_default))
    return plain


def _default(value: object) -> object:
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


#: Where the migrations are (Alembic's script location).
MIGRATIONS = Path(__file__).with_name("migrations")
#: PostgreSQL advisory lock key held while migrating (any fixed number; "teachpth" in ASCII).
_MIGRATION_LOCK = 0x7465616368707468 & 0x7FFFFFFFFFFFFFFF


def migrate(engine: Engine, *, lock_path: str | None = None) -> None:
    """Bring the database to the newest schema with Alembic (``service/migrations``).

    An empty database gets every table; one made by a release before Alembic (no
    ``alembic_version`` table) is brought to the first migration's schema by it, then up. Two
    instances starting together take turns: a PostgreSQL advisory lock, or a lock file beside a
    SQLite database.

    Parameters
    ----------
    engine : sqlalchemy.engine.Engine
    lock_path : str, optional
        The SQLite database file (its ``.migrate-lock`` sibling is locked).
    """
    import fcntl

    from alembic import command
    from alembic.config import Config

    config = Config()
    config.set_main_option("script_location", str(MIGRATIONS))
    lock = open(lock_path + ".migrate-lock", "a") if lock_path else None  # noqa: SIM115
    try:
        if lock is not None:
            os.chmod(lock.name, PRIVATE_FILE)
            fcntl.flock(lock, fcntl.LOCK_EX)
        with engine.begin() as connection:
            if connection.dialect.name == "postgresql":
                connection.exec_driver_sql(f"SELECT pg_advisory_xact_lock({_MIGRATION_LOCK})")
            config.attributes["connection"] = connection
            command.upgrade(config, "head")
    finally:
        if lock is not None:
            lock.close()


def schema_revision(engine: Engine) -> str | None:
    """The Alembic revision the database is at (None: not under Alembic)."""
    from alembic.runtime.migration import MigrationContext

    with engine.connect() as connection:
        return MigrationContext.configure(connection).get_current_revision()
