"""The API's documentation, served by the daemon itself: Swagger UI at ``/api/v1/docs``, ReDoc at ``/api/v1/redoc``.

FastAPI's own docs page loads Swagger UI from a CDN, which a plant network
does not reach. Here the Swagger UI files come from the ``fastapi-offline``
package (``swagger-ui-bundle.js``, ``swagger-ui.css``: the swagger-ui-dist
build it ships), served under ``/api/v1/docs/assets/``, and the page starts
Swagger UI with a script file of ours (``docs-init.js``) instead of an inline
script, so its Content-Security-Policy (:data:`DOCS_POLICY`) allows scripts
from the daemon only. Swagger UI sets inline ``style`` attributes, hence
``style-src 'unsafe-inline'`` on this page alone; nothing else is relaxed.

ReDoc (a reference page for reading rather than trying) comes from the same
package (``redoc.standalone.js``), started by ``redoc-init.js``, under
:data:`REDOC_POLICY`: the docs' policy plus ``worker-src blob:`` (its search
index runs in a Web Worker made from a blob). ReDoc injects ``<style>``
elements (styled-components), which ``'unsafe-inline'`` already covers. The
bundle is served with one change: its side menu's Redocly logo, the one
thing it would load from outside by itself (a CDN), is a blank image.
"""

from __future__ import annotations

import functools
import importlib.resources
import pathlib

from fastapi import APIRouter, FastAPI
from fastapi.responses import FileResponse, HTMLResponse, Response
from fastapi.staticfiles import StaticFiles

# Swagger UI's files as shipped by fastapi-offline.
ASSETS = pathlib.Path(str(importlib.resources.files("fastapi_offline") / "static"))
INIT = pathlib.Path(__file__).parent / "docs-init.js"
REDOC_INIT = pathlib.Path(__file__).parent / "redoc-init.js"
# The image ReDoc's side menu loads from a CDN (unconditionally, in its "API docs by Redocly" link), and what it is
# replaced with: a blank 1×1 GIF (a data: image, which the policy allows).
REDOC_LOGO = "https://cdn.redoc.ly/redoc/logo-mini.svg"
BLANK_IMAGE = "data:image/gif;base64,R0lGODlhAQABAIAAAAAAAP///yH5BAEAAAAALAAAAAABAAEAAAIBRAA7"
# Scripts, styles sheets, images and the OpenAPI document from the daemon only; inline style attributes (Swagger
# UI's own rendering) allowed; no framing.
DOCS_POLICY = ("default-src 'self'; script-src 'self'; style-src 'self' 'unsafe-inline'; img-src 'self' data:; "
               "connect-src 'self'; frame-ancestors 'none'; base-uri 'none'; form-action 'self'; object-src 'none'")
REDOC_POLICY = f"{DOCS_POLICY}; worker-src 'self' blob:"

# A docs page: its title, an extra line in the head (a style sheet), the root element and the two scripts (the
# bundle, then ours that starts it on the OpenAPI document).
_PAGE = """<!doctype html>
<html lang="en">
<head>
  <meta charset="utf-8">
  <meta name="viewport" content="width=device-width, initial-scale=1">
  <title>{title}</title>
  <link rel="icon" href="docs/assets/favicon.png">{head}
</head>
<body>
  <div id="{root}" data-openapi="openapi.json"></div>
  <script src="{bundle}"></script>
  <script src="{init}"></script>
</body>
</html>
"""


@functools.cache
def redoc_bundle() -> bytes:
    """fastapi-offline's ``redoc.standalone.js`` with its CDN logo replaced by :data:`BLANK_IMAGE` (read once)."""
    return (ASSETS / "redoc.standalone.js").read_text(encoding="utf-8").replace(REDOC_LOGO, BLANK_IMAGE).encode()


def policy_of(path: str, prefix: str) -> str | None:
    """The Content-Security-Policy of a docs path (Swagger UI's or ReDoc's page and files); None for another path."""
    if path == f"{prefix}/redoc":
        return REDOC_POLICY
    if path == f"{prefix}/docs" or path.startswith(f"{prefix}/docs/"):
        return DOCS_POLICY
    return None


def install(app: FastAPI, prefix: str) -> None:
    """Serve Swagger UI at ``{prefix}/docs``, ReDoc at ``{prefix}/redoc`` and their files below ``{prefix}/docs/``
    (relative URLs: works behind a proxy's path)."""
    router = APIRouter(prefix=prefix, include_in_schema=False)
    page = _PAGE.format(title=f"{app.title} · API", head='\n  <link rel="stylesheet" href="docs/assets/swagger-ui.css">',
                        root="swagger-ui", bundle="docs/assets/swagger-ui-bundle.js", init="docs/docs-init.js")
    redoc_page = _PAGE.format(title=f"{app.title} · API reference", head="", root="redoc",
                              bundle="docs/redoc.standalone.js", init="docs/redoc-init.js")

    @router.get("/docs")
    async def docs() -> HTMLResponse:
        return HTMLResponse(page)

    @router.get("/docs/docs-init.js")
    async def init() -> FileResponse:
        return FileResponse(INIT, media_type="text/javascript")

    @router.get("/redoc")
    async def redoc() -> HTMLResponse:
        return HTMLResponse(redoc_page)

    @router.get("/docs/redoc.standalone.js")
    async def redoc_script() -> Response:
        return Response(redoc_bundle(), media_type="text/javascript")

    @router.get("/docs/redoc-init.js")
    async def redoc_init() -> FileResponse:
        return FileResponse(REDOC_INIT, media_type="text/javascript")

    app.include_router(router)
    app.mount(f"{prefix}/docs/assets", StaticFiles(directory=ASSETS), name="docs-assets")
