"""The job queue (Huey): SQLite storage in the data directory, or Redis when configured."""
