"""FastAPI service: jobs, scenes, artifacts. Never imports torch."""
