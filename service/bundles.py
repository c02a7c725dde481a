"""Session bundles: one zip per session that another data folder (or another site) can import.

A bundle holds ``manifest.json`` and, at their paths in the data folder, every file of every
artifact of the session (the arrays, the raw upload as it came, a preview picture). The manifest
says which teachpath and which bundle schema wrote it, the session with its calibrations, and
each artifact with its kind, inputs, parameters, summary and the SHA-256 and size of each of its
files. Jobs and captures are not in it: they are the work of one service, not the session's.

Export is deterministic: the manifest has sorted keys and the zip entries fixed dates and order,
so exporting an imported session gives the same bytes. Import checks everything before it changes
anything: the zip and the manifest against hostile input (sizes that lie, too many entries, paths
that climb out, deep nesting), the schema version (a newer one is refused: upgrade teachpath), ids
and file names against the patterns this version writes, and every file against its checksum as
it is copied out. Files are copied under temporary names, then renamed into place and recorded in
one transaction; on any failure nothing stays behind. Importing a bundle of a session that is
already here with the same content changes nothing (idempotent); a different session with the
same id is refused.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import math
import os
import re
import secrets
import threading
import zipfile
import zlib
from collections.abc import Callable
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any, BinaryIO, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, ValidationInfo, field_validator
from sqlalchemy import select
from sqlalchemy.exc import IntegrityError

from service.artifacts import ID_PREFIX, KindName, check_stored
from service.parsing import Arrays, load_arrays
from service.store import FOLDERS, PRIVATE_FILE, ArtifactRow, SessionRow, Store, file_digest

if TYPE_CHECKING:
    from service.settings import Settings

#: What the manifest's ``format`` says.
BUNDLE_FORMAT = "teachpath-session-bundle"
#: The bundle layout this version writes and the newest it reads. Raise it when the manifest or
#: the files change in a way an older teachpath could not read.
BUNDLE_SCHEMA = 1
MANIFEST_NAME = "manifest.json"
#: Bounds on what an import reads before it trusts the bundle.
MAX_MANIFEST_BYTES = 16 * 1024 * 1024
MAX_ENTRIES = 20_000
#: Deepest nesting of the manifest (summaries nest a few levels; a bundle is not a parser test).
MAX_DEPTH = 32
#: Zip entry dates: fixed, so that the same session exports to the same bytes.
ZIP_DATE = (1980, 1, 1, 0, 0, 0)
_CHUNK = 1 << 20

_HEX = r"[0-9a-f]{12}"
SESSION_ID = re.compile(rf"ses_{_HEX}")
#: The files of an artifact, relative to the data folder, as this version names them (besides
#: its uploads folder). A real-arm journal is not one: it is the execution's record until the
#: execution artifact exists, and removed at the next start after that.
_FILE_PATTERNS = ("arrays/{id}.npz", "arrays/{id}.png")
#: An upload's kept name (``service.uploads.storage_name``): never a dot-file, which export skips.
_UPLOAD_NAME = re.compile(r"[A-Za-z0-9_-][A-Za-z0-9._-]{0,199}")


#: Reads an artifact's raw upload again as an upload is read: (kind, params, bytes, file name)
#: -> its arrays (see :func:`service.inputs.reread_upload`); raises what the reader says.
Reread = Callable[[str, dict[str, Any], bytes, str], Arrays]
#: The kinds whose artifacts keep the file they were read from (and only one).
UPLOAD_KINDS = ("recording", "touches", "scan")


class BundleError(ValueError):
    """The bundle cannot be imported (or the session exported): what is wrong and what to do.
    Nothing was changed."""


class BundleConflictError(BundleError):
    """The bundle's session (or one of its artifacts) exists here with other content."""


def teachpath_version() -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("teachpath")
    except PackageNotFoundError:  # a checkout run without installing it
        return "unknown"


# -- the manifest ----------------------------------------------------------------------------------


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class FileEntry(_Strict):
    """One file of an artifact."""

    path: str = Field(max_length=300)
    sha256: str = Field(pattern=r"^[0-9a-f]{64}$")
    size: int = Field(ge=0, le=1 << 40)


class ArtifactEntry(_Strict):
    id: str = Field(max_length=32)
    kind: KindName
    created_at: datetime
    inputs: dict[str, Any]
    params: dict[str, Any]
    summary: dict[str, Any]
    source_name: str | None = Field(None, max_length=300)
    #: The artifact's own file (the arrays), the one its row names and checks on every read.
    data: FileEntry
    #: The others: the raw upload, a preview, a journal.
    files: list[FileEntry] = Field(max_length=100)

    @field_validator("id")
    @classmethod
    def _id_pattern(cls, value: str) -> str:
        if not re.fullmatch(rf"[a-z]{{3}}_{_HEX}", value):
            raise ValueError(f"{value!r} is not an artifact id (like rcn_0123456789ab)")
        return value


class SessionEntry(_Strict):
    id: str = Field(max_length=32)
    name: str = Field(max_length=200)
    created_at: datetime
    recording_id: str | None = Field(None, max_length=32)
    scan_id: str | None = Field(None, max_length=32)
    T_base_tracker: list[list[float]] | None = None
    T_scan_tracker: list[list[float]] | None = None
    tip_offset_m: list[float] | None = Field(None, min_length=3, max_length=3)
    calibration_report: dict[str, Any] | None = None

    @field_validator("T_base_tracker", "T_scan_tracker")
    @classmethod
    def _rigid(
        cls, value: list[list[float]] | None, info: ValidationInfo
    ) -> list[list[float]] | None:
        if value is not None:
            from recon.transforms import check_rigid

            # A field validator always has its field's name (None is for model validators).
            name = info.field_name or "transform"
            check_rigid(value, name=name)  # raises ValueError: not a rigid 4x4
        return value

    @field_validator("id")
    @classmethod
    def _id_pattern(cls, value: str) -> str:
        if not SESSION_ID.fullmatch(value):
            raise ValueError(f"{value!r} is not a session id (like ses_0123456789ab)")
        return value


class Manifest(_Strict):
    format: Literal["teachpath-session-bundle"]
    schema_version: int = Field(ge=1)
    teachpath_version: str = Field(max_length=64)
    session: SessionEntry
    artifacts: list[ArtifactEntry] = Field(max_length=MAX_ENTRIES)

    def content(self) -> dict[str, Any]:
        """What the bundle holds, without who wrote it (compared on a repeated import)."""
        return self.model_dump(mode="json", exclude={"teachpath_version"})


def _utc(moment: datetime) -> datetime:
    return moment.replace(tzinfo=UTC) if moment.tzinfo is None else moment.astimezone(UTC)


# -- export ----------------------------------------------------------------------------------------


def artifact_files(store: Store, artifact: ArtifactRow) -> list[str]:
    """Every file of an artifact besides its arrays, relative to the data folder, sorted."""
    found = []
    for pattern in _FILE_PATTERNS:
        relative = pattern.format(id=artifact.id)
        if relative != artifact.path and (store.data_dir / relative).is_file():
            found.append(relative)
    uploads = store.data_dir / "uploads" / artifact.id
    if uploads.is_dir():
        found += [
            f"uploads/{artifact.id}/{entry.name}"
            for entry in uploads.iterdir()
            if entry.is_file() and not entry.name.startswith(".")
        ]
    return sorted(found)


def _file_entry(store: Store, relative: str) -> FileEntry:
    sha256, size = file_digest(store.data_dir / relative)
    return FileEntry(path=relative, sha256=sha256, size=size)


def build_manifest(store: Store, session_id: str) -> Manifest:
    """The manifest of a stored session (its files read and checksummed now).

    Raises
    ------
    BundleError
        No such session, or an artifact's arrays no longer match the checksum stored with them.
    """
    session = store.session(session_id)
    if session is None:
        raise BundleError(f"there is no session {session_id!r} in {store.data_dir}")
    artifacts = sorted(store.artifacts(session_id), key=lambda row: (_utc(row.created_at), row.id))
    entries = []
    for row in artifacts:
        data = _file_entry(store, row.path)
        if data.sha256 != row.sha256:
            raise BundleError(
                f"the arrays of {row.id} ({row.path}) no longer match their checksum: the data "
                "folder is damaged; restore it from a backup before exporting this session"
            )
        entries.append(
            ArtifactEntry(
                id=row.id,
                kind=row.kind,
                created_at=_utc(row.created_at),
                inputs=row.inputs or {},
                params=row.params or {},
                summary=row.summary or {},
                source_name=row.source_name,
                data=data,
                files=[_file_entry(store, path) for path in artifact_files(store, row)],
            )
        )
    return Manifest(
        format=BUNDLE_FORMAT,
        schema_version=BUNDLE_SCHEMA,
        teachpath_version=teachpath_version(),
        session=SessionEntry(
            **{name: getattr(session, name) for name in SessionEntry.model_fields}
            | {"created_at": _utc(session.created_at)}
        ),
        artifacts=entries,
    )


def manifest_bytes(manifest: Manifest) -> bytes:
    return (json.dumps(manifest.model_dump(mode="json"), sort_keys=True, indent=1) + "\n").encode()


def export_bundle(store: Store, session_id: str, out: Path | BinaryIO | IO[bytes]) -> Manifest:
    """Write a session's bundle to ``out`` (a path, written atomically, or an open binary file).

    Returns
    -------
    Manifest
        What the bundle holds.
    """
    manifest = build_manifest(store, session_id)
    if isinstance(out, (str, Path)):
        from drivers.files import atomic_path

        with atomic_path(Path(out)) as tmp, tmp.open("wb") as handle:
            _write_zip(store, manifest, handle)
    else:
        _write_zip(store, manifest, out)
    return manifest


def _write_zip(store: Store, manifest: Manifest, handle: IO[bytes]) -> None:
    with zipfile.ZipFile(handle, "w") as bundle:
        _add(bundle, MANIFEST_NAME, io.BytesIO(manifest_bytes(manifest)))
        for artifact in manifest.artifacts:
            for entry in [artifact.data, *artifact.files]:
                with (store.data_dir / entry.path).open("rb") as source:
                    _add(bundle, entry.path, source)


def _add(bundle: zipfile.ZipFile, name: str, source: BinaryIO) -> None:
    info = zipfile.ZipInfo(name, date_time=ZIP_DATE)
    info.external_attr = PRIVATE_FILE << 16
    # Fast deflate: float arrays hardly compress, text does, and a bundle is written often.
    info.compress_type = zipfile.ZIP_DEFLATED
    with bundle.open(info, "w", force_zip64=True) as target:
        for block in iter(lambda: source.read(_CHUNK), b""):
            target.write(block)


# -- reading in place ----------------------------------------------------------------------------


class BundleReader:
    """A bundle read where it lies (for replay): the manifest and layout checked on opening,
    each file checked against its checksum when it is read.

    Parameters
    ----------
    path : path
        The bundle.

    Raises
    ------
    BundleError
        As :func:`import_bundle` would for the zip, the manifest and the layout.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        try:
            self._zip = zipfile.ZipFile(self.path)
        except (zipfile.BadZipFile, zipfile.LargeZipFile, OSError, EOFError, ValueError) as exc:
            raise BundleError(
                f"{self.path.name} is not a readable zip ({exc}): export it again"
            ) from None
        try:
            self.manifest = _read_manifest(self._zip)
            _check_layout(self._zip, self.manifest, max_bytes=1 << 40)
        except BaseException:
            self._zip.close()
            raise
        self._by_id = {artifact.id: artifact for artifact in self.manifest.artifacts}

    def __enter__(self) -> BundleReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self._zip.close()

    def artifacts(self, kind: str) -> list[ArtifactEntry]:
        """The artifacts of one kind, oldest first."""
        return [a for a in self.manifest.artifacts if a.kind == kind]

    def artifact(self, artifact_id: str) -> ArtifactEntry:
        try:
            return self._by_id[artifact_id]
        except KeyError:
            raise BundleError(f"{self.path.name} has no artifact {artifact_id}") from None

    def arrays(self, artifact_id: str) -> Arrays:
        """An artifact's arrays, after checking their file against the manifest."""
        entry = self.artifact(artifact_id).data
        try:
            with self._zip.open(entry.path) as handle:
                content = handle.read(entry.size + 1)
        except (zipfile.BadZipFile, EOFError, zlib.error) as exc:
            raise BundleError(f"{self.path.name}: {entry.path} is damaged ({exc})") from None
        if len(content) != entry.size or hashlib.sha256(content).hexdigest() != entry.sha256:
            raise BundleError(f"{self.path.name}: {entry.path} does not match its checksum")
        return load_arrays(io.BytesIO(content))


# -- import ----------------------------------------------------------------------------------------


@dataclass(frozen=True)
class ImportResult:
    session_id: str
    #: False when the same session was here already (nothing was changed).
    created: bool
    n_artifacts: int
    n_files: int
    n_bytes: int


#: A bundle's member may unpack to at most this many times its compressed size (beyond a small
#: floor): arrays and uploads compress 1-10x; a bomb (2 GB of zeros in 2 MB) far more.
MAX_COMPRESSION_RATIO = 100
#: Members this small are not held to the ratio (a short CSV of repeated digits compresses well).
RATIO_FLOOR_BYTES = 1 << 20


def import_bundle(
    store: Store,
    source: Path | bytes | BinaryIO,
    *,
    max_bytes: int = 8 << 30,
    max_file_bytes: int | None = None,
    reread: Reread | None = None,
) -> ImportResult:
    """Import a session bundle into a data folder: all of it or nothing.

    Parameters
    ----------
    store : Store
    source : path, bytes or binary file
    max_bytes : int
        The largest total size of the files a bundle may unpack to.
    max_file_bytes : int, optional
        The largest size of any one file in it (the service passes its upload limit: an array or
        a raw upload that came in a bundle is held to the limit of one that is uploaded).
    reread : callable, optional
        Reads each raw upload again, as an upload of it would be read (the service passes its
        readers and limits); the arrays it gives must be the bundle's own, bit for bit. Without
        it, raw uploads are only checked against their checksums.

    Raises
    ------
    BundleError
        Not a bundle, damaged, tampered with, written by a newer teachpath, or hostile (what is
        wrong is said); nothing was changed.
    BundleConflictError
        The session or one of its artifacts exists here with other content.
    """
    opened = source if not isinstance(source, bytes) else io.BytesIO(source)
    try:
        bundle = zipfile.ZipFile(opened)
    except (zipfile.BadZipFile, zipfile.LargeZipFile, OSError, EOFError, ValueError) as exc:
        raise BundleError(
            f"not a readable zip ({exc}): the bundle is truncated or not a teachpath bundle; "
            "export it again"
        ) from None
    with bundle:
        manifest = _read_manifest(bundle)
        files = _check_layout(bundle, manifest, max_bytes, max_file_bytes)
        with _IMPORTING, store.presence("import") as still_here:
            existing = _existing(store, manifest)
            if existing is not None:
                return existing
            written = _unpack(store, bundle, files, manifest, still_here, reread)
            try:
                _record(store, manifest)
            except IntegrityError:
                # Another process recorded the same ids meanwhile. The files this import put in
                # place go (it created them); files it found in place were another's.
                _undo(store, manifest, written)
                existing = _existing(store, manifest)
                if existing is not None:
                    return existing
                raise BundleConflictError(
                    f"session {manifest.session.id} or one of its artifacts was imported by "
                    "another process meanwhile, with other content"
                ) from None
            except BaseException:
                _undo(store, manifest, written)
                raise
    return ImportResult(
        session_id=manifest.session.id,
        created=True,
        n_artifacts=len(manifest.artifacts),
        n_files=len(files),
        n_bytes=sum(entry.size for entry in files),
    )


#: A bundle may unpack to this many uploads' worth of files in all (each file at most one
#: upload's worth): a 2.5 MB bundle unpacked to 2 GB under the old 8 GiB bound.
BUNDLE_FILES = 8


def import_under(store: Store, source: Path | bytes | BinaryIO, settings: Settings) -> ImportResult:
    """Import a bundle as this server takes one (the service and the CLI alike): each file held
    to the upload limit (``settings.max_upload_mb``), the whole to :data:`BUNDLE_FILES` times
    that, and each raw upload read again by the readers and limits of an upload.

    Parameters
    ----------
    store : Store
    source : path, bytes or binary file
    settings : service.settings.Settings

    Raises
    ------
    BundleError, BundleConflictError
        See :func:`import_bundle`.
    """
    from functools import partial

    from service.inputs import reread_upload

    limit = int(settings.max_upload_mb * 1024 * 1024)
    return import_bundle(
        store,
        source,
        max_bytes=BUNDLE_FILES * limit,
        max_file_bytes=limit,
        reread=partial(reread_upload, settings),
    )


#: One import at a time in this process (a second import of the same bundle waits, then finds
#: the session there); other processes are kept apart by the database's keys.
_IMPORTING = threading.Lock()


def _undo(store: Store, manifest: Manifest, written: list[Path]) -> None:
    """Remove the files this import created, except those an artifact recorded meanwhile names
    (another process's import of the same ids, with the same bytes, committed first)."""
    ids = [artifact.id for artifact in manifest.artifacts]
    with store.db() as db:
        recorded = set(db.scalars(select(ArtifactRow.id).where(ArtifactRow.id.in_(ids))))
    for path in written:
        owner = path.parent.name if path.parent.parent.name == "uploads" else path.stem
        if owner not in recorded:
            path.unlink(missing_ok=True)
    for artifact in manifest.artifacts:
        with contextlib.suppress(OSError):
            (store.data_dir / "uploads" / artifact.id).rmdir()


def _read_manifest(bundle: zipfile.ZipFile) -> Manifest:
    infos = bundle.infolist()
    if len(infos) > MAX_ENTRIES + 1:
        raise BundleError(f"the bundle has {len(infos)} entries, more than {MAX_ENTRIES + 1}")
    for info in infos:  # before anything is read: zipfile raises odd errors for these
        if info.flag_bits & 0x1:
            raise BundleError(f"{info.filename[:100]!r} is encrypted: teachpath never writes that")
        if info.compress_type not in (zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED):
            raise BundleError(
                f"{info.filename[:100]!r} is compressed with method {info.compress_type}: "
                "teachpath writes stored or deflated entries only"
            )
    try:
        info = bundle.getinfo(MANIFEST_NAME)
    except KeyError:
        raise BundleError(
            f"the zip has no {MANIFEST_NAME}: it is not a teachpath session bundle (export one "
            "with `teachpath bundle export` or GET /sessions/{id}/bundle)"
        ) from None
    if info.file_size > MAX_MANIFEST_BYTES:
        raise BundleError(f"{MANIFEST_NAME} declares {info.file_size} bytes, more than allowed")
    try:
        with bundle.open(info) as handle:
            raw = handle.read(MAX_MANIFEST_BYTES + 1)
    except (zipfile.BadZipFile, OSError, EOFError, ValueError, zlib.error) as exc:
        raise BundleError(
            f"{MANIFEST_NAME} cannot be read ({exc}): export the bundle again"
        ) from None
    if len(raw) > MAX_MANIFEST_BYTES:
        raise BundleError(f"{MANIFEST_NAME} is larger than {MAX_MANIFEST_BYTES} bytes")
    try:
        document = json.loads(raw, parse_constant=_not_finite, parse_float=_finite_float)
    except (ValueError, RecursionError) as exc:
        raise BundleError(f"{MANIFEST_NAME} is not valid JSON ({str(exc)[:200]})") from None
    if not isinstance(document, dict):
        raise BundleError(f"{MANIFEST_NAME} must hold a JSON object")
    if _depth(document) > MAX_DEPTH:
        raise BundleError(
            f"{MANIFEST_NAME} is nested more than {MAX_DEPTH} levels deep: not a manifest this "
            "teachpath writes"
        )
    version = document.get("schema_version")
    if isinstance(version, int) and version > BUNDLE_SCHEMA:
        writer = str(document.get("teachpath_version"))[:40]
        raise BundleError(
            f"the bundle was written by a newer teachpath ({writer}, bundle schema {version}; "
            f"this one reads up to {BUNDLE_SCHEMA}): upgrade teachpath to import it"
        )
    try:
        return Manifest.model_validate(document)
    except (ValidationError, RecursionError) as exc:
        raise BundleError(f"{MANIFEST_NAME} is not a valid manifest: {_first_error(exc)}") from None


def _depth(document: object) -> int:
    """How deeply lists and objects nest in a parsed JSON document (without recursion)."""
    deepest, stack = 0, [(document, 1)]
    while stack:
        value, level = stack.pop()
        if isinstance(value, dict | list):
            deepest = max(deepest, level)
            children = value.values() if isinstance(value, dict) else value
            stack.extend((child, level + 1) for child in children)
    return deepest


def _not_finite(name: str) -> float:
    raise ValueError(f"{name} is not a number JSON allows")


def _finite_float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise ValueError(f"{text[:40]} is too large a number")
    return value


def _first_error(exc: Exception) -> str:
    if isinstance(exc, ValidationError) and exc.errors():
        error = exc.errors()[0]
        where = ".".join(str(part) for part in error["loc"])
        return f"{where}: {error['msg']}"[:300]
    return "nested too deeply"


def _check_layout(  # noqa: C901
    bundle: zipfile.ZipFile, manifest: Manifest, max_bytes: int, max_file_bytes: int | None = None
) -> list[FileEntry]:
    """The files to unpack, after checking that ids, names and sizes are what this version
    writes and that the zip holds exactly them."""
    session = manifest.session
    ids = [artifact.id for artifact in manifest.artifacts]
    if len(set(ids)) != len(ids):
        raise BundleError("the manifest lists an artifact twice")
    for field in ("recording_id", "scan_id"):
        named = getattr(session, field)
        if named is not None and named not in ids:
            raise BundleError(f"the session's {field} {named!r} is not among its artifacts")
    files: list[FileEntry] = []
    for artifact in manifest.artifacts:
        if not artifact.id.startswith(ID_PREFIX[artifact.kind] + "_"):
            raise BundleError(f"{artifact.id} is not the id of a {artifact.kind}")
        if artifact.data.path != f"arrays/{artifact.id}.npz":
            raise BundleError(f"{artifact.id}'s arrays must be arrays/{artifact.id}.npz")
        allowed = {pattern.format(id=artifact.id) for pattern in _FILE_PATTERNS}
        for entry in artifact.files:
            upload = entry.path.split("/")
            if entry.path not in allowed and not (
                len(upload) == 3
                and upload[:2] == ["uploads", artifact.id]
                and _UPLOAD_NAME.fullmatch(upload[2])
            ):
                raise BundleError(f"{entry.path!r} is not a file teachpath keeps for {artifact.id}")
        n_uploads = sum(entry.path.startswith("uploads/") for entry in artifact.files)
        if n_uploads > (1 if artifact.kind in UPLOAD_KINDS else 0):
            raise BundleError(
                f"{artifact.id} ({artifact.kind}) lists {n_uploads} uploaded files: a "
                f"{artifact.kind} keeps {'one' if artifact.kind in UPLOAD_KINDS else 'none'}"
            )
        files += [artifact.data, *artifact.files]
    paths = [entry.path for entry in files]
    if len(set(paths)) != len(paths):
        raise BundleError("the manifest lists a file twice")
    names = [info.filename for info in bundle.infolist()]
    if len(set(names)) != len(names):
        raise BundleError("the zip holds an entry twice")
    extra = set(names) - set(paths) - {MANIFEST_NAME}
    missing = set(paths) - set(names)
    if extra or missing:
        what = (
            f"{len(missing)} listed files are missing (first: {sorted(missing)[0]})"
            if missing
            else f"it holds {len(extra)} files the manifest does not list (first: "
            f"{sorted(extra)[0][:100]!r})"
        )
        raise BundleError(f"the bundle does not match its manifest: {what}; export it again")
    total = 0
    for entry in files:
        info = bundle.getinfo(entry.path)
        declared = info.file_size
        if declared != entry.size:
            raise BundleError(
                f"{entry.path}: the zip says {declared} bytes, the manifest {entry.size}: the "
                "bundle was altered; export it again"
            )
        if max_file_bytes is not None and declared > max_file_bytes:
            raise BundleError(
                f"{entry.path} unpacks to {declared} bytes, more than the {max_file_bytes} an "
                "upload may have here (TEACHPATH_MAX_UPLOAD_MB)"
            )
        if declared > RATIO_FLOOR_BYTES and declared > MAX_COMPRESSION_RATIO * max(
            info.compress_size, 1
        ):
            raise BundleError(
                f"{entry.path} unpacks to {declared} bytes from {info.compress_size}: more than "
                f"{MAX_COMPRESSION_RATIO} times, no file teachpath writes compresses so well"
            )
        total += entry.size
    if total > max_bytes:
        raise BundleError(
            f"the bundle unpacks to {total} bytes, more than the {max_bytes} allowed here"
        )
    return files


def _existing(store: Store, manifest: Manifest) -> ImportResult | None:
    """The result of importing a session that is already here with the same content; None if
    it is not here. Raises BundleConflictError if it (or an artifact id) is, with other content."""
    session_id = manifest.session.id
    with store.db() as db:
        row = db.get(SessionRow, session_id)
        ids = [artifact.id for artifact in manifest.artifacts]
        taken = list(db.scalars(select(ArtifactRow).where(ArtifactRow.id.in_(ids)))) if ids else []
    if row is None:
        if taken:
            raise BundleConflictError(
                f"artifact {taken[0].id} of the bundle already belongs to session "
                f"{taken[0].session_id} here; the bundle cannot be imported into this data folder"
            )
        return None
    if row.deleted_at is not None:
        raise BundleConflictError(
            f"session {session_id} was deleted in this data folder (its data is kept on disk); "
            "import the bundle into another data folder"
        )
    try:
        here = build_manifest(store, session_id)
    except BundleError as exc:
        raise BundleConflictError(f"session {session_id} is here already, but {exc}") from None
    if here.content() != manifest.content():
        n_here, n_bundle = len(here.artifacts), len(manifest.artifacts)
        raise BundleConflictError(
            f"session {session_id} is here already with other content ({n_here} artifacts here, "
            f"{n_bundle} in the bundle): delete it here first, or import into another data folder"
        )
    return ImportResult(session_id, False, len(manifest.artifacts), 0, 0)


def _unpack(
    store: Store,
    bundle: zipfile.ZipFile,
    files: list[FileEntry],
    manifest: Manifest,
    still_here: Callable[[], None] = lambda: None,
    reread: Reread | None = None,
) -> list[Path]:
    """Copy the files out under temporary names, checking each against its size and checksum
    and each artifact's arrays and summary against its kind, then rename them into place.
    Returns the final paths (for undoing)."""
    staged: list[tuple[Path, Path]] = []
    try:
        for entry in files:
            final = store.data_dir / entry.path
            if final.parent.name not in FOLDERS:
                final.parent.mkdir(mode=0o700, exist_ok=True)
            tmp = final.with_name(f".{final.name}.import-{secrets.token_hex(4)}")
            staged.append((tmp, final))
            digest, size = hashlib.sha256(), 0
            with bundle.open(entry.path) as source, tmp.open("wb") as target:
                os.chmod(tmp, PRIVATE_FILE)
                while block := source.read(_CHUNK):
                    size += len(block)
                    if size > entry.size:
                        break
                    digest.update(block)
                    target.write(block)
                target.flush()
                os.fsync(target.fileno())
            still_here()
            if size != entry.size or digest.hexdigest() != entry.sha256:
                raise BundleError(
                    f"{entry.path} does not match its checksum in the manifest: the bundle was "
                    "altered or damaged; export it again"
                )
    except (zipfile.BadZipFile, EOFError, zlib.error) as exc:
        _remove(staged)
        raise BundleError(f"the bundle is damaged ({exc}); export it again") from None
    except BaseException:
        _remove(staged)
        raise
    try:
        _check_contents(staged, files, manifest, reread, still_here)
    except BaseException:
        _remove(staged)
        raise
    return _place(staged, files)


def _place(staged: list[tuple[Path, Path]], files: list[FileEntry]) -> list[Path]:
    """Link each checked file to its final name, never over an existing file: one found there
    with the same bytes is left as it is (another import of the same session put it there),
    one with other bytes is a conflict. Returns the files this import created (for undoing)."""
    created: list[Path] = []
    try:
        for (tmp, final), entry in zip(staged, files, strict=True):
            try:
                os.link(tmp, final)
                created.append(final)
            except FileExistsError:
                if file_digest(final)[0] != entry.sha256:
                    raise BundleConflictError(
                        f"{entry.path} exists in this data folder with other content: another "
                        "import of different data with the same ids; nothing was imported"
                    ) from None
    except BaseException:
        for path in created:
            path.unlink(missing_ok=True)
        raise
    finally:
        _remove(staged)
    return created


def _check_contents(
    staged: list[tuple[Path, Path]],
    files: list[FileEntry],
    manifest: Manifest,
    reread: Reread | None = None,
    still_here: Callable[[], None] = lambda: None,
) -> None:
    """Each artifact's arrays and summary as its kind has them, and its raw upload read again
    into those very arrays: a bundle whose checksums were recomputed after an edit must not
    store what the service cannot read back, nor a raw file that is not what the arrays came
    from."""

    where = {entry.path: tmp for (tmp, _), entry in zip(staged, files, strict=True)}
    for artifact in manifest.artifacts:
        path = where[artifact.data.path]
        try:
            # np.savez stores its members uncompressed: a compressed member could unpack to
            # far more memory than the file's size (a bomb inside the bundle).
            _check_npz(path)
            arrays = load_arrays(path)
            check_stored(artifact.kind, arrays, artifact.summary)
        except (ValueError, KeyError, OSError, EOFError, zipfile.BadZipFile, MemoryError) as exc:
            raise BundleError(
                f"{artifact.id} ({artifact.kind}) does not hold what a {artifact.kind} holds: "
                f"{_first_error(exc) if isinstance(exc, ValidationError) else str(exc)[:200]}"
            ) from None
        uploads = [entry for entry in artifact.files if entry.path.startswith("uploads/")]
        if uploads and reread is not None:
            _check_upload(artifact, uploads[0], where[uploads[0].path], arrays, reread, manifest)
            still_here()


def _check_upload(
    artifact: ArtifactEntry,
    upload: FileEntry,
    raw_path: Path,
    arrays: Arrays,
    reread: Reread,
    manifest: Manifest,
) -> None:
    """The raw upload read again as an upload (same readers, options and limits) gives the
    artifact's arrays, bit for bit.

    Raises
    ------
    BundleError
    """
    import numpy as np

    name = upload.path.rsplit("/", 1)[-1]
    try:
        fresh = reread(artifact.kind, artifact.params, raw_path.read_bytes(), name)
    except BundleError:
        raise
    except Exception as exc:  # noqa: BLE001 -- any reader's refusal refuses the bundle, said
        raise BundleError(
            f"{artifact.id}'s original file {name[:100]!r} cannot be read as an upload here: "
            f"{str(exc)[:300]}"
        ) from None
    differs = sorted(
        key
        for key in set(arrays) | set(fresh)
        if key not in arrays
        or key not in fresh
        or arrays[key].shape != fresh[key].shape
        or arrays[key].dtype != fresh[key].dtype
        or not np.array_equal(arrays[key], fresh[key], equal_nan=arrays[key].dtype.kind in "fc")
    )
    if differs:
        older = manifest.teachpath_version != teachpath_version()
        raise BundleError(
            f"{artifact.id}'s arrays are not what its original file {name[:100]!r} reads as "
            f"({', '.join(differs[:5])} differ): the bundle was altered"
            + (
                f", or teachpath {manifest.teachpath_version} that wrote it read the file "
                "otherwise; upload the original file into a new session instead"
                if older
                else "; export it again"
            )
        )


def _check_npz(path: Path) -> None:
    """An arrays file whose arrays fit in it: ``np.savez`` stores its members uncompressed, and
    each member's header must not declare more data than the member holds (numpy allocates what
    the header declares before it reads: a bomb inside the bundle).

    Raises
    ------
    ValueError
    """
    import numpy as np

    with zipfile.ZipFile(path) as npz:
        for info in npz.infolist():
            if info.compress_type != zipfile.ZIP_STORED or info.flag_bits & 0x1:
                raise ValueError("its arrays file has compressed or encrypted members")
            with npz.open(info) as member:
                version = np.lib.format.read_magic(member)
                if version == (1, 0):
                    shape, _, dtype = np.lib.format.read_array_header_1_0(member)
                else:
                    shape, _, dtype = np.lib.format.read_array_header_2_0(member)
            declared = math.prod(shape) * dtype.itemsize
            if dtype.hasobject or declared > info.file_size:
                raise ValueError(
                    f"its array {info.filename[:60]!r} declares {declared} bytes in a member of "
                    f"{info.file_size}"
                )


def _remove(staged: list[tuple[Path, Path]]) -> None:
    for tmp, final in staged:
        tmp.unlink(missing_ok=True)
        if final.parent.parent.name == "uploads":
            with contextlib.suppress(OSError):
                final.parent.rmdir()


def _record(store: Store, manifest: Manifest) -> None:
    """The session and its artifacts, in one transaction."""
    session = manifest.session
    with store.db.begin() as db:
        # The manifest's session and artifacts hold the rows' own columns (by construction).
        db.add(SessionRow(**session.model_dump()))
        db.flush()  # the session before the artifacts that refer to it
        for artifact in manifest.artifacts:
            db.add(
                ArtifactRow(
                    **artifact.model_dump(exclude={"data", "files"}),
                    session_id=session.id,
                    path=artifact.data.path,
                    sha256=artifact.data.sha256,
                    size=artifact.data.size,
                )
            )


__all__ = [
    "BUNDLE_FILES",
    "BUNDLE_SCHEMA",
    "BundleConflictError",
    "BundleError",
    "BundleReader",
    "ImportResult",
    "Manifest",
    "build_manifest",
    "export_bundle",
    "import_bundle",
]
