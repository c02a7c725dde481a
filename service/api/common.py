"""Pieces several routers share: the list/get routes of an artifact kind, uploads, downloads."""

from __future__ import annotations

import contextlib
from collections.abc import AsyncIterator, Callable, Mapping
from typing import Any

from fastapi import APIRouter, Request, UploadFile
from fastapi.responses import Response
from pydantic import BaseModel

from service.api.deps import ServicesDep
from service.core import Services
from service.errors import ApiError
from service.inputs import Upload
from service.store import ArtifactRow, SessionRow
from service.uploads import clean_filename

#: ``outdated(services, session, row)``: what changed since an artifact was made.
Outdated = Callable[[Services, SessionRow, ArtifactRow], list[str]]


def add_artifact_routes(
    router: APIRouter,
    kind: str,
    plural: str,
    model: type[BaseModel],
    *,
    outdated: Outdated | None = None,
) -> None:
    """``GET /{plural}`` (oldest first) and ``GET /{plural}/{artifact_id}`` for one kind.

    ``outdated(services, session, row) -> list[str]``, where given, fills each one's
    ``outdated`` (:mod:`service.provenance`): what changed since it was made (the session's
    inputs and calibration, the cell).
    """

    def shown(services: Services, session: SessionRow, row: ArtifactRow) -> ArtifactRow | BaseModel:
        if outdated is None:
            return row
        return model.model_validate(row).model_copy(
            update={"outdated": outdated(services, session, row)}
        )

    def list_artifacts(session_id: str, services: ServicesDep) -> list[ArtifactRow | BaseModel]:
        session = services.session(session_id)
        return [shown(services, session, row) for row in services.store.artifacts(session_id, kind)]

    def get_artifact(
        session_id: str, artifact_id: str, services: ServicesDep
    ) -> ArtifactRow | BaseModel:
        session = services.session(session_id)
        return shown(services, session, services.artifact(session_id, kind, artifact_id))

    router.add_api_route(
        f"/{plural}",
        list_artifacts,
        methods=["GET"],
        response_model=list[model],  # type: ignore[valid-type]  # the kind's model, a value
        name=f"list_{plural}",
        summary=f"Every {kind} of the session, oldest first",
    )
    router.add_api_route(
        f"/{plural}/{{artifact_id}}",
        get_artifact,
        methods=["GET"],
        response_model=model,
        name=f"get_{kind}",
        summary=f"One {kind}: its inputs, parameters and summary",
    )


@contextlib.asynccontextmanager
async def received(file: UploadFile, services: Services) -> AsyncIterator[Upload]:
    """The uploaded file, counted as in flight until the block ends (parsed and stored).

    Its size is known before its bytes are read (the form parser spooled it to disk), so an
    upload past the server's size limit, or one the in-flight cap has no room for, is refused
    before it takes any memory. Its name is cleaned (:func:`service.uploads.clean_filename`).

    Raises
    ------
    ApiError
        413 ``upload_too_large``, 503 ``uploads_busy`` (with ``Retry-After``), or 422
        ``invalid_file`` for an empty file.
    """
    limit_mb = services.settings.max_upload_mb
    limit = int(limit_mb * 1024 * 1024)
    if file.size is not None and file.size > limit:
        raise ApiError(413, "upload_too_large", f"the upload exceeds {limit_mb:g} MB")
    size = min(file.size if file.size is not None else limit, limit)
    _require_room(services, size)
    with services.uploads.hold(size):
        content = await file.read(limit + 1)
        if len(content) > limit:
            raise ApiError(413, "upload_too_large", f"the upload exceeds {limit_mb:g} MB")
        if not content:
            raise ApiError(422, "invalid_file", "the uploaded file is empty")
        yield Upload(content=content, filename=clean_filename(file.filename))


def _require_room(services: Services, size: int) -> None:
    """503 ``storage_full`` when the data folder's disk has no room for an upload of ``size``
    bytes and its arrays (kept twice over: the raw file and what it is parsed to), before the
    upload is parsed: a parse that fails for the server's full disk is not the file's fault."""
    import errno
    import shutil

    from service.api.health import MIN_FREE_BYTES

    if shutil.disk_usage(services.store.data_dir).free < 2 * size + MIN_FREE_BYTES:
        raise OSError(errno.ENOSPC, "no room in the data folder for this upload")


def download(content: bytes | str, *, media_type: str, filename: str) -> Response:
    """A file download."""
    return Response(
        content,
        media_type=media_type,
        headers={"Content-Disposition": f'attachment; filename="{filename}"'},
    )


def gzip_json(content: Mapping[str, Any], request: Request) -> Response:
    """JSON for the pendant's drawings, gzip-compressed (``Content-Encoding: gzip``) for a
    client that accepts it (every browser), plain for one that does not."""
    import gzip
    import json

    body = json.dumps(content, separators=(",", ":"), allow_nan=False).encode()
    headers = {"Cache-Control": "no-store", "Vary": "Accept-Encoding"}
    if "gzip" in request.headers.get("accept-encoding", "").lower():
        body = gzip.compress(body, compresslevel=5, mtime=0)
        headers["Content-Encoding"] = "gzip"
    return Response(body, media_type="application/json", headers=headers)


#: OpenAPI entries of the download routes (FastAPI's type for ``responses``).
OpenApiResponses = dict[int | str, dict[str, Any]]
CSV: OpenApiResponses = {200: {"content": {"text/csv": {}}}}
BINARY: OpenApiResponses = {200: {"content": {"application/octet-stream": {}}}}
PNG: OpenApiResponses = {200: {"content": {"image/png": {}}}}
