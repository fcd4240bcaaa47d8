"""The FastAPI application factory; nothing heavy happens at import time."""

from __future__ import annotations

from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import FastAPI

from service import __version__
from service.api.errors import install_error_handlers
from service.api.routes import atlases, features, frames, health, jobs, queries
from service.config import Settings
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
    async def lifespan(_app: FastAPI) -> AsyncIterator[None]:
        runtime.start(background=background_load)
        try:
            yield
        finally:
            runtime.stop()

    app = FastAPI(
        title="LoopNet",
        version=__version__,
        description=DESCRIPTION,
        lifespan=lifespan,
    )
    app.state.runtime = runtime
    install_error_handlers(app)
    for router in (
        health.router,
        atlases.router,
        frames.router,
        features.router,
        queries.router,
        jobs.router,
    ):
        app.include_router(router, prefix="/v1")
    return app
