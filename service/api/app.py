"""The FastAPI application factory; nothing heavy happens at import time."""

from __future__ import annotations

from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

import anyio.to_thread
from fastapi import FastAPI

from service import __version__
from service.api import metrics, slashes
from service.api.docs import install_offline_docs
from service.api.errors import install_error_handlers
from service.api.guard import RequestGuard
from service.api.host_guard import HostOriginGuard
from service.api.request_log import RequestLogMiddleware
from service.api.routes import (
    atlases,
    browse,
    features,
    frames,
    health,
    jobs,
    keys,
    loop_closures,
    queries,
    snapshots,
)
from service.api.security_headers import SecurityHeaders
from service.concurrency import default_workers, request_threads
from service.config import Settings
from service.console.router import install as install_console
from service.ml.pipeline import FeaturePipeline
from service.runtime import Runtime

DESCRIPTION = """
LoopNet recognises places for robots running SLAM. Robots POST camera frames into a shared
*map atlas* of submaps; a query frame returns the frame and submap it revisits, a cosine
similarity of LoopNet embeddings, and a loop-closure decision.
"""


def create_app(
    settings: Settings | None = None,
    *,
    pipeline: FeaturePipeline | None = None,
    background_load: bool = True,
) -> FastAPI:
    """Build the app; its lifespan migrates the database and loads the model.

    ``pipeline`` injects already loaded CNNs (the tests share one across apps).
    """
    runtime = Runtime(settings or Settings(), pipeline)

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        runtime.start(background=background_load)
        _size_thread_pool(runtime.settings)
        app.state.authenticator = runtime.authenticator
        app.state.authenticator.announce()
        try:
            yield
        finally:
            runtime.stop()

    app = FastAPI(
        title="LoopNet",
        version=__version__,
        description=DESCRIPTION,
        lifespan=lifespan,
        docs_url=None,  # served from the package's files, below: no CDN
        redoc_url=None,
    )
    app.state.runtime = runtime
    install_error_handlers(app)
    app.add_middleware(RequestGuard, settings=runtime.settings)
    install_offline_docs(app)
    routers = (
        health,
        atlases,
        frames,
        features,
        queries,
        jobs,
        keys,
        loop_closures,
        snapshots,
        browse,
    )
    for router in (module.router for module in routers):
        app.include_router(router, prefix="/v1")
    metrics.install(app)
    install_console(app)
    slashes.install(app.router)
    # outermost last: the log sees every answer, every answer gets the security headers, and
    # a foreign Host or origin is refused before authentication and the body
    app.add_middleware(HostOriginGuard, settings=runtime.settings)
    app.add_middleware(SecurityHeaders)
    app.add_middleware(RequestLogMiddleware, log_format=runtime.settings.log_format)
    return app


def _size_thread_pool(settings: Settings) -> None:
    """Give the synchronous routes enough threads that requests queued for inference never
    starve the others (the gate, not the thread pool, is what bounds inference)."""
    workers = settings.inference_workers or default_workers(settings.torch_threads)
    limiter = anyio.to_thread.current_default_thread_limiter()
    limiter.total_tokens = max(
        limiter.total_tokens, request_threads(workers, settings.inference_queue)
    )
