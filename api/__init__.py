"""FastAPI service: scenes, jobs, artifacts. Imports `service` (the core), never `worker` or torch."""
