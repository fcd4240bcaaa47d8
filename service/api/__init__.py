"""The HTTP layer: a thin FastAPI shell over :class:`service.atlas_service.AtlasService`."""
