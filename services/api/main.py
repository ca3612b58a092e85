"""The API service: experiments and runs over REST, a metrics store, live metrics, a dashboard.

`make_app(settings)` builds the FastAPI app: a SQLite store (`store.py`), a scheduler
thread with its own bus session (`scheduler.py`), the routes and the dashboard.
`macb serve api --listen-http 127.0.0.1:8000 --data-dir D` runs it with uvicorn.

Access: loopback by default. With MACB_API_TOKEN set, every call but GET /health
needs `Authorization: Bearer <token>` (the dashboard page also takes `?token=`, which
it then sends as that header); without a token the API refuses to listen on any
address that is not loopback.
"""

from __future__ import annotations

import contextlib
import hmac
import ipaddress
import json
import logging
import threading
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any
from urllib.parse import parse_qs, urlencode

from fastapi import FastAPI, Request
from fastapi.encoders import jsonable_encoder
from fastapi.exception_handlers import http_exception_handler
from fastapi.exceptions import RequestValidationError
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.responses import HTMLResponse, JSONResponse, Response
from pydantic import Field, SecretStr
from pydantic_settings import BaseSettings, SettingsConfigDict
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import Match

from shared.net.bus import default_connect
from shared.persist.files import DATA_DIR_RULE, default_data_dir

from .pages import page
from .routes import experiments, presets, runs, workers
from .scheduler import Scheduler
from .store import Store

log = logging.getLogger("macb.api")


class Settings(BaseSettings):
    """API settings; each can be set as MACB_API_<NAME> in the environment."""

    model_config = SettingsConfigDict(env_prefix="MACB_API_", extra="ignore")

    host: str = Field("127.0.0.1", description="address to listen on (loopback by default)")
    port: int = Field(8000, ge=0, le=65535)
    data_dir: Path = Field(
        default_factory=default_data_dir,
        description=f"the store goes here unless `db` is set (default: {DATA_DIR_RULE})",
    )
    db: Path | None = Field(None, description="SQLite file (default: DATA_DIR/api.sqlite3)")
    token: SecretStr | None = Field(None, description="bearer token required on every call")
    connect: list[str] | None = Field(None, description="router endpoints (MACB_ZENOH_CONNECT)")
    service_id: str = "api"
    max_body: int = Field(64 * 1024, ge=1, description="largest request body, bytes (413)")
    scheduler: bool = Field(
        True,
        description="run the scheduler (off: the store served as it is; runs posted here are "
        "stored and queued, but nothing in this process starts or follows them)",
    )
    sse_poll_s: float = Field(0.25, gt=0)
    counter_grace_s: float = Field(120.0, gt=0)
    start_timeout_s: float = Field(60.0, gt=0)
    group_size: int = Field(
        1,
        ge=1,
        description="start up to N queued lockstep runs of one experiment that can share "
        "a group as one run group (one learner, actor and evaluator for them all)",
    )
    task_modules: list[str] = Field(
        ["mpe2", "pettingzoo", "examples"],
        description="packages a custom task (package.module:factory) may come from (the "
        "API imports and calls it to check a body); MACB_API_TASK_MODULES takes a JSON list",
    )

    configs_dir: Path | None = Field(
        None,
        description="the presets the dashboard offers (default: the shipped configs/, "
        "MACB_CONFIGS_DIR)",
    )

    @property
    def presets_dir(self) -> Path:
        if self.configs_dir is not None:
            return self.configs_dir
        from shared.settings import shipped_configs

        return shipped_configs()

    @property
    def db_path(self) -> Path:
        return self.db or self.data_dir / "api.sqlite3"

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"http://{host}:{self.port}"


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def check_bind(settings: Settings) -> None:
    """Refuse an empty token (a compose file passing an unset variable gives one, and
    "Bearer " would then be the password), and a non-loopback address without a token
    (raises ValueError)."""
    if settings.token is not None and not settings.token.get_secret_value().strip():
        raise ValueError("MACB_API_TOKEN is set but empty: give it a secret or unset it")
    if not is_loopback(settings.host) and settings.token is None:
        raise ValueError(
            f"refusing to listen on {settings.host}: not a loopback address and no token; "
            "set MACB_API_TOKEN (clients then send Authorization: Bearer <token>)"
        )


# ---------------------------------------------------------------- ASGI middleware
async def _send_json(send, status: int, detail: str, headers: list | None = None) -> None:
    body = json.dumps({"detail": detail}).encode()
    await send(
        {
            "type": "http.response.start",
            "status": status,
            "headers": [
                (b"content-type", b"application/json"),
                (b"content-length", str(len(body)).encode()),
                *(headers or []),
            ],
        }
    )
    await send({"type": "http.response.body", "body": body})


class BodyLimit:
    """Refuse bodies over `max_body` bytes with 413 before the app sees them."""

    def __init__(self, app, max_body: int) -> None:
        self.app = app
        self.max_body = max_body

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        length = dict(scope["headers"]).get(b"content-length")
        if length is not None:
            try:
                declared = int(length)
            except ValueError:
                await _send_json(send, 400, "bad Content-Length")
                return
            if declared > self.max_body:
                await _send_json(send, 413, f"request body over {self.max_body} bytes")
                return
        chunks, size, more = [], 0, True
        while more:
            message = await receive()
            if message["type"] == "http.disconnect":
                return
            chunk = message.get("body", b"")
            size += len(chunk)
            if size > self.max_body:
                await _send_json(send, 413, f"request body over {self.max_body} bytes")
                return
            chunks.append(chunk)
            more = message.get("more_body", False)
        body, replayed = b"".join(chunks), False

        async def replay():
            nonlocal replayed
            if not replayed:
                replayed = True
                return {"type": "http.request", "body": body, "more_body": False}
            return await receive()

        await self.app(scope, replay, send)


class TokenAuth:
    """With a token: `Authorization: Bearer <token>` on every call but /health."""

    OPEN = ("/health",)
    # May take the token as ?token= (a link, a browser's address); /docs passes it on to
    # the /openapi.json it loads.
    PAGES = ("/", "/view", "/docs", "/openapi.json")

    def __init__(self, app, token: str) -> None:
        self.app = app
        self.expected = f"Bearer {token}".encode()
        self.token = token.encode()

    def _ok(self, scope) -> bool:
        if scope["path"] in self.OPEN:
            return True
        header = dict(scope["headers"]).get(b"authorization", b"")
        if hmac.compare_digest(header, self.expected):
            return True
        if scope["path"] in self.PAGES and scope["method"] in ("GET", "HEAD"):
            query = parse_qs(scope.get("query_string", b"").decode("latin-1"))
            given = (query.get("token") or [""])[0].encode()
            return hmac.compare_digest(given, self.token)
        return False

    async def __call__(self, scope, receive, send) -> None:
        if scope["type"] == "http" and not self._ok(scope):
            await _send_json(
                send, 401, "missing or wrong bearer token", [(b"www-authenticate", b"Bearer")]
            )
            return
        await self.app(scope, receive, send)


# ---------------------------------------------------------------- the app
def _validation_error(request: Request, exc: Exception) -> JSONResponse:
    """422 naming each field and the reason (400 when the body is not JSON at all)."""
    assert isinstance(exc, RequestValidationError)  # (registered for it alone)
    errors = []
    for e in exc.errors():
        loc = [str(p) for p in e.get("loc", ())]
        msg = str(e.get("msg", "invalid")).removeprefix("Value error, ")
        field = ".".join(loc[1:]) if len(loc) > 1 else ""
        if not field and ": " in msg and " " not in msg.split(": ", 1)[0].replace(" x ", "_"):
            field = msg.split(": ", 1)[0]
        if e.get("type") == "extra_forbidden":
            msg = "unknown key (misspelt?)"
        if e.get("type") == "json_invalid":  # loc is (body, character position)
            field, msg = "body", f"not valid JSON: {msg} at character {loc[-1]}"
        errors.append({"loc": loc, "field": field or "body", "msg": msg, "type": e.get("type")})
    status = 400 if any(e["type"] == "json_invalid" for e in errors) else 422
    return JSONResponse({"detail": jsonable_encoder(errors)}, status_code=status)


METHODS = ("GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS")


def allowed_methods(app: FastAPI, scope: Mapping[str, Any]) -> list[str]:
    """The methods some route of the app answers on this request's path."""
    return [
        method
        for method in METHODS
        if any(r.matches({**scope, "method": method})[0] is Match.FULL for r in app.router.routes)
    ]


async def _http_error(request: Request, exc: Exception) -> Response:
    """A 405's `Allow` lists every method of the path, not only those of the route that
    matched first (GET and POST /experiments are two routes: Starlette named one)."""
    assert isinstance(exc, StarletteHTTPException)  # (registered for it alone)
    if exc.status_code == 405 and (allowed := allowed_methods(request.app, request.scope)):
        headers = {**(exc.headers or {}), "Allow": ", ".join(allowed)}
        exc = StarletteHTTPException(405, exc.detail, headers)
    return await http_exception_handler(request, exc)


# The figure view's data for an experiment, computed by the report's functions: given by
# the command that starts the API (cli/view.py's experiment_view), since services/ does
# not import cli/. It takes the experiment (as GET /experiments/{id}) and each run's points.
FigureView = Callable[[dict[str, Any], dict[str, list[dict[str, Any]]]], dict[str, Any]]


def make_app(settings: Settings | None = None, figure_view: FigureView | None = None) -> FastAPI:
    settings = settings or Settings()
    store = Store(settings.db_path)
    scheduler = None
    if settings.scheduler:
        scheduler = Scheduler(
            store,
            settings.connect or default_connect(),
            service_id=settings.service_id,
            http_url=settings.url,
            counter_grace_s=settings.counter_grace_s,
            group_size=settings.group_size,
            start_timeout_s=settings.start_timeout_s,
        )

    @contextlib.asynccontextmanager
    async def lifespan(app: FastAPI):
        if scheduler is not None:
            scheduler.start()
        log.info("API store %s", settings.db_path)
        try:
            yield
        finally:
            if scheduler is not None:
                scheduler.close()
            store.close()

    app = FastAPI(
        title="MACB API",
        version=workers.VERSION,
        description="Experiments and runs of multi-agent count-based exploration on the "
        "cluster: launch, follow, stop, and read every stored metric point.",
        lifespan=lifespan,
        docs_url=None,  # ours below: it passes a ?token= on to the schema it loads
    )
    app.state.settings = settings
    app.state.store = store
    app.state.scheduler = scheduler
    app.state.figure_view = figure_view
    app.add_exception_handler(RequestValidationError, _validation_error)
    app.add_exception_handler(StarletteHTTPException, _http_error)
    app.include_router(experiments.router)
    app.include_router(runs.router)
    app.include_router(workers.router)
    app.include_router(presets.router)

    @app.get("/", response_class=HTMLResponse, include_in_schema=False)
    def dashboard() -> HTMLResponse:
        return HTMLResponse(page("dashboard.html"), headers={"Cache-Control": "no-cache"})

    @app.get("/docs", response_class=HTMLResponse, include_in_schema=False)
    def api_docs(token: str | None = None) -> HTMLResponse:
        """Swagger UI. A browser cannot send the bearer header with a link, so the token
        it was given as ?token= goes on to the schema's URL (its "Try it out" requests
        carry no token: with one set, they get 401; macb and curl send the header)."""
        schema = app.openapi_url or "/openapi.json"
        if token:
            schema += "?" + urlencode({"token": token})
        return get_swagger_ui_html(openapi_url=schema, title=f"{app.title} - docs")

    @app.get("/view", response_class=HTMLResponse, include_in_schema=False)
    def figure_page() -> HTMLResponse:
        """The figure view of ?experiment=ID (its data: GET /experiments/{id}/figure)."""
        return HTMLResponse(page("figure.html"), headers={"Cache-Control": "no-cache"})

    app.add_middleware(BodyLimit, max_body=settings.max_body)
    if settings.token is not None:
        app.add_middleware(TokenAuth, token=settings.token.get_secret_value())
    return app


# ---------------------------------------------------------------- serving
def _uvicorn_config(app: FastAPI, settings: Settings):
    import uvicorn

    return uvicorn.Config(
        app,
        host=settings.host,
        port=settings.port,
        log_level="warning",
        access_log=False,
        timeout_graceful_shutdown=2,
        lifespan="on",
    )


def serve(settings: Settings, figure_view: FigureView | None = None) -> int:
    """Run the API in the foreground until SIGTERM / Ctrl-C; exit code."""
    import uvicorn

    try:
        check_bind(settings)
    except ValueError as err:
        log.error("%s", err)
        print(f"macb serve api: {err}", flush=True)
        return 2
    app = make_app(settings, figure_view)
    print(f"API on {settings.url}/ (docs at /docs), store {settings.db_path}", flush=True)
    server = uvicorn.Server(_uvicorn_config(app, settings))
    server.run()
    return 0 if server.started else 1


class ApiServer:
    """The API in a thread of this process on a loopback port (tests, benchmarks)."""

    def __init__(self, settings: Settings, figure_view: FigureView | None = None) -> None:
        self.settings = settings
        self.figure_view = figure_view
        self.app: FastAPI | None = None
        self.server: Any = None
        self.thread: threading.Thread | None = None

    @property
    def url(self) -> str:
        return self.settings.url

    def start(self, timeout: float = 30.0) -> ApiServer:
        import time

        import uvicorn

        check_bind(self.settings)
        if self.settings.port == 0:  # pick a free port now, so the app knows its URL
            import socket

            with socket.socket() as s:
                s.bind((self.settings.host, 0))
                port = s.getsockname()[1]
            self.settings = self.settings.model_copy(update={"port": port})
        self.app = make_app(self.settings, self.figure_view)
        self.server = uvicorn.Server(_uvicorn_config(self.app, self.settings))
        self.thread = threading.Thread(target=self.server.run, name="macb-api-http", daemon=True)
        self.thread.start()
        deadline = time.monotonic() + timeout
        while not self.server.started:
            if not self.thread.is_alive() or time.monotonic() > deadline:
                raise RuntimeError(f"the API did not start on {self.url}")
            time.sleep(0.02)
        return self

    def stop(self) -> None:
        if self.server is not None:
            self.server.should_exit = True
        if self.thread is not None:
            self.thread.join(30)

    def __enter__(self) -> ApiServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
