"""Running a fleet of robots and replicas: API keys and atlas snapshots."""
