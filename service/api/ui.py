"""The teach pendant's static files, and the API docs served from local copies (no CDN).

The browser libraries (three.js, Swagger UI, ReDoc) come from npm at set-up time
(``scripts/setup.sh``: ``npm ci`` and a copy into ``service/ui/vendor/``, git-ignored). Every
page here is sent with a Content-Security-Policy that allows only this origin; inline scripts
(the page's import map, the docs' start-up snippets) are allowed by their SHA-256 alone.
"""

from __future__ import annotations

import base64
import hashlib
import re
from pathlib import Path

from fastapi import FastAPI
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html
from fastapi.responses import FileResponse, HTMLResponse, Response
from fastapi.staticfiles import StaticFiles
from starlette.types import Scope

UI_DIR = Path(__file__).resolve().parent.parent / "ui"
VENDOR_DIR = UI_DIR / "vendor"
#: Where the static files are served.
PREFIX = "/ui"
#: The set-up step that brings the vendored libraries (named where they are missing).
SETUP_HINT = "run scripts/setup.sh (make setup): it installs them with npm ci"

_INLINE_SCRIPT = re.compile(r"<script(?![^>]*\bsrc=)[^>]*>(.*?)</script>", re.S | re.I)


def _script_hashes(html: str) -> list[str]:
    return [
        "'sha256-" + base64.b64encode(hashlib.sha256(body.encode()).digest()).decode() + "'"
        for body in _INLINE_SCRIPT.findall(html)
        if body.strip()
    ]


def policy(html: str = "", *, style: str = "'self'", worker: str = "'self'") -> str:
    """The Content-Security-Policy for a page: this origin only; its inline scripts by hash."""
    scripts = " ".join(["'self'", *_script_hashes(html)])
    return (
        f"default-src 'self'; script-src {scripts}; style-src {style}; "
        f"img-src 'self' data: blob:; worker-src {worker}; connect-src 'self'; "
        "object-src 'none'; base-uri 'none'; frame-ancestors 'none'; form-action 'self'"
    )


def headers(csp: str) -> dict[str, str]:
    return {
        "Content-Security-Policy": csp,
        "Referrer-Policy": "no-referrer",
        "X-Content-Type-Options": "nosniff",
        "Cache-Control": "no-cache",
    }


class UiFiles(StaticFiles):
    """The pendant's files, with the security headers."""

    async def get_response(self, path: str, scope: Scope) -> Response:
        response = await super().get_response(path, scope)
        response.headers.update(headers(policy()))
        return response


class GuideFiles(StaticFiles):
    """The documentation site (``make docs``), with the security headers: each page's inline
    scripts allowed by their hashes; inline styles allowed (the diagrams draw with them)."""

    async def get_response(self, path: str, scope: Scope) -> Response:
        response = await super().get_response(path, scope)
        html = ""
        # A file's response (not a 304, nor a redirect) has the path of the page.
        if response.media_type == "text/html" and isinstance(response, FileResponse):
            html = Path(response.path).read_text(errors="replace")
        response.headers.update(headers(policy(html, style="'self' 'unsafe-inline'")))
        return response


def _page(response: HTMLResponse, **csp: str) -> HTMLResponse:
    html = bytes(response.body).decode()
    return HTMLResponse(html, headers=headers(policy(html, **csp)))


def install(app: FastAPI, guide_dir: Path | None = None) -> None:
    """``/`` (the pendant), ``/ui/...`` (its files), ``/docs`` and ``/redoc`` (local assets),
    and ``/guide/`` (the documentation site, where ``make docs`` built it).

    The app must be made with ``docs_url=None, redoc_url=None``.
    """
    app.mount(PREFIX, UiFiles(directory=UI_DIR, check_dir=False), name="ui")
    if guide_dir is not None and (guide_dir / "index.html").is_file():
        app.mount("/guide", GuideFiles(directory=guide_dir, html=True), name="guide")
    else:

        @app.get("/guide", include_in_schema=False)
        @app.get("/guide/{rest:path}", include_in_schema=False)
        def guide_not_built(rest: str = "") -> HTMLResponse:
            return HTMLResponse(
                "<!doctype html><title>teachpath guide</title><p>The documentation site is not "
                "built on this server: run <code>make docs</code> (or <code>make run</code>, "
                "which builds it) and restart the service. The same pages are in the "
                "repository's <code>docs/</code> folder.</p>",
                status_code=404,
                headers=headers(policy()),
            )

    @app.get("/", response_class=HTMLResponse, include_in_schema=False)
    def pendant() -> HTMLResponse:
        """The teach pendant (static; it calls the API with the token from the URL)."""
        html = (UI_DIR / "index.html").read_text()
        return HTMLResponse(html, headers=headers(policy(html)))

    vendor = f"{PREFIX}/vendor"
    openapi_url = app.openapi_url or "/openapi.json"  # the pages are only served with it

    @app.get("/docs", response_class=HTMLResponse, include_in_schema=False)
    def swagger_ui() -> HTMLResponse:
        page = get_swagger_ui_html(
            openapi_url=openapi_url,
            title=f"{app.title} - API",
            swagger_js_url=f"{vendor}/swagger-ui/swagger-ui-bundle.js",
            swagger_css_url=f"{vendor}/swagger-ui/swagger-ui.css",
            swagger_favicon_url=f"{vendor}/swagger-ui/favicon-32x32.png",
            swagger_ui_parameters={"validatorUrl": None},
        )
        return _page(page)

    @app.get("/redoc", response_class=HTMLResponse, include_in_schema=False)
    def redoc() -> HTMLResponse:
        page = get_redoc_html(
            openapi_url=openapi_url,
            title=f"{app.title} - API",
            redoc_js_url=f"{vendor}/redoc/redoc.standalone.js",
            redoc_favicon_url=f"{vendor}/swagger-ui/favicon-32x32.png",
            with_google_fonts=False,
        )
        # ReDoc styles itself with generated <style> elements and searches in a blob: worker.
        return _page(page, style="'self' 'unsafe-inline'", worker="'self' blob:")
