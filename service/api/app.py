"""The FastAPI app factory: settings in, app out; artifacts loaded once in the lifespan.

``create_app(settings)`` wires routers, error handlers and middleware. Its lifespan loads the
artifact folder (ONNX sessions, FAISS index, catalog), checks it against the manifest and
refuses to start with an error naming the bad file; then it runs a warm-up suggestion, after
which ``/readyz`` answers 200, and starts the micro-batcher that runs suggestions
(``service.api.batching``; closed, after answering what is queued, at shutdown) and the
catalog writer, all held by one ``Served`` (``service.api.served``) that routes get through
``service.api.deps.ServedDep``.
``uvicorn --factory service.api.app:create_app`` works too.
"""

from __future__ import annotations

import gc
import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager, suppress
from functools import partial
from pathlib import Path

import anyio
import fastapi_offline
from fastapi import FastAPI, Request
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html, get_swagger_ui_oauth2_redirect_html
from fastapi.staticfiles import StaticFiles
from starlette.formparsers import MultiPartParser
from starlette.responses import HTMLResponse
from starlette.routing import NoMatchFound

from service import __version__
from service.api.access_log import install_access_log_redaction
from service.api.deps import served_of
from service.api.errors import install_error_handlers
from service.api.head import HeadAsGetMiddleware
from service.api.json_body import JsonBodyMiddleware
from service.api.metrics import Metrics
from service.api.middleware import BodyLimitMiddleware, JsonCorsMiddleware, MetricsMiddleware, body_bound
from service.api.openapi_extras import add_common_responses, add_limits
from service.api.overload import ErrorBudgetMiddleware, OverloadMiddleware
from service.api.routes import assemble, catalog_write, parts, probes, suggest
from service.api.routes.page import install_page
from service.api.served import Served
from service.artifacts.layout import ArtifactError
from service.artifacts.loading import load_served_artifacts
from service.catalog_store.store import StoreError
from service.geometry import mesh_kernel
from service.geometry.inputs import MeshUploads
from service.modeling.assembly import Assembler
from service.settings import Settings, get_settings
from service.suggest import contact_kernel
from service.suggest.engine import SuggestionEngine

log = logging.getLogger(__name__)

DESCRIPTION = """\
Component suggestions for 3D modeling (ComplementMe, SIGGRAPH Asia 2017): send a partial
assembly as points or as a mesh; get catalog parts that complete it, ranked by the retrieval
network's mixture, each with the translation the placement network predicts for it.

Points are in the canonical frame (y up, the complete object centred and scaled to unit radius)
unless a request gives its own `frame` (`center`, `radius`, `up_axis`); answers are then in that
frame. Part ids contain a slash and are used verbatim in paths: `/parts/chair-0007/2/mesh`.
Every error is `{"error": {"code": ..., "message": ...}}`.
"""


@asynccontextmanager
async def lifespan(app: FastAPI) -> AsyncIterator[None]:
    settings: Settings = app.state.settings
    try:
        artifacts = load_served_artifacts(settings)
    except ArtifactError as exc:
        log.error("refusing to start: %s", exc)
        raise
    engine = SuggestionEngine(artifacts, settings)
    if settings.warmup:
        engine.warmup()         # compiles (or loads) contact refinement's and the spread's kernels
        contact_kernel.warm()    # and the assembly's cover shares, so the first /assemble does not
        mesh_kernel.warm()       # and the OBJ reader's, so the first upload does not
        Assembler(engine, settings).warm()  # and what /assemble reads of each category's shapes
        build_routes(app)        # and FastAPI's per-route state, so no route's first request does
    served = Served(engine, settings, app.state.metrics)
    try:  # catalog additions (COMPLEMENTME_DATA_DIR): serves shipped + added parts from here on
        served.open_catalog()
    except StoreError as exc:
        log.error("refusing to start: %s", exc)
        served.close(settings.request_timeout)
        raise
    # Move everything loaded so far (catalog records, sessions, the app) out of the collector's
    # reach: a full collection walked those ~160k objects in 60-90 ms, the p99 of JSON requests.
    gc.collect()
    gc.freeze()
    # A JSON request holds ~1000 coordinate lists while it waits for its batch; at Python's
    # default threshold the collector ran more than once per request and walked the lists of
    # every request in flight (see the gc_threshold setting).
    gc.set_threshold(settings.gc_threshold, *gc.get_threshold()[1:])
    app.state.served = served
    app.state.ready = True
    try:
        yield
    finally:
        app.state.ready = False
        # Requests still queued for a batch are answered; later ones get 503 shutting_down.
        await anyio.to_thread.run_sync(served.close, settings.request_timeout)
        app.state.served = None


def build_routes(app: FastAPI) -> None:
    """Build the state FastAPI keeps per route (its parameter models and validators) now.

    FastAPI builds an included router's routes on the first request that reaches the router:
    15-20 ms of the process's first `/suggest`, measured (36-38 ms against 10-13 for the next
    one). Looking up a route name that no route has walks every route, building each on the way,
    through Starlette's public ``url_path_for``; the lookup then fails, as it is meant to.
    """
    with suppress(NoMatchFound):
        app.url_path_for("complementme-warm-up: no route has this name")


# /docs and /redoc load Swagger UI and ReDoc from the service itself, not from a CDN, so the API
# reference works without internet: the files ship in the fastapi-offline package (MIT).
DOCS_ASSETS = Path(fastapi_offline.__file__).resolve().parent / "static"
DOCS_ASSETS_URL = "/docs-assets"


def install_offline_docs(app: FastAPI) -> None:
    """Serve ``/docs`` (Swagger UI) and ``/redoc`` (ReDoc) with their scripts under ``/docs-assets``."""
    app.mount(DOCS_ASSETS_URL, StaticFiles(directory=DOCS_ASSETS), name="docs-assets")
    title = app.title

    @app.get("/docs", include_in_schema=False)
    def get_swagger_ui(request: Request) -> HTMLResponse:
        root = request.scope.get("root_path", "")
        return get_swagger_ui_html(
            openapi_url=f"{root}{app.openapi_url}", title=f"{title} - Swagger UI",
            oauth2_redirect_url=f"{root}/docs/oauth2-redirect",
            swagger_js_url=f"{root}{DOCS_ASSETS_URL}/swagger-ui-bundle.js",
            swagger_css_url=f"{root}{DOCS_ASSETS_URL}/swagger-ui.css",
            swagger_favicon_url=f"{root}{DOCS_ASSETS_URL}/favicon.png")

    @app.get("/docs/oauth2-redirect", include_in_schema=False)
    def get_swagger_ui_redirect() -> HTMLResponse:
        return get_swagger_ui_oauth2_redirect_html()

    @app.get("/redoc", include_in_schema=False)
    def get_redoc(request: Request) -> HTMLResponse:
        root = request.scope.get("root_path", "")
        return get_redoc_html(
            openapi_url=f"{root}{app.openapi_url}", title=f"{title} - ReDoc",
            redoc_js_url=f"{root}{DOCS_ASSETS_URL}/redoc.standalone.js",
            redoc_favicon_url=f"{root}{DOCS_ASSETS_URL}/favicon.png", with_google_fonts=False)


def create_app(settings: Settings | None = None) -> FastAPI:
    """Build the app; artifacts load when its lifespan starts (uvicorn, or ``with TestClient(app)``)."""
    settings = settings or get_settings()
    # FastAPI's OpenTelemetry would add OTLP exporters when FASTAPI_OTEL_AUTO_CONFIGURE is set in
    # the environment: the service exports nothing unless its own code is told to.
    app = FastAPI(title="ComplementMe suggestion service", version=__version__, description=DESCRIPTION,
                  lifespan=lifespan, telemetry={"auto_configure": False}, docs_url=None, redoc_url=None)
    app.state.settings = settings
    app.state.metrics = Metrics()
    app.state.served = None
    app.state.ready = False
    app.state.uploads = MeshUploads(settings)
    # Starlette spools a form's file part to disk past a class-wide bound (1 MiB): for a few-MB
    # mesh most of the form's parse is that write and its read back. The uploads in reception
    # hold at most max_receiving_bytes together (the overload middleware's reception budget).
    # The bound is a process global, like the server it configures.
    MultiPartParser.spool_max_size = settings.upload_memory_bytes
    install_access_log_redaction()
    install_error_handlers(app)
    app.include_router(suggest.router)
    app.include_router(parts.router)
    app.include_router(probes.router)
    app.include_router(catalog_write.router)
    add_common_responses(app)
    add_limits(app, settings.limits)
    app.include_router(assemble.router)
    install_page(app)
    install_offline_docs(app)

    def model_version() -> str | None:
        served = served_of(app)
        return served.model_version if served is not None else None

    # Added last = outermost: metrics see every response, including a 413 from the body limit.
    app.add_middleware(OverloadMiddleware, max_inflight=settings.max_inflight, max_queue=settings.max_queue,
                       timeout=settings.request_timeout, max_inflight_writes=settings.max_inflight_writes,
                       max_inflight_suggest=settings.max_inflight_suggest,
                       refusal_delay=settings.overload_refusal_delay,
                       max_receiving_bytes=settings.max_receiving_bytes,
                       max_receiving_bytes_per_client=settings.max_receiving_bytes_per_client,
                       body_bound=partial(body_bound, max_body_bytes=settings.max_body_bytes,
                                          max_upload_bytes=settings.max_upload_bytes),
                       metrics=app.state.metrics)
    app.add_middleware(JsonBodyMiddleware, max_body_points=settings.max_body_points)
    app.add_middleware(BodyLimitMiddleware, max_body_bytes=settings.max_body_bytes,
                       max_upload_bytes=settings.max_upload_bytes,
                       body_read_timeout=settings.body_read_timeout)
    if settings.client_error_burst:
        # Outside the body checks (their refusals count as errors), inside CORS (a browser can
        # read the 429).
        app.add_middleware(ErrorBudgetMiddleware, rate=settings.client_error_rate,
                           burst=settings.client_error_burst,
                           refusal_delay=settings.overload_refusal_delay, metrics=app.state.metrics)
    if settings.cors_origins:  # browsers only; none by default
        app.add_middleware(JsonCorsMiddleware, allow_origins=settings.cors_origins,
                           allow_methods=["GET", "POST", "DELETE"],
                           allow_headers=["Authorization", "Content-Type"],
                           expose_headers=["X-Model-Version"])
    app.add_middleware(MetricsMiddleware, metrics=app.state.metrics, model_version=model_version)
    app.add_middleware(HeadAsGetMiddleware)
    return app
