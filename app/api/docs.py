"""The interactive API docs (/docs) and the favicon, served from the app's own files.

FastAPI's default /docs page loads Swagger UI from a CDN and is blank without internet, while the
service is meant to work on a closed network. Swagger UI comes from the npm registry instead
(swagger-ui-dist in web/package.json, copied into static/vendor/swagger-ui by ``make setup`` and the
Dockerfile), like Leaflet. /redoc is turned off rather than vendored: it is a second renderer of the same
document, and its default page also pulls fonts from Google."""

from __future__ import annotations

from pathlib import Path

from fastapi import FastAPI
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.responses import FileResponse, HTMLResponse

from app.api import security

VENDOR = "/static/vendor/swagger-ui"
DOCS_CSS = "/static/docs.css"


def install(app: FastAPI, web_dir: Path) -> None:
    """Call on an app made with ``docs_url=None, redoc_url=None``."""

    @app.get("/docs", include_in_schema=False)
    def docs() -> HTMLResponse:
        page = get_swagger_ui_html(
            openapi_url=app.openapi_url,
            title=f"{app.title} - API docs",
            swagger_js_url=f"{VENDOR}/swagger-ui-bundle.js",
            swagger_css_url=f"{VENDOR}/swagger-ui.css",
            swagger_favicon_url="/favicon.ico",
            # No call to swagger.io's online validator: nothing leaves the machine.
            swagger_ui_parameters={"validatorUrl": None},
        )
        # Our few rules after Swagger UI's: the description's wide error table scrolls inside itself at phone
        # width instead of widening the whole page (static/docs.css).
        body = bytes(page.body).replace(b"</head>", f'<link rel="stylesheet" href="{DOCS_CSS}">\n</head>'.encode(), 1)
        return HTMLResponse(body, headers=security.DOCS_HEADERS)  # never framed; no script policy (security.py)

    @app.get("/favicon.ico", include_in_schema=False)
    def favicon() -> FileResponse:
        return FileResponse(web_dir / "favicon.ico", media_type="image/x-icon")
