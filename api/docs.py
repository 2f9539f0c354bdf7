"""The API's interactive documentation, served by the daemon itself: Swagger UI at ``/api/v1/docs``.

FastAPI's own docs page loads Swagger UI from a CDN, which a plant network
does not reach. Here the Swagger UI files come from the ``fastapi-offline``
package (``swagger-ui-bundle.js``, ``swagger-ui.css``: the swagger-ui-dist
build it ships), served under ``/api/v1/docs/assets/``, and the page starts
Swagger UI with a script file of ours (``docs-init.js``) instead of an inline
script, so its Content-Security-Policy (:data:`DOCS_POLICY`) allows scripts
from the daemon only. Swagger UI sets inline ``style`` attributes, hence
``style-src 'unsafe-inline'`` on this page alone; nothing else is relaxed.
"""

from __future__ import annotations

import importlib.resources
import pathlib

from fastapi import APIRouter, FastAPI
from fastapi.responses import FileResponse, HTMLResponse
from fastapi.staticfiles import StaticFiles

# Swagger UI's files as shipped by fastapi-offline.
ASSETS = pathlib.Path(str(importlib.resources.files("fastapi_offline") / "static"))
INIT = pathlib.Path(__file__).parent / "docs-init.js"
# Scripts, styles sheets, images and the OpenAPI document from the daemon only; inline style attributes (Swagger
# UI's own rendering) allowed; no framing.
DOCS_POLICY = ("default-src 'self'; script-src 'self'; style-src 'self' 'unsafe-inline'; img-src 'self' data:; "
               "connect-src 'self'; frame-ancestors 'none'; base-uri 'none'; form-action 'self'; object-src 'none'")

_PAGE = """<!doctype html>
<html lang="en">
<head>
  <meta charset="utf-8">
  <meta name="viewport" content="width=device-width, initial-scale=1">
  <title>{title} · API</title>
  <link rel="icon" href="docs/assets/favicon.png">
  <link rel="stylesheet" href="docs/assets/swagger-ui.css">
</head>
<body>
  <div id="swagger-ui" data-openapi="openapi.json"></div>
  <script src="docs/assets/swagger-ui-bundle.js"></script>
  <script src="docs/docs-init.js"></script>
</body>
</html>
"""


def install(app: FastAPI, prefix: str) -> None:
    """Serve the docs page at ``{prefix}/docs`` and its files below it (relative URLs: works behind a proxy's path)."""
    router = APIRouter(prefix=prefix, include_in_schema=False)
    page = _PAGE.format(title=app.title)

    @router.get("/docs")
    async def docs() -> HTMLResponse:
        return HTMLResponse(page)

    @router.get("/docs/docs-init.js")
    async def init() -> FileResponse:
        return FileResponse(INIT, media_type="text/javascript")

    app.include_router(router)
    app.mount(f"{prefix}/docs/assets", StaticFiles(directory=ASSETS), name="docs-assets")
