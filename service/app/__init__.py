"""Atlases as the application sees them: the catalog, the loaded state of each atlas, ingest,
queries with verification, filters, the change feed and the loop closures recorded between robots."""
