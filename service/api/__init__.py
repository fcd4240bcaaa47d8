"""The HTTP layer: a thin FastAPI shell over :class:`service.app.catalog.AtlasService`."""
