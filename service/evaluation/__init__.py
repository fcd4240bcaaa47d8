"""The evaluation harness: datasets in the layouts users have, the paper's protocol, Recall@K,
precision-recall, ablations and classical baselines, in one report (``loopnet eval``).

It drives the same :class:`~service.app.catalog.AtlasService` code path as the HTTP API.
"""
