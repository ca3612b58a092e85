"""`macb view`'s app: the figure view's page and its data over a runs folder, read-only
(cli/view.py reads the folder; this module only serves it). Apart from cli/view.py so that
`macb`'s other commands do not import FastAPI.
"""

from __future__ import annotations

from typing import Any, Protocol

from fastapi import FastAPI, Request, Response
from fastapi.responses import HTMLResponse, JSONResponse

from cli.runs_folder import RunsError
from services.api.pages import page


class Source(Protocol):
    """What the app serves: cli/view.py's FolderView."""

    def data(self) -> tuple[str, dict[str, Any]]: ...


def page_app(view: Source) -> FastAPI:
    """The read-only app: GET / (the page), GET /figure.json (its data; ETag, 304 when
    unchanged: the page polls it)."""
    app = FastAPI(title="macb view", docs_url=None, redoc_url=None, openapi_url=None)

    @app.get("/", response_class=HTMLResponse)
    def index() -> HTMLResponse:
        return HTMLResponse(page("figure.html"), headers={"Cache-Control": "no-cache"})

    @app.get("/figure.json")
    def figure_json(request: Request) -> Response:
        try:
            version, data = view.data()
        except (RunsError, OSError, ValueError) as err:
            return JSONResponse({"detail": str(err)}, status_code=503)
        etag = f'"{version}"'
        if request.headers.get("if-none-match") == etag:
            return Response(status_code=304, headers={"ETag": etag})
        return JSONResponse(data, headers={"ETag": etag, "Cache-Control": "no-cache"})

    return app
