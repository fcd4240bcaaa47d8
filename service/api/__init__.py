"""The HTTP layer: a thin FastAPI shell over :class:`service.atlas.catalog.AtlasService`."""
