"""Background jobs: submitting them, the queue (Huey) and its recovery, and the retraining a worker runs."""
