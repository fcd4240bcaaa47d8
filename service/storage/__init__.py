"""Persistence: SQLAlchemy models, the engine, migrations and the per-frame feature store."""
