"""The worker process entry point (``python -m workers``); the jobs live in service.jobs."""
