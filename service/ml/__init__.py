"""The ML core: images, local and global features, fusion heads.

This package is a library: it imports torch, kornia, numpy and PIL only, never FastAPI or
SQLAlchemy, so the evaluation harness, the worker and the API share one code path.
"""
