"""The FastAPI application factory: the stateless HTTP front of posemetry, mounting every room's routes.

The app holds no state of its own beyond an engine and a dispatcher, so any number of API processes can run
side by side. Everything it accepts goes to SQL first; the dispatcher only nudges workers.
"""

from __future__ import annotations

import functools
import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import TYPE_CHECKING

from fastapi import Depends, FastAPI
from sqlalchemy import Engine

from service import __version__
from service.calibration import routes as calibration
from service.calibration.service import DueSolves
from service.cameras import routes as cameras
from service.cameras.cache import CameraCache
from service.console import routes as console
from service.dispatch import Dispatcher, NullDispatcher
from service.distances import routes as distances
from service.frames import routes as frames
from service.frames.writer import FrameWriter
from service.health import metrics
from service.health import routes as health
from service.http.json_body import register_body_schemas
from service.http.keep_alive import RecycleConnections
from service.http.problems import PROBLEM_MEDIA_TYPE, PROBLEM_SCHEMA, BodyGuard, HeaderGuard, install_handlers
from service.http.query_params import known_query_only
from service.keys import routes as keys
from service.keys.authenticator import Authenticator
from service.keys.dependencies import AUTH_RESPONSE_DESCRIPTIONS, require_key
from service.keys.middleware import AuthenticateBeforeBody
from service.observability import redact
from service.observability.collectors import SharedStateCollector
from service.observability.http import RequestTelemetry
from service.observability.metrics import exposition_registry
from service.pictures import routes as pictures
from service.settings import Settings, get_settings
from service.store import make_engine, make_session_factory
from service.violations import routes as violations
from service.webhooks import routes as webhooks

if TYPE_CHECKING:
    from service.observability.queue_depths import QueueDepths

log = logging.getLogger(__name__)

DESCRIPTION = """Camera auto-calibration and physical distances from human pose.

Post people's keypoints per camera; the service calibrates each camera from the people it sees and reports how
far apart people stand, in metres, with a 1-sigma uncertainty. Every error is an RFC 9457
`application/problem+json` document.

Every route except `/healthz` and `/readyz` needs an API key: `Authorization: Bearer <key>` (401 without one).
Admin keys create keys with `POST /v1/keys`; a key may be limited to some cameras (403 for the others). This
documentation (`/docs`, `/redoc`, `/openapi.json`) is public: it describes the API and holds no data.
"""

PROBLEM_RESPONSES: dict[int | str, dict[str, object]] = {
    "4XX": {"description": "Problem details (RFC 9457)", "content": {PROBLEM_MEDIA_TYPE: {"schema": PROBLEM_SCHEMA}}},
    "5XX": {"description": "Problem details (RFC 9457)", "content": {PROBLEM_MEDIA_TYPE: {"schema": PROBLEM_SCHEMA}}},
}
AUTH_RESPONSES: dict[int | str, dict[str, object]] = {
    status: {"description": text, "content": {PROBLEM_MEDIA_TYPE: {"schema": PROBLEM_SCHEMA}}}
    for status, text in AUTH_RESPONSE_DESCRIPTIONS.items()
}
# Each room's routes, in the order the OpenAPI document lists them. Routers anyone may call: liveness and readiness,
# for load balancers and orchestrators that hold no key, and the operator console's page, which holds no data (its
# script reads the API with the operator's key).
PUBLIC_ROUTERS = (health, console)
ROUTERS = (cameras, frames, pictures, calibration, distances, violations, webhooks, keys, metrics, health, console)


def create_app(
    settings: Settings | None = None,
    *,
    dispatcher: Dispatcher | None = None,
    engine: Engine | None = None,
    queue_depths: QueueDepths | None = None,
) -> FastAPI:
    """Build the API. `dispatcher` hands work to the workers (the CLI passes the Redis one); without it frames
    are stored but nobody is told (NullDispatcher). `engine` defaults to one built from settings and disposed
    when the app shuts down; a passed engine stays the caller's. `queue_depths` reads the queues' depths for
    /metrics (the CLI passes one on the dispatcher's Redis)."""
    settings = settings or get_settings()
    owns_engine = engine is None
    if engine is None:
        engine = make_engine(settings.database_url, busy_timeout_s=settings.database_busy_timeout_s)
    if dispatcher is None:
        log.info("no dispatcher given: frames are stored but no worker is notified")
        dispatcher = NullDispatcher()

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        yield
        app.state.frame_writer.close()  # stores what was already posted
        app.state.camera_cache.close()
        if owns_engine:
            engine.dispose()

    app = FastAPI(
        title="posemetry",
        version=__version__,
        description=DESCRIPTION,
        lifespan=lifespan,
        responses=PROBLEM_RESPONSES,
        # FastAPI's built-in OpenTelemetry hooks cost a provider lookup per request even when nothing is
        # configured; the service reports its own metrics.
        telemetry={"tracing": False, "metrics": False, "logs": False},
    )
    app.state.settings = settings
    app.state.engine = engine
    app.state.session_factory = make_session_factory(engine)
    app.state.read_session_factory = make_session_factory(engine, read_only=True)
    due_solves = DueSolves(settings, app.state.read_session_factory, dispatcher)
    app.state.frame_writer = FrameWriter(
        app.state.session_factory, after_commit=functools.partial(frames.dispatch_stored, dispatcher, due_solves)
    )
    app.state.camera_cache = CameraCache(settings.camera_cache_ttl_s, app.state.read_session_factory)
    app.state.dispatcher = dispatcher
    app.state.authenticator = Authenticator(
        admin_key=None if settings.admin_key is None else settings.admin_key.get_secret_value(),
        read_sessions=app.state.read_session_factory,
        write_sessions=app.state.session_factory,
        cache_ttl_s=settings.api_key_cache_ttl_s,
    )
    shared_state = SharedStateCollector(app.state.read_session_factory, queue_depths)
    app.state.metrics_registry = exposition_registry([shared_state])
    install_handlers(app)
    redact.APP_SECRETS.add(settings.logged_secrets())
    app.add_middleware(
        BodyGuard,
        max_body_bytes=settings.max_body_bytes,
        uploads=(frames.upload_route(settings),),
        routes=app.router.routes,
    )
    # A body is not read for a caller without a key.
    public_paths = frozenset(route.path for module in PUBLIC_ROUTERS for route in module.router.routes)
    app.add_middleware(AuthenticateBeforeBody, authenticator=app.state.authenticator, public_paths=public_paths)
    app.add_middleware(HeaderGuard, max_header_bytes=settings.max_header_bytes)
    app.add_middleware(RecycleConnections, max_requests=settings.keep_alive_max_requests)
    # Added last, so outermost: what the key check and the body guard refuse is measured, logged and given a
    # request id too.
    app.add_middleware(RequestTelemetry, route_templates=lambda: app.openapi()["paths"])
    # Protected unless listed as public: a router added to ROUTERS later needs a key without anyone remembering.
    for module in ROUTERS:
        if module in PUBLIC_ROUTERS:
            app.include_router(module.router, dependencies=[Depends(known_query_only)])
        else:
            app.include_router(
                module.router, dependencies=[Depends(require_key), Depends(known_query_only)], responses=AUTH_RESPONSES
            )
    app.webhooks.include_router(webhooks.callbacks)
    register_body_schemas(app, frames.JSON_BODIES)
    return app
